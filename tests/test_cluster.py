"""data_gen on Dask (`data_gen.cluster`): a local cluster of 2 single-threaded workers writes the same
dataset as the serial writer; a worker that dies mid-shot costs only that shot, which runs again;
an interrupted client resumes; without Dask, a clear error names the extra."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import data_gen

pytest.importorskip("distributed", reason="the cluster extra (pip install 'jaxdenoise[cluster]') is not installed")

KW = dict(width=8, spp=(1, 2), instances=1, ref_spp=4, progress=False, max_depth=3)


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.exr"))}


def _scenes(m: dict) -> dict:
    """The manifest's scenes without what legitimately differs between runs (timings)."""
    drop = ("seconds", "compile_seconds", "buffer_seconds", "render_seconds")

    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items() if k not in drop}
        return x

    return clean(m["scenes"])


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "d"
    return out, data_gen.generate_dataset("mixed", 4, out, **KW)


@pytest.mark.mitsuba
def test_local_cluster_writes_the_serial_dataset(serial, tmp_path):
    out_s, m_s = serial
    m = data_gen.generate_dataset("mixed", 4, tmp_path / "d", scheduler="local:2", **KW)
    assert _files(tmp_path / "d") == _files(out_s)  # bit-identical EXRs
    assert _scenes(m) == _scenes(m_s)
    run = m["runs"][-1]
    assert run["scheduler"] == "local:2" and run["workers"] == 2 and run["retries"] == 0
    assert run["drjit_threads"] == 1  # single-threaded workers render with one Dr.Jit thread
    assert not list((tmp_path / "d").rglob(".attempts-*"))


@pytest.mark.mitsuba
def test_a_worker_dying_mid_shot_costs_only_that_shot(serial, tmp_path):
    out_s, _ = serial
    marker = tmp_path / "died"
    m = data_gen.generate_dataset("mixed", 4, tmp_path / "d", scheduler="local:2", _die_once=str(marker), **KW)
    assert marker.exists()  # a worker did die (after writing one file of its shot)
    assert m["runs"][-1]["retries"] >= 1
    assert _files(tmp_path / "d") == _files(out_s)  # complete and correct all the same


@pytest.mark.slow
@pytest.mark.mitsuba
def test_interrupted_client_resumes(serial, tmp_path):
    out_s, _ = serial
    out = tmp_path / "d"
    cmd = [sys.executable, "-m", "data_gen", "dataset", "--family", "mixed", "--count", "4", "--res", "8",
           "--spp", "1,2", "--ref-spp", "4", "--max-depth", "3", "--no-progress", "--scheduler", "local:2",
           "--out", str(out)]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(out.rglob("*.exr"))) < 3:
        time.sleep(0.2)
    os.killpg(p.pid, signal.SIGKILL)  # the client and its local cluster
    p.wait()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Dask local:2: 2 worker(s)" in r.stdout
    assert _files(out) == _files(out_s)
    m = json.loads((out / "manifest.json").read_text())
    assert [x["status"] for x in m["runs"]] == ["running", "finished"]  # the interrupted run is listed


def test_without_dask_the_error_names_the_extra(monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "distributed" or name.startswith("distributed."):
            raise ImportError("No module named 'distributed'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    from data_gen import cluster

    with pytest.raises(ImportError, match=r"install the cluster extra: pip install 'jaxdenoise\[cluster\]' "
                                               r"\(from a clone: pip install -e '\.\[cluster\]'\)"):
        cluster.connect("local:1")


@pytest.mark.slow
def test_bench_scores_on_dask_equal_local_scores(tmp_path):
    """`bench --scheduler local:2`: the quality columns computed by the workers equal a local run's
    (tolerance 1e-6 relative: the same programs on the same inputs); timings come from the client
    alone afterwards, as the report says; --no-timing gives quality only."""
    from conftest import make_shot, synthetic_frame

    from jaxdenoise import bench

    data = tmp_path / "data"
    for s in range(2):
        (data / f"scene_{s:04d}").mkdir(parents=True)
        make_shot(data / f"scene_{s:04d}", synthetic_frame(16, 16, seed=100 + s).color,
                  {4: synthetic_frame(16, 16, seed=s, fields=("color", "albedo", "normal")),
                   16: synthetic_frame(16, 16, seed=10 + s, fields=("color", "albedo", "normal"))})
    local = bench.run(data, ["input", "gaussian"], tmp_path / "local", runs=5, progress=False)
    dist = bench.run(data, ["input", "gaussian"], tmp_path / "dask", runs=5, progress=False, scheduler="local:2")
    key = lambda r: (r["file"], r["method"])
    a = {key(r): r for r in local["records"]}
    b = {key(r): r for r in dist["records"]}
    assert set(a) == set(b)
    for k in a:
        for m in ("relmse", "ssim", "psnr"):
            assert b[k][m] == pytest.approx(a[k][m], rel=1e-6)
        assert b[k]["seconds"] > 0  # timed on the client
    assert dist["config"]["dask_workers"] == 2 and "after the distributed scoring" in dist["config"]["timing"]
    q = bench.run(data, ["input", "gaussian"], tmp_path / "q", runs=5, progress=False, scheduler="local:2",
                  timing=False)
    assert all(r["seconds"] is None for r in q["records"]) and not (tmp_path / "q" / "error_vs_time.png").exists()
    assert "No `error_vs_time.png`" in (tmp_path / "q" / "results.md").read_text()


@pytest.mark.slow
@pytest.mark.mitsuba
def test_dask_cli_recipe_on_localhost(serial, tmp_path):
    """The documented recipe: a scheduler and a worker started with the `dask` CLI, then
    `--scheduler tcp://127.0.0.1:PORT` (docs/data_gen.md)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    addr = f"tcp://127.0.0.1:{port}"
    sched = subprocess.Popen(["dask", "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    work = subprocess.Popen(["dask", "worker", addr, "--nthreads", "1", "--nworkers", "2", "--no-dashboard"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        import distributed

        with distributed.Client(addr, timeout=60) as c:
            c.wait_for_workers(2, timeout=60)
        m = data_gen.generate_dataset("mixed", 4, tmp_path / "d", scheduler=addr, **KW)
    finally:
        work.terminate()
        sched.terminate()
        work.wait(30)
        sched.wait(30)
    assert m["runs"][-1]["workers"] == 2
    assert _files(tmp_path / "d") == _files(serial[0])
