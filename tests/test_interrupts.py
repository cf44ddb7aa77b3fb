"""Interrupted work resumed (reliability issue): `python -m data_gen dataset`, training and `bench`
are killed with SIGKILL at random moments, then run again. No half-written file is ever visible
under its final name, and the resumed result equals an uninterrupted run (datasets bit for bit,
weights within a stated tolerance). The dataset case in the default suite; training and bench, and
several kill moments of each, under `slow`."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT / "tests") + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _kill_when(cmd: list[str], ready, cwd=ROOT) -> int | None:
    """Start ``cmd``, SIGKILL it as soon as ``ready()`` holds (None if it finished first: its return
    code). A moment set by the run's progress, not by a wall time measured on another run (a second
    run can be much faster than the first: warm caches)."""
    p = subprocess.Popen(cmd, cwd=cwd, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while p.poll() is None:
            if ready():
                p.send_signal(signal.SIGKILL)
                p.wait()
                return None
            time.sleep(0.002)
        return p.returncode
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def _kill_at_file(cmd: list[str], folder: Path, n: int, cwd=ROOT) -> int | None:
    """`_kill_when` ``folder`` holds ``n`` finished EXR files."""
    return _kill_when(cmd, lambda: folder.is_dir() and sum(not f.name.startswith(".")
                                                              for f in folder.rglob("*.exr")) >= n, cwd)


def _checkpoint_step(run: Path) -> int:
    """The step of ``run``'s checkpoint (-1 before the first; the file is replaced atomically)."""
    try:
        return int(json.loads((run / "checkpoint" / "config.json").read_text())["step"])
    except (FileNotFoundError, json.JSONDecodeError, KeyError):
        return -1


def _run(cmd: list[str], env=ENV) -> float:
    """Run ``cmd`` to completion (it must succeed); returns its wall time."""
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    return time.perf_counter() - t0


def _exr_files(folder: Path) -> dict[str, bytes]:
    """Every EXR under ``folder``, temporaries (dot files) included: a resumed run must leave none."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.exr"))}


def _all_complete(folder: Path) -> None:
    """Every file under its final name reads completely (EXR) or parses (JSON). Temporaries (dot
    files: `fsutil.atomic_path`) may be partial; the next run removes them."""
    from jaxdenoise.io import read_buffers

    for p in folder.rglob("*.exr"):
        if not p.name.startswith("."):
            read_buffers(p)
    for p in folder.rglob("*.json"):
        if not p.name.startswith("."):
            json.loads(p.read_text())


DATASET = [sys.executable, "-m", "data_gen", "dataset", "--family", "mixed", "--count", "2", "--res", "8",
           "--spp", "1,2", "--instances", "2", "--ref-spp", "4", "--max-depth", "3", "--no-progress"]


@pytest.fixture(scope="module")
def dataset_reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("full") / "d"
    return out, _run(DATASET + ["--out", str(out)])


def _dataset_case(tmp_path, reference, fraction):
    """Killed once ``fraction`` of the reference run's EXR files exist (at least one, one short of
    all), resumed, compared bit for bit."""
    ref_dir, _ = reference
    total = len(_exr_files(ref_dir))
    out = tmp_path / f"d_{fraction:.2f}"
    rc = _kill_at_file(DATASET + ["--out", str(out)], out, min(total - 1, max(1, round(fraction * total))))
    assert rc is None, "the run finished before the kill; the case tests nothing"
    if out.exists():
        _all_complete(out)  # nothing half-written under a final name
    _run(DATASET + ["--out", str(out)])
    assert _exr_files(out) == _exr_files(ref_dir)  # bit for bit


@pytest.mark.mitsuba
def test_dataset_killed_and_resumed_is_identical(tmp_path, dataset_reference):
    _dataset_case(tmp_path, dataset_reference, 0.7)


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_dataset_killed_at_random_moments(tmp_path, dataset_reference, seed):
    _dataset_case(tmp_path, dataset_reference, float(np.random.default_rng(seed).uniform(0.4, 0.8)))


TRAIN = """
import sys
from test_train import CFG
from conftest import fit
fit("lbf", sys.argv[1], sys.argv[2], steps=12, config=CFG, progress=False, checkpoint_every=1,
    resume=True, optimizer="adam", learning_rate=1e-2)
