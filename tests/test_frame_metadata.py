"""Per-frame metadata (spp) survives every path, and the one sequence driver (issue: LBF sees the
frame's real spp at inference).

`lbf` reads spp (the inverse-spp secondary feature and the per-sample standard deviations): it runs
through `denoise`, `load`, `bench`, the CLI and training validation on a frame written to EXR at
4 spp, and each must equal a direct `lbf.apply` on that frame with spp = 4. Before the fix, `prepare`
dropped spp and lbf silently used 1; `test_spp_changes_lbf_output` shows that this difference is
far above the tolerances used here, so these tests fail on the old code.
"""
from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

import jaxdenoise as jd
from jaxdenoise import bench, checkpoint, metrics
from jaxdenoise.inference import prepare
from jaxdenoise.buffers import BuffersError, map_frames, stack
from jaxdenoise.cli import main
from jaxdenoise.io import read_buffers, read_image
from jaxdenoise.methods import get, lbf
from jaxdenoise.sequence import run, run_all

from conftest import make_shot, registered, synthetic_frame

# Small LBF (3x3 window, no prefilter) with non-trivial normalization: compiles in seconds.
CFG = lbf.Config(radius=1, prefilter=False, features=("normal", "albedo"), temporal_radius=1)
# Tolerance between paths: all run the same jitted float32 program, up to fusion differences.
TOL = 1e-5


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("w")
    params = lbf.init(jax.random.PRNGKey(3), CFG)
    n = params["norm"]["mean"].shape[0]
    # The inverse-spp feature is the last secondary feature; give the network a real dependence on it.
    params["norm"] = {"mean": np.linspace(-0.5, 0.5, n).astype(np.float32),
                      "std": np.linspace(0.2, 0.4, n).astype(np.float32)}
    checkpoint.save(folder, params, CFG)
    return folder, jax.tree_util.tree_map(np.asarray, params)


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    frame = synthetic_frame(16, 16, seed=7, fields=("color", "color_var", "normal", "normal_var", "albedo",
                                                    "albedo_var"))
    (root / "scene_0000").mkdir()
    make_shot(root / "scene_0000", synthetic_frame(16, 16, seed=8).color, {4: frame})
    return root


def _direct(params, path, spp):
    b, _ = read_buffers(path)
    return np.asarray(lbf.apply(params, b.replace(spp=np.float32(spp)), CFG))


def test_spp_changes_lbf_output(shot, weights):
    _, params = weights
    path = shot / "scene_0000" / "spp0004_00.exr"
    assert read_buffers(path)[0].spp == 4  # the header's spp, read back exactly
    diff = np.abs(_direct(params, path, 4) - _direct(params, path, 1)).max()
    assert diff > 100 * TOL, diff  # what dropping spp used to cost


def test_prepare_and_only_keep_spp():
    b = synthetic_frame(spp=4)
    assert b.only(()).spp == 4 and "spp" in b.only(()).present()
    assert prepare(get("gaussian"), b).spp == 4 and prepare(get("lbf"), b).spp == 4
    seq = stack([synthetic_frame(seed=i, spp=4 * (i + 1)) for i in range(3)])
    np.testing.assert_array_equal(seq.spp, [4, 8, 12])  # one per frame, exact
    assert map_frames(lambda f: f.color * f.spp, seq).shape == seq.color.shape


def test_denoise_and_load_see_the_file_spp(shot, weights):
    folder, params = weights
    path = shot / "scene_0000" / "spp0004_00.exr"
    want = _direct(params, path, 4)
    b, _ = read_buffers(path)
    np.testing.assert_allclose(jd.denoise(b, method="lbf", weights=folder), want, atol=TOL)
    infer = jd.load("lbf", folder)
    np.testing.assert_allclose(np.asarray(infer(b)), want, atol=TOL)


