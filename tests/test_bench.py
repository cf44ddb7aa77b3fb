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


def test_cli_errors_one_line_for_bad_input_a_traceback_for_bugs(data, tmp_path, capsys, monkeypatch):
    """Input the library refuses (`JaxdenoiseError`, a missing file) is one ``error:`` line and exit
    code 2; any other exception is a bug and propagates with its traceback; ``--debug`` lets the
    bad-input error propagate too."""
    from jaxdenoise.errors import JaxdenoiseError
    from jaxdenoise.methods import MethodError

    src = data / "scene_0000" / "spp0004_00.exr"
    bad = ["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--method", "nope"]
    assert main(bad) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: unknown method 'nope'") and len(err.strip().splitlines()) == 1
    assert main(["denoise", str(tmp_path / "missing.exr"), "-o", str(tmp_path / "o.exr")]) == 2
    assert "missing.exr" in capsys.readouterr().err
    with pytest.raises(MethodError, match="unknown method"):
        main(["--debug"] + bad)
    assert issubclass(MethodError, JaxdenoiseError)

    def bug(*a, **k):
        raise ValueError("an internal bug")  # not the project's error type

    monkeypatch.setattr("jaxdenoise.inference.prepare", bug)
    with pytest.raises(ValueError, match="an internal bug"):
        main(["denoise", str(src), "-o", str(tmp_path / "o3.exr"), "--method", "gaussian"])


def test_records_say_which_buffers_a_method_read_and_what_it_ran_without(tmp_path, capsys):
    """A method that can use albedo, on a 4-spp row mixing a frame with albedo and one without: each
    record lists the buffers read and, for the second, a note; the row counts the frames the note
    concerns; the table, the viewer, the API (a `JaxdenoiseWarning`) and the CLI (a warning line)
    say so too."""
    import warnings

    import jaxdenoise as jd
    from jaxdenoise.errors import JaxdenoiseWarning

    root = tmp_path / "data"
    for s, fields in enumerate((("color", "albedo"), ("color",))):
        (root / f"scene_{s:04d}").mkdir(parents=True)
        make_shot(root / f"scene_{s:04d}", synthetic_frame(16, 16, seed=1).color,
                  {4: synthetic_frame(16, 16, seed=2 + s, fields=fields)})
    note = "uses-albedo ran without optional buffer(s) ['albedo'] it can use"
    with registered("uses-albedo", "fake_optional_albedo"):
        report = bench.run(root, ["uses-albedo"], tmp_path / "r", runs=5, progress=False)
        recs = sorted(report["records"], key=lambda r: r["shot"])
        assert [r["buffers"] for r in recs] == [["albedo", "color"], ["color"]]  # exact
        assert [r["notes"] for r in recs] == [[], [note]]
        row = bench.summarize(report["records"])[0]
        assert row["notes"] == [f"{note} (1 of 2 frame(s))"] and row["buffers"] == ["albedo", "color"]
        assert f"{note} (1 of 2 frame(s))" in (tmp_path / "r" / "results.md").read_text()
        assert note in (tmp_path / "r" / "viewer.html").read_text()
        bare = synthetic_frame(16, 16, seed=3, fields=("color",))
        with pytest.warns(JaxdenoiseWarning, match=r"ran without optional buffer\(s\) \['albedo'\]"):
            jd.denoise(bare, method="uses-albedo")
        with warnings.catch_warnings():
            warnings.simplefilter("error", JaxdenoiseWarning)
            jd.denoise(synthetic_frame(16, 16, seed=3, fields=("color", "albedo")), method="uses-albedo")
        src = root / "scene_0001" / "spp0004_00.exr"
        assert main(["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--method", "uses-albedo"]) == 0
        assert f"warning: {note}" in capsys.readouterr().err


def test_each_method_is_charged_the_passes_that_made_what_it_read(tmp_path):
    """A gradient frame (0.5 s in all; a buffer-only render of it 0.13 s): a plain method pays the
    buffer render, a gradient method the frame; with the G-PT primal as colour, the plain method
    pays the frame too. A two-pass record of before 0.8.2 (``gradient_seconds`` 0.37 of 0.5 s) reads
    the same."""
    from jaxdenoise.io import write_buffers, write_image

    ref = synthetic_frame(16, 16, seed=1).color
    frame = synthetic_frame(16, 16, seed=2, fields=("color", "dx", "dy")).replace(spp=np.float32(4))
    for primal, plain_time, timing in (("base", 0.13, {"buffer_seconds": 0.13}), ("gpt", 0.5, {"buffer_seconds": 0.13}),
                                       ("base", 0.13, {"gradient_seconds": 0.37})):
        name = f"{primal}_{next(iter(timing))}"
        shot = tmp_path / name / "scene_0000"
        shot.mkdir(parents=True)
        write_image(shot / "reference.exr", ref)
        write_buffers(shot / "spp0004_00.exr", frame, {"render_seconds": 0.5, "primal": primal, **timing})
        report = bench.run(tmp_path / name, ["input", "poisson-l2"], tmp_path / f"r_{name}", runs=5, progress=False)
        got = {r["method"]: r for r in report["records"]}
        assert got["input"]["render_seconds"] == pytest.approx(plain_time)
        assert got["poisson-l2"]["render_seconds"] == pytest.approx(0.5)
        assert [r["frame_render_seconds"] for r in got.values()] == [pytest.approx(0.5)] * 2
        # every record carries the raw input's error on its frame: the input method's own score
        assert got["poisson-l2"]["input_relmse"] == pytest.approx(got["input"]["relmse"], rel=1e-6)
    render = jdata.Render(tmp_path / "x.exr", 4, None, 0.13, None)
    assert bench.charged_render_seconds(render, ["color"]) is None  # unknown stays unknown


def test_table_shows_the_input_error_and_flags_a_method_that_made_it_worse():
    rows = [{"method": m, "spp": 4, "frames": 1, "relmse": e, "input_relmse": 0.5, "ssim": 0.5, "psnr": 20.0,
             "seconds": 0.01, "compile_seconds": 0.1, "rss_peak_mb": 1.0, "xla_mb": 1.0, "notes": []}
            for m, e in (("good", 0.05), ("bad", 1.5))]
    md = bench.markdown_table(rows)
    assert "| good | 4 | 1 | 0.05 | 0.5 | 0.1x |" in md
    assert "| bad | 4 | 1 | 1.5 | 0.5 | **3x: worse** |" in md


def test_plot_styles_differ_for_every_method():
    names = [f"m{i}" for i in range(40)]
    styles = bench.plot_styles(names)
    pairs = {(s["color"], s["marker"]) for s in styles.values()}
    assert len(pairs) == len(names)
    assert len({styles[n]["color"] for n in names[:20]}) == 20  # the first 20 also differ in colour alone


def test_report_paths_never_carry_this_machines_absolute_paths(tmp_path, monkeypatch):
    """Reports write a path relative to the report when both live in one tree (a repository), and
    a cache under the home directory as ``~/...`` when the report is elsewhere (the demo's case)."""
    from jaxdenoise.fsutil import report_path

    home, repo = tmp_path / "home", tmp_path / "work" / "repo"
    monkeypatch.setenv("HOME", str(home))
    cache, out = home / ".cache" / "jaxdenoise" / "demo", repo / "docs" / "results" / "demo"
    assert report_path(cache, out) == "~/.cache/jaxdenoise/demo"
    assert report_path(repo / "data" / "heldout", out) == "../../../data/heldout"
    assert report_path(home / "proj" / "data", home / "proj" / "docs") == "../data"  # a repository under ~
    assert report_path(cache) == "~/.cache/jaxdenoise/demo"
