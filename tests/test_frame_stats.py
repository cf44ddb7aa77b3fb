"""Per-frame statistics of the networks' inputs (DEMC's world-position z-score, RAE's mean linear
depth, GradNet's largest depth) are those of the whole render in training as at inference: a
training crop's inputs, built from the cache with the statistics it carries, equal the whole
frame's inputs cropped at the same place (and differ from those a per-crop statistic gives); an
export keeps the values; a cache built without them gets them on opening (no EXR decoded again);
an export without them is refused, naming the file and the statistic."""
from __future__ import annotations

import json

import numpy as np
import pytest

from jaxdenoise import pipeline, view
from jaxdenoise.errors import JaxdenoiseError
from jaxdenoise.methods import demc, rae
from jaxdenoise.methods import gradnet as G

H, W, C, T = 24, 20, 12, 7  # frame, crop, frames of the video
SPPS = (1, 4, 64)  # rae's, demc's and gradnet's training rates
DEMC = demc.Config(train_crop=C, train_batch=4, train_spps=(4,))
RAE = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, train_crop=C, train_batch=2, train_spps=(1,))
GRAD = G.Config(widths=(8, 16, 16), g_width=8, train_crop=C, train_batch=4)
NORM = {"mean": np.zeros(12, np.float32), "std": np.ones(12, np.float32)}  # demc's z-score: identity