def test_bench_sees_the_file_spp(shot, weights, tmp_path):
    folder, params = weights
    path = shot / "scene_0000" / "spp0004_00.exr"
    want = _direct(params, path, 4)
    ref = read_image(shot / "scene_0000" / "reference.exr")
    report = bench.run(shot, ["lbf"], tmp_path / "r", runs=5, weights={"lbf": str(folder)}, progress=False)
    rec = report["records"][0]
    assert rec["relmse"] == pytest.approx(float(metrics.relmse(want, ref)), rel=1e-4)
    # no absolute machine path in the report: the data folder is relative to it
    cfg = json.loads((tmp_path / "r" / "config.json").read_text())
    assert not cfg["data_dir"].startswith("/") and (tmp_path / "r" / cfg["data_dir"]).resolve() == shot.resolve()


def test_cli_sees_the_file_spp(shot, weights, tmp_path):
    folder, params = weights
    path = shot / "scene_0000" / "spp0004_00.exr"
    out = tmp_path / "o.exr"
    assert main(["denoise", str(path), "-o", str(out), "--method", "lbf", "--weights", str(folder)]) == 0
    np.testing.assert_allclose(read_image(out), _direct(params, path, 4), atol=TOL)


def test_training_validation_sees_the_file_spp(shot, weights):
    from jaxdenoise.train import load_validation, validate

    folder, params = weights
    m = dataclasses.replace(get("lbf"), config=CFG)
    frames = load_validation(m, shot)
    assert frames[0]["buffers"].spp == 4
    want = _direct(params, shot / "scene_0000" / "spp0004_00.exr", 4)
    score = validate(m, params, frames)
    assert score["relmse"] == pytest.approx(float(metrics.relmse(want, frames[0]["reference"])), rel=1e-4)


def test_frame_without_spp_is_refused_by_name(shot, tmp_path, weights):
    folder, _ = weights
    b = synthetic_frame(8, 8, spp=None)
    with pytest.raises(BuffersError, match=r"method 'lbf' needs the frame's \['spp'\]"):
        jd.denoise(b, method="lbf", weights=folder)
    from jaxdenoise.io import write_buffers

    p = write_buffers(tmp_path / "nospp.exr", b)
    rc = main(["denoise", str(p), "-o", str(tmp_path / "x.exr"), "--method", "lbf", "--weights", str(folder)])
    assert rc == 2  # clear error, file named (checked through prepare's message below)
    with pytest.raises(BuffersError, match=r"nospp\.exr: method 'lbf' needs the frame's \['spp'\]"):
        prepare(get("lbf"), read_buffers(p)[0], where=str(p))
    # a method that does not read spp runs without it
    assert jd.denoise(b, method="gaussian").shape == (8, 8, 3)


# -- the sequence driver ---------------------------------------------------------------------------

def _write_sequence(folder, frames, refs):
    """``folder/frame_XXXX/{reference,spp0004_00}.exr`` for each frame (the bench layout of a video)."""
    from jaxdenoise.io import write_buffers, write_image

    for i, (f, r) in enumerate(zip(frames, refs)):
        d = folder / f"frame_{i:04d}"
        d.mkdir(parents=True)
        write_image(d / "reference.exr", r)
        write_buffers(d / "spp0004_00.exr", f)


def _frames(n=5, spp=4):
    return [synthetic_frame(12, 12, seed=i, spp=spp) for i in range(n)]


def test_windowed_driver_emits_frame_t_once_t_plus_ahead_has_arrived(weights, monkeypatch):
    """Streaming: frame t leaves the driver when frame t+1 (the look-ahead of CFG) has been read,
    the last frames when the stream ends; O(T): each frame is prepared exactly once."""
    _, params = weights
    m = dataclasses.replace(get("lbf"), config=CFG)
    consumed = []

    def source():
        for i, f in enumerate(_frames()):
            consumed.append(i)
            yield f

    seen_at = [len(consumed) for _ in run(m, params, source())]
    assert seen_at == [2, 3, 4, 5, 5]  # exact: t + ahead + 1 frames read, clipped at the end

    from jaxdenoise import sequence

    calls = {"prepare": 0, "window": 0}

    def prep(module, config):
        def f(p, b):
            calls["prepare"] += 1
            return module.prepare_frame(p, b, config)
        return f

    def win(module, config):
        def f(p, w, c):
            calls["window"] += 1
            return module.apply_window(p, w, c, config)
        return f

    monkeypatch.setattr(sequence, "_jitted_prepare_frame", prep)
    monkeypatch.setattr(sequence, "_jitted_window", win)
    run_all(m, params, _frames(6))
    assert calls == {"prepare": 6, "window": 6}  # exact: every frame prepared and emitted once


