import json

import numpy as np
import pytest

from jaxdenoise import bench, data as jdata
from jaxdenoise.cli import main

from conftest import make_shot, registered, synthetic_frame


@pytest.fixture
def data(tmp_path):
    root = tmp_path / "data"
    for s in range(2):
        ref = synthetic_frame(h=16, w=16, seed=100 + s).color
        renders = {spp: synthetic_frame(h=16, w=16, seed=10 * s + spp, fields=("color", "albedo", "normal"))
                   for spp in ((4, 16) if s == 0 else (4,))}
        (root / f"scene_{s:04d}").mkdir(parents=True)
        make_shot(root / f"scene_{s:04d}", ref, renders)
    return root


def test_discover_layout(data):
    shots = jdata.discover(data)
    assert [s.name for s in shots] == ["scene_0000", "scene_0001"]
    assert [r.spp for r in shots[0].renders] == [4, 16]
    assert shots[0].renders[1].render_seconds == pytest.approx(0.16, rel=1e-6)


def test_discover_follows_linked_shot_folders(data, tmp_path):
    # a selection of shots linked into a folder of its own (as experiments/lbf_train.py does)
    sel = tmp_path / "selection"
    sel.mkdir()
    (sel / "scene_0001").symlink_to(data / "scene_0001")
    assert [s.name for s in jdata.discover(sel)] == ["scene_0001"]


def test_bench_writes_three_reports(data, tmp_path):
    out = tmp_path / "report"
    report = bench.run(data, ["input", "gaussian"], out, runs=5, progress=False)
    assert len(report["records"]) == 3 * 2  # one record per render x method
    for name in ("results.json", "results.md", "error_vs_time.png", "config.json"):
        assert (out / name).stat().st_size > 0
    res = json.loads((out / "results.json").read_text())
    rec = res["records"][0]
    for key in ("relmse", "ssim", "psnr", "seconds", "compile_seconds", "rss_peak_bytes", "xla_bytes", "spp", "method"):
        assert key in rec
    assert all(len(r["seconds_all"]) == 5 for r in res["records"])
    inp = [r for r in res["records"] if r["method"] == "input"]
    assert all(r["compile_seconds"] >= 0 and r["rss_peak_bytes"] >= 0 for r in res["records"])
    # one quantity per column: XLA's estimate only for jitted methods, measured RSS growth for all
    assert all(r["xla_bytes"] > 0 for r in res["records"])  # input and gaussian are both jitted
    # relmse of the raw input recomputed independently with NumPy (tolerance: float32 rounding)
    from jaxdenoise.io import read_image
    x = read_image(data / inp[0]["file"])
    ref = read_image(data / "scene_0000" / "reference.exr")
    want = np.mean((x - ref) ** 2 / (ref ** 2 + 0.01))
    assert inp[0]["relmse"] == pytest.approx(want, rel=1e-5)
    md = (out / "results.md").read_text()
    assert "| gaussian | 4 | 2 |" in md and "| input | 16 | 1 |" in md


def test_bench_records_what_cannot_run(data, tmp_path):

    with registered("gauss-needs-dx", "fake_needs_dx"):
        report = bench.run(data, ["input", "gauss-needs-dx"], tmp_path / "r", runs=5, progress=False)
    assert len(report["records"]) == 3
    assert {s["reason"] for s in report["skipped"]} == {"frame lacks buffer(s) ['dx']"}
    assert "frame lacks buffer(s) ['dx']" in (tmp_path / "r" / "results.md").read_text()


def test_bench_protocol_and_errors(data, tmp_path):
    with pytest.raises(ValueError, match="runs=2; the protocol needs at least 5"):
        bench.run(data, ["input"], tmp_path / "r", runs=2, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no shot found"):
        bench.run(tmp_path / "empty", ["input"], tmp_path / "r", progress=False)


def test_cli_bench_and_denoise(data, tmp_path, capsys):
    assert main(["bench", str(data), "--methods", "input,gaussian", "--out", str(tmp_path / "cli"), "--quiet"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("bench: 6 record(s), 2 shot(s), 2 method(s)")
    src = data / "scene_0000" / "spp0004_00.exr"
    assert main(["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--method", "gaussian"]) == 0
    assert (tmp_path / "o.config.json").is_file()
    assert capsys.readouterr().out.startswith("denoise: spp0004_00.exr ->")
    assert main(["denoise", str(src), "-o", str(tmp_path / "o2.exr"), "--method", "nope"]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err