"""


@pytest.fixture(scope="module")
def train_data(tmp_path_factory):
    from test_train import write_rooms

    return write_rooms(tmp_path_factory.mktemp("rooms"))


def _train_case(tmp_path, data, fraction):
    """Killed once the run's checkpoint reached ``fraction`` of its 12 steps (between 1 and 11:
    `checkpoint_every=1`), resumed, compared with an uninterrupted run."""
    full, part = tmp_path / "full", tmp_path / f"part_{fraction:.2f}"
    cmd = [sys.executable, "-c", TRAIN, str(data)]
    _run(cmd + [str(full)])
    at = min(11, max(1, round(fraction * 12)))
    assert _kill_when(cmd + [str(part)], lambda: _checkpoint_step(part) >= at) is None, "finished before the kill"
    assert at <= _checkpoint_step(part) < 12, "killed, but not in the middle of the run"
    if part.exists():
        _all_complete(part)
        from jaxdenoise import checkpoint

        if (part / "checkpoint" / "params.npz").exists():
            checkpoint.load(part / "checkpoint")  # a complete, loadable checkpoint
    _run(cmd + [str(part)])
    from jaxdenoise import checkpoint

    a, _ = checkpoint.load(full / "weights")
    b, _ = checkpoint.load(part / "weights")
    import jax

    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        # the same batches and updates from the last checkpoint: equal up to float32 rounding
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)


@pytest.mark.slow
def test_training_killed_and_resumed_matches(tmp_path, train_data):
    _train_case(tmp_path, train_data, 0.8)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_training_killed_at_random_moments(tmp_path, train_data, seed):
    _train_case(tmp_path, train_data, float(np.random.default_rng(seed).uniform(0.5, 0.9)))


@pytest.mark.slow
def test_bench_killed_leaves_no_half_written_report(tmp_path):
    """Killed while scoring or writing, bench leaves either no report file or a complete one."""
    from conftest import make_shot, synthetic_frame

    data = tmp_path / "data"
    (data / "scene_0000").mkdir(parents=True)
    make_shot(data / "scene_0000", synthetic_frame(16, 16, seed=1).color,
              {4: synthetic_frame(16, 16, seed=2), 16: synthetic_frame(16, 16, seed=3)})
    cmd = [sys.executable, "-m", "jaxdenoise.cli", "bench", str(data), "--methods", "input,gaussian", "--quiet"]
    report = tmp_path / "r"
    _run(cmd + ["--out", str(report)])
    _all_complete(report)
    # Kill moments set by the run's own progress (never a fraction of another run's wall time: a run
    # can be much faster than the one timed): while scoring (its report folder made, nothing in it),
    # while writing a new report (its first file, temporary or final, has appeared: the plot is
    # still to come), and while writing over a complete one (a temporary file in it, or its
    # results.json replaced: again before the plot).
    before = (report / "results.json").stat().st_mtime_ns

    def rewriting() -> bool:
        try:
            replaced = (report / "results.json").stat().st_mtime_ns != before
        except FileNotFoundError:
            replaced = True
        return replaced or any(f.name.startswith(".") for f in report.iterdir())

    moments = {tmp_path / "scoring": lambda f: f.is_dir(),
               tmp_path / "writing": lambda f: f.is_dir() and any(f.iterdir()),
               report: lambda f: rewriting()}
    for out, ready in moments.items():
        assert _kill_when(cmd + ["--out", str(out)], lambda: ready(out)) is None, \
            f"bench finished before the kill ({out.name})"
        if out.exists():
            _all_complete(out)
    _run(cmd + ["--out", str(report)])
    assert json.loads((report / "results.json").read_text())["records"]