def test_api_cli_and_driver_agree_on_a_sequence(weights, tmp_path):
    folder, params = weights
    frames = _frames(4)
    m = dataclasses.replace(get("lbf"), config=CFG)
    want = run_all(m, params, frames)
    np.testing.assert_allclose(jd.denoise_sequence(frames, method="lbf", weights=folder), want, atol=TOL)
    np.testing.assert_allclose(np.stack(list(jd.load("lbf", folder).sequence(stack(frames)))), want, atol=TOL)
    from jaxdenoise.io import write_buffers

    for i, f in enumerate(frames):
        (tmp_path / "seq" / f"frame_{i:04d}").mkdir(parents=True)
        write_buffers(tmp_path / "seq" / f"frame_{i:04d}" / "spp0004_00.exr", f)
    out = tmp_path / "out"
    assert main(["denoise", "--frames", str(tmp_path / "seq" / "frame_*" / "spp0004_00.exr"), "-o", str(out),
                 "--method", "lbf", "--weights", str(folder)]) == 0
    written = sorted(out.glob("*.exr"))
    assert [p.name for p in written] == [f"frame_{i:04d}_spp0004_00.exr" for i in range(4)]
    for i, p in enumerate(written):
        np.testing.assert_allclose(read_image(p), want[i], atol=TOL)


def test_bench_runs_sequences_through_the_driver(weights, tmp_path):
    """A 3-frame sequence: per-frame records, one temporal record per method with the temporal
    error, equal to the driver's output scored by hand."""

    folder, params = weights
    frames = _frames(3)
    refs = [synthetic_frame(12, 12, seed=50 + i).color for i in range(3)]
    _write_sequence(tmp_path / "data" / "seq_a", frames, refs)
    report = bench.run(tmp_path / "data", ["input", "lbf"], tmp_path / "r", runs=5,
                       weights={"lbf": str(folder)}, progress=False)
    assert len(report["records"]) == 3 * 2 and {r["frame"] for r in report["records"]} == {0, 1, 2}
    t = {x["method"]: x for x in report["temporal"]}
    assert t["lbf"]["kind"] == "windowed" and t["input"]["kind"] == "frame"
    m = dataclasses.replace(get("lbf"), config=CFG)
    out = run_all(m, params, frames)
    want = float(metrics.temporal_error(out, np.stack(refs)))
    assert t["lbf"]["temporal_error"] == pytest.approx(want, rel=1e-4)
    assert "## Sequences" in (tmp_path / "r" / "results.md").read_text()
    # --no-timing: the same scores from one untimed pass, no time columns, the report still written
    quiet = bench.run(tmp_path / "data", ["input", "lbf"], tmp_path / "q", weights={"lbf": str(folder)},
                      progress=False, timing=False)
    tq = {x["method"]: x for x in quiet["temporal"]}
    assert tq["lbf"]["temporal_error"] == pytest.approx(want, rel=1e-4) and tq["lbf"]["seconds_per_frame"] is None
    assert all(r["seconds"] is None and r["seconds_all"] == [] for r in quiet["records"])
    assert "## Sequences" in (tmp_path / "q" / "results.md").read_text()