def _frame(t: int, spp: int):
    """Every buffer, with ramps across the image so that a crop's statistics are not the frame's:
    position (demc's z-score, rae's depth through the camera), depth (gradnet's maximum); a block of
    background pixels (normal 0: no surface, rae's mean leaves them out)."""
    from conftest import synthetic_frame

    f = synthetic_frame(H, W, seed=100 * t + spp)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    pos = f.position + np.stack([xx * 0.5, yy * 0.1, yy * 0.2 + t], -1)
    normal = np.array(f.normal)
    normal[:3, :4] = 0.0
    return f.replace(position=pos.astype(np.float32), normal=normal,
                     depth=(f.depth * (1 + xx / W)[..., None]).astype(np.float32))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A 7-frame video (``seq/frame_XXXX/``), each frame rendered at 1, 4 and 64 spp."""
    from conftest import make_shot

    root = tmp_path_factory.mktemp("frame_stats")
    for t in range(T):
        d = root / "data" / "seq" / f"frame_{t:04d}"
        d.mkdir(parents=True)
        make_shot(d, np.ones((H, W, 3), np.float32), {s: _frame(t, s) for s in SPPS}, {"primal": "gpt"})
    return root


@pytest.fixture
def cache_env(data, monkeypatch):
    monkeypatch.setenv("JAXDENOISE_CACHE", str(data / "cache"))
    return data / "data"


def _whole_frames(folder, spp):
    """The renders at ``spp`` as inference reads them (`jaxdenoise.io.read_buffers`), in frame order."""
    from jaxdenoise.io import read_buffers

    return [read_buffers(folder / "seq" / f"frame_{t:04d}" / f"spp{spp:04d}_00.exr")[0] for t in range(T)]


def _locate(albedo, frames):
    """``(frame, y, x)`` of the window of ``frames`` whose albedo is ``albedo`` (random per pixel:
    unique); albedo is neither modulated nor, with the augmentation switched off, turned."""
    c = albedo.shape[0]
    for t, f in enumerate(frames):
        a = np.asarray(f.albedo)
        for y in range(H - c + 1):
            for x in range(W - c + 1):
                if np.array_equal(a[y:y + c, x:x + c], albedo):
                    return t, y, x
    raise AssertionError("crop not found in any frame")


@pytest.fixture
def no_augment(monkeypatch):
    """The methods' own `batch`, with the pipeline's augmentation switched off (it only moves pixels
    and scales radiance: the crop can then be found in the whole frame as it is)."""
    monkeypatch.setattr(pipeline, "augment", lambda item, rng, **kw: item)


def _without_stats(batch):
    return {k: v for k, v in batch.items() if not k.startswith(pipeline.STAT)}


def test_demc_crop_inputs_are_the_whole_frames_inputs_cropped(cache_env, no_augment):
    ds = demc.make_dataset(cache_env, DEMC, progress=False)
    b = demc.batch(ds, 0, DEMC, np.random.default_rng(0))
    assert b["stat.position_mean"].shape == (4, 3) and b["stat.position_std"].shape == (4, 3)
    frames = _whole_frames(cache_env, 4)
    params = {"norm": NORM}
    xc, xf = (np.asarray(a) for a in demc.inputs(params, b, DEMC))
    _, old = demc.inputs(params, _without_stats(b), DEMC)  # the statistics of the crop itself
    for i in range(4):
        t, y, x = _locate(b["albedo"][i], frames)
        wc, wf = (np.asarray(a)[y:y + C, x:x + C] for a in demc.inputs(params, frames[t], DEMC))
        np.testing.assert_allclose(xc[i], wc, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(xf[i], wf, rtol=1e-6, atol=1e-6)  # position z-scored by the frame's moments
        assert np.max(np.abs(np.asarray(old[i])[..., 3:6] - wf[..., 3:6])) > 0.05  # a crop's own moments differ


def test_rae_sequence_crop_inputs_are_each_whole_frames_inputs_cropped(cache_env, no_augment):
    """Each frame of a sequence crop carries its own frame's mean depth (one value per frame, not
    one per sequence: `step` normalizes every frame by its own at inference)."""
    ds = rae.make_dataset(cache_env, RAE, progress=False)
    seq = ds.sequences(2, C, np.random.default_rng(1), frames=T, augment=False)
    assert seq["stat.depth_mean"].shape == (2, T, 1)
    b = rae.batch(ds, 0, RAE, np.random.default_rng(1))
    frames = _whole_frames(cache_env, 1)
    whole = [np.asarray(rae.inputs(f, RAE)) for f in frames]
    means = [float(rae.surface_mean(view.linear_depth(f.position, f.normal, f.world_to_camera))[0])
             for f in frames]
    assert len(set(means)) == T  # the frames' means differ: a per-sequence value would be wrong
    off = []
    for i in range(2):
        for k in range(T):
            t, y, x = _locate(b["albedo"][i, k], frames)
            np.testing.assert_allclose(b["x"][i, k], whole[t][y:y + C, x:x + C], rtol=1e-5, atol=1e-6)
            d = b["x"][i, k, ..., 5] * means[t]  # the crop's linear depth (channel 5: after colour, normal x, y)
            off.append(abs(float(np.sum(d[d > 0]) / np.sum(d > 0)) / means[t] - 1))
    assert max(off) > 0.05  # a crop's own mean is another scale


def test_backward_playback_reverses_the_statistics_with_the_frames(cache_env):
    ds = rae.make_dataset(cache_env, RAE, progress=False)
    s = ds.sequences(6, C, np.random.default_rng(5), frames=T, rotate=False, flip=False, modulate=False)
    frames = _whole_frames(cache_env, 1)
    by_frame = {f["frame"]: f["stats"]["depth_mean"] for f in ds.frames}
    order = []
    for i in range(6):
        ts = [_locate(s["albedo"][i, k], frames)[0] for k in range(T)]
        order.append(ts[1] - ts[0])
        np.testing.assert_array_equal(s["stat.depth_mean"][i], np.asarray([by_frame[t] for t in ts], np.float32))
    assert set(order) == {-1, 1}  # both playback directions were drawn


def test_gradnet_crop_inputs_are_the_whole_frames_inputs_cropped(cache_env, no_augment):
    ds = G.make_dataset(cache_env, GRAD, progress=False)
    b = G.batch(ds, 0, GRAD, np.random.default_rng(2))
    assert b["stat.depth_max"].shape == (4, 1)
    frames = _whole_frames(cache_env, 64)
    got = G.inputs(b, GRAD)
    old = np.asarray(G.inputs(_without_stats(b), GRAD)["feat"])
    peaks = []
    for i in range(4):
        t, y, x = _locate(b["albedo"][i], frames)
        want = G.inputs(frames[t], GRAD)
        for k in ("feat", "tb", "tdx", "tdy"):
            np.testing.assert_allclose(np.asarray(got[k][i]), np.asarray(want[k])[y:y + C, x:x + C],
                                       rtol=1e-6, atol=1e-6)
        assert np.max(old[i, ..., 6]) == pytest.approx(1.0)  # a crop's own maximum maps its depth to [0, 1]...
        peaks.append(float(np.max(np.asarray(got["feat"][i, ..., 6]))))
    assert min(peaks) < 0.9  # ...the whole frame's leaves a crop below 1


def test_exports_keep_the_statistics(cache_env, tmp_path):
    """Crops, sequence crops and whole renders: the exported statistics (float32) are the cache's,
    value for value, and whatever is drawn from the export carries them, as a draw from the cache."""
    ds = demc.make_dataset(cache_env, DEMC, progress=False)
    summary = ds.export(tmp_path / "crops.npz", n=5, size=C, rng=np.random.default_rng(3))
    assert summary["stats"] == ["color_mean", "position_mean", "position_std"]
    r = np.random.default_rng(3)
    ds.crops(1, C, r, augment=False)  # the export's probe draw
    want = ds.crops(summary["count"], C, r, augment=False)
    ex = demc.make_dataset(tmp_path / "crops.npz", DEMC, progress=False)
    for n in ("color_mean", "position_mean", "position_std"):
        np.testing.assert_array_equal(ex.stats[n], want["stat." + n])
    drawn = demc.batch(ex, 0, DEMC, np.random.default_rng(0))
    assert {tuple(v) for v in drawn["stat.position_mean"]} <= {tuple(v) for v in ex.stats["position_mean"]}

    seqs = rae.make_dataset(cache_env, RAE, progress=False)
    summary = seqs.export(tmp_path / "seq.npz", n=3, size=C, rng=np.random.default_rng(4), frames=T)
    r = np.random.default_rng(4)
    seqs.sequences(1, C, r, frames=T, augment=False)
    want = seqs.sequences(summary["count"], C, r, frames=T, augment=False)
    ex = rae.make_dataset(tmp_path / "seq.npz", RAE, progress=False)
    np.testing.assert_array_equal(ex.stats["depth_mean"], want["stat.depth_mean"])
    s = ex.sequences(2, 8, np.random.default_rng(0), frames=T, augment=False)
    assert s["stat.depth_mean"].shape == (2, T, 1)

    seqs.export(tmp_path / "whole.npz", n=100, whole=True)
    ex = rae.make_dataset(tmp_path / "whole.npz", RAE, progress=False)
    np.testing.assert_array_equal(ex.stats["depth_mean"], seqs.whole()["stat.depth_mean"])
    b = rae.batch(ex, 0, RAE, np.random.default_rng(0))  # trains from it as from the cache
    assert b["x"].shape == (2, T, C, C, rae.in_channels(RAE))


def test_a_cache_without_the_statistics_gets_them_without_decoding(cache_env, tmp_path, monkeypatch):
    """A cache built before the method declared its statistics: opened with them, it computes them
    from the cached whole renders (no EXR read) and stores them in its index."""
    import jaxdenoise.io as io

    old = pipeline.build_cache(cache_env, demc.FEATURES, tmp_path / "old", spps=(4,))
    index = old.folder / "index.json"
    assert "stats" not in json.loads(index.read_text())["frames"][0]
    fresh = demc.make_dataset(cache_env, DEMC, progress=False)  # computed when the frames were cached

    def boom(*a, **k):
        raise AssertionError("an EXR was decoded again")

    monkeypatch.setattr(io, "read_buffers", boom)
    monkeypatch.setattr(io, "read_image", boom)
    again = pipeline.build_cache(cache_env, demc.FEATURES, tmp_path / "old", spps=(4,),
                                 stats=demc.frame_stats(DEMC))
    assert again.folder == old.folder
    stored = json.loads(index.read_text())["frames"]
    assert [f["stats"] for f in stored] == [f["stats"] for f in fresh.frames]
    np.testing.assert_array_equal(again.render(0)["stat.position_std"], fresh.render(0)["stat.position_std"])


def test_an_export_without_the_statistics_is_refused(cache_env, tmp_path):
    plain = pipeline.build_cache(cache_env, demc.FEATURES, tmp_path / "cache", spps=(4,))  # no statistics
    plain.export(tmp_path / "old.npz", n=4, size=C, rng=np.random.default_rng(0))
    with pytest.raises(JaxdenoiseError, match=r"old\.npz: the export lacks the per-frame statistic\(s\) "
                                              r"\['color_mean', 'position_mean', 'position_std'\]"):
        demc.make_dataset(tmp_path / "old.npz", DEMC, progress=False)
    # a method that declares none (global position z-score, the paper's exposure) reads it as before
    none = demc.Config(position_norm="global", exposure="none", train_spps=(4,))
    assert len(demc.make_dataset(tmp_path / "old.npz", none, progress=False)) == 4
