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

pytest.importorskip("distributed", reason="the cluster extra (pip install -e '.[cluster]') is not installed")

KW = dict(width=8, spp=(1, 2), instances=1, ref_spp=4, progress=False, max_depth=3)


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.exr"))}


def _scenes(m: dict) -> dict:
    """The manifest's scenes without what legitimately differs between runs (timings)."""
    drop = ("seconds", "compile_seconds", "gradient_seconds", "render_seconds")

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
    assert not list((tmp_path / "d").rglob(".attempts-*"))


@pytest.mark.mitsuba
def test_a_worker_dying_mid_shot_costs_only_that_shot(serial, tmp_path):
    out_s, _ = serial
    marker = tmp_path / "died"
    m = data_gen.generate_dataset("mixed", 4, tmp_path / "d", scheduler="local:2", _die_once=str(marker), **KW)
    assert marker.exists()  # a worker did die (after writing one file of its shot)
    assert m["runs"][-1]["retries"] >= 1
    assert _files(tmp_path / "d") == _files(out_s)  # complete and correct all the same


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

    with pytest.raises(ImportError, match=r"install the cluster extra: pip install -e '\.\[cluster\]'"):
        cluster.connect("local:1")