def test_driver_refuses_stacked_frames_and_empty_sequences(weights):
    _, params = weights
    m = dataclasses.replace(get("lbf"), config=CFG)
    with pytest.raises(BuffersError, match="must be one \\(H, W, 3\\) frame"):
        list(run(m, params, [stack(_frames(2))], names=["a.exr"]))
    with pytest.raises(BuffersError, match="no frames"):
        run_all(m, params, [])
    with pytest.raises(BuffersError, match="leading time axis"):
        jd.denoise_sequence(synthetic_frame(), method="gaussian")


def test_causal_method_through_driver_and_bench(tmp_path):
    """A toy recurrent method: the driver carries its state (frame t = EMA of frames 0..t), and bench
    writes its temporal record with kind 'causal'; the EMA flickers less than the input."""
    from jaxdenoise.io import write_buffers, write_image

    with registered("ema", "fake_recurrent"):
        m = get("ema")
        assert m.temporal == "causal"
        frames = _frames(3)
        out = run_all(m, {}, frames)
        c = [np.asarray(f.color) for f in frames]
        want = [c[0], 0.5 * c[0] + 0.5 * c[1]]
        want.append(0.5 * want[1] + 0.5 * c[2])
        np.testing.assert_allclose(out, np.stack(want), rtol=1e-6)
        ref = synthetic_frame(12, 12, seed=99).color
        for i, f in enumerate(frames):
            d = tmp_path / "data" / "seq" / f"frame_{i:04d}"
            d.mkdir(parents=True)
            write_image(d / "reference.exr", ref)  # a static scene: any change is flicker
            write_buffers(d / "spp0004_00.exr", f)
        report = bench.run(tmp_path / "data", ["input", "ema"], tmp_path / "r", runs=5, progress=False)
    t = {x["method"]: x for x in report["temporal"]}
    assert t["ema"]["kind"] == "causal" and t["ema"]["frames"] == 3
    assert t["ema"]["temporal_error"] < t["input"]["temporal_error"]


def test_training_validation_steps_temporal_methods_through_sequences(tmp_path):
    """A sequence in the validation folder is one entry run through the driver: the toy recurrent
    method's score equals the mean RelMSE of its driven outputs (1e-6), not of per-frame applies."""
    from jaxdenoise.train import load_validation, validate

    frames = _frames(3)
    refs = [synthetic_frame(12, 12, seed=60 + i).color for i in range(3)]
    _write_sequence(tmp_path / "val" / "seq", frames, refs)
    with registered("ema", "fake_recurrent"):
        m = get("ema")
        entries = load_validation(m, tmp_path / "val")
        assert len(entries) == 1 and len(entries[0]["frames"]) == 3
        got = validate(m, {}, entries)["relmse"]
        out = run_all(m, {}, frames)
    want = np.mean([float(metrics.relmse(o, r)) for o, r in zip(out, refs)])
    assert got == pytest.approx(want, rel=1e-6)
    per_frame = np.mean([float(metrics.relmse(np.asarray(f.color), r)) for f, r in zip(frames, refs)])
    assert abs(got - per_frame) > 1e-4  # the state changed frames 1 and 2


def test_validation_from_a_whole_video_export_is_the_same_sequence(tmp_path):
    """A validation export of whole renders (the GPU machine has no OpenImageIO) keeps the video:
    one entry, its frames in order through the driver, the folder's score to float16 rounding."""
    from jaxdenoise import pipeline
    from jaxdenoise.train import load_validation, validate

    frames = _frames(3)
    refs = [synthetic_frame(12, 12, seed=60 + i).color for i in range(3)]
    _write_sequence(tmp_path / "val" / "seq", frames, refs)
    cache = pipeline.build_cache(tmp_path / "val", ["color"], tmp_path / "cache")
    cache.export(tmp_path / "val.npz", n=100, whole=True)
    with registered("ema", "fake_recurrent"):
        m = get("ema")
        folder, export = load_validation(m, tmp_path / "val"), load_validation(m, tmp_path / "val.npz")
        assert len(export) == 1 and len(export[0]["frames"]) == 3
        want, got = validate(m, {}, folder)["relmse"], validate(m, {}, export)["relmse"]
    assert got == pytest.approx(want, rel=2e-3)
