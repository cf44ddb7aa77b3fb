"""jaxdenoise.pipeline: gradient-consistent rotations and flips, aligned crops, a cache decoded once,
determinism under a seed, sequence crops with camera stops, and the compact export."""
from __future__ import annotations

import numpy as np
import pytest

from jaxdenoise import pipeline
from jaxdenoise.buffers import Buffers



def _grads(img):
    dx = np.zeros_like(img)
    dy = np.zeros_like(img)
    dx[..., :, :-1, :] = img[..., :, 1:, :] - img[..., :, :-1, :]
    dy[..., :-1, :, :] = img[..., 1:, :, :] - img[..., :-1, :, :]
    return dx, dy


@pytest.mark.parametrize("k", [1, 2, 3])
@pytest.mark.parametrize("flip", [False, True])
def test_rotated_gradients_equal_gradients_of_the_rotated_image(k, flip):
    img = np.random.default_rng(k).normal(size=(2, 5, 7, 3)).astype(np.float32)
    dx, dy = _grads(img)
    out = pipeline.rotate90({"color": img, "dx": dx, "dy": dy}, k)
    if flip:
        out = pipeline.flip_lr(out)
    want_dx, want_dy = _grads(out["color"])
    # exact: the same float differences, moved and negated
    np.testing.assert_array_equal(out["dx"], want_dx)
    np.testing.assert_array_equal(out["dy"], want_dy)


def _coded_frame(h, w, t=0, inst=0, spp=4):
    """color = (y, x, 100 t + inst), albedo = color / 1000, depth = t: alignment is checkable."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    color = np.stack([yy, xx, np.full_like(yy, 100 * t + inst)], -1)
    return Buffers(color=color, albedo=color / 1000, depth=np.full((h, w, 1), t, np.float32),
                   normal=np.zeros((h, w, 3), np.float32) + [0, 0, 1], spp=np.float32(spp))


@pytest.fixture
def folder(tmp_path):
    from jaxdenoise.io import write_buffers, write_image

    root = tmp_path / "data"
    for s in range(2):
        d = root / f"scene_{s:04d}"
        d.mkdir(parents=True)
        write_image(d / "reference.exr", _coded_frame(12, 10).color * 2)
        for spp in (4, 16):
            write_buffers(d / f"spp{spp:04d}_00.exr", _coded_frame(12, 10, spp=spp))
    for t in range(8):
        d = root / "seq" / f"frame_{t:04d}"
        d.mkdir(parents=True)
        write_image(d / "reference.exr", _coded_frame(12, 10, t).color * 2)
        for inst in range(2):
            write_buffers(d / f"spp0001_{inst:02d}.exr", _coded_frame(12, 10, t, inst, spp=1))
    return root


def test_crops_align_across_buffers_and_are_deterministic(folder, tmp_path):
    cache = pipeline.build_cache(folder, ["albedo", "depth", "normal"], tmp_path / "cache", spps=(4, 16))
    a = cache.crops(6, 8, np.random.default_rng([3, 7]), augment=False)
    assert a["color"].shape == (6, 8, 8, 3) and a["depth"].shape == (6, 8, 8, 1)  # exact
    np.testing.assert_allclose(a["albedo"], a["color"] / 1000, rtol=1e-6)  # same window in every buffer
    np.testing.assert_allclose(a["reference"], a["color"] * 2, rtol=1e-6)
    assert set(a["spp"].tolist()) <= {4.0, 16.0}
    b = cache.crops(6, 8, np.random.default_rng([3, 7]), augment=False)
    for f in a:
        np.testing.assert_array_equal(a[f], b[f])  # (seed, step) -> the same batch
    aug = cache.crops(6, 8, np.random.default_rng([3, 8]), modulate=False)
    np.testing.assert_allclose(aug["albedo"], aug["color"] / 1000, rtol=1e-6)  # rotations keep alignment
    mod = cache.crops(4, 8, np.random.default_rng(1), rotate=False, flip=False)
    ratio = mod["reference"] / np.maximum(mod["color"], 1e-6)
    assert np.allclose(ratio[mod["color"] > 1], 2.0, rtol=1e-5)  # colour and target modulated alike


def test_cache_is_decoded_once(folder, tmp_path, monkeypatch):
    first = pipeline.build_cache(folder, ["albedo"], tmp_path / "cache")
    import jaxdenoise.io as io

    def boom(*a, **k):
        raise AssertionError("an EXR was decoded again")

    monkeypatch.setattr(io, "read_buffers", boom)
    monkeypatch.setattr(io, "read_image", boom)
    again = pipeline.build_cache(folder, ["albedo"], tmp_path / "cache")
    assert again.folder == first.folder
    again.crops(2, 4, np.random.default_rng(0))  # sampling reads the memory-mapped arrays only
    with pytest.raises(ValueError, match="lacks buffer\\(s\\) \\['roughness'\\]"):
        monkeypatch.undo()
        pipeline.build_cache(folder, ["roughness"], tmp_path / "cache")


def test_sequence_crops_keep_frame_order_and_camera_stops(folder, tmp_path):
    cache = pipeline.build_cache(folder, ["depth"], tmp_path / "cache", spps=(1,))
    s = cache.sequences(5, 8, np.random.default_rng(0), augment=False)
    assert s["color"].shape == (5, 7, 8, 8, 3)
    t = s["depth"][:, :, 0, 0, 0]
    assert np.all(np.diff(t, axis=1) == 1)  # 7 consecutive frames, forward
    stops = cache.sequences(20, 8, np.random.default_rng(1), stop_probability=1.0, augment=False)
    t = stops["depth"][:, :, 0, 0, 0]
    inst = stops["color"][:, :, 0, 0, 2] - 100 * t
    for row_t, row_i in zip(t, inst):
        held = np.flatnonzero(np.diff(row_t) == 0)
        assert held.size >= 1  # the camera (and target) stay...
        k = held[0]
        assert row_i[k] != row_i[k + 1]  # ...while the noisy frame advances to another instance
    rev = cache.sequences(30, 8, np.random.default_rng(2), rotate=False, flip=False, modulate=False)
    d = np.diff(rev["depth"][:, :, 0, 0, 0], axis=1)
    assert (d == -1).all(axis=1).any() and (d == 1).all(axis=1).any()  # both playback directions


def test_export_is_compact_and_round_trips(folder, tmp_path):
    cache = pipeline.build_cache(folder, ["albedo", "normal", "depth"], tmp_path / "cache")
    summary = cache.export(tmp_path / "train.npz", n=50, size=8, rng=np.random.default_rng(0), max_mib=0.02)
    assert summary["count"] == min(50, summary["fit"]) and summary["bytes"] <= 0.02 * 2**20
    ex = pipeline.load_export(tmp_path / "train.npz")
    assert ex.count == summary["count"]
    b = ex.sample(3, np.random.default_rng(0), augment=False)
    # float16 radiance (3 significant digits) and 8-bit albedo (1/255 of its range)
    np.testing.assert_allclose(b["reference"], b["color"] * 2, rtol=2e-3)
    np.testing.assert_allclose(b["albedo"], np.clip(b["color"] / 1000, 0, 1), atol=1 / 255)
    np.testing.assert_allclose(b["normal"][..., 2], 1.0, atol=1 / 255)
    seq = cache.export(tmp_path / "seq.npz", n=4, size=8, rng=np.random.default_rng(0), frames=7)
    ex = pipeline.load_export(tmp_path / "seq.npz")
    assert ex.items["color"].shape == (seq["count"], 7, 8, 8, 3)
    s = ex.sequences(3, 6, np.random.default_rng(0), stop_probability=1.0, augment=False)
    assert s["color"].shape == (3, 7, 6, 6, 3)  # sub-windows of the exported sequence crops
    assert np.all(np.diff(s["depth"][:, :, 0, 0, 0], axis=1) == 1)  # one instance per frame: no stop


def test_whole_video_export_samples_sequences_like_the_cache(folder, tmp_path):
    """A whole-render export keeps the videos (frames in order, noise instances): sequences drawn
    from it with a seed are the cache's draws (to float16 / 8-bit rounding), camera stops included;
    ``instances=1`` keeps one instance per frame, and then no stop is possible."""
    cache = pipeline.build_cache(folder, ["albedo", "depth"], tmp_path / "cache", spps=(1,))
    summary = cache.export(tmp_path / "vid.npz", n=10**6, whole=True, spps=(1,))
    assert summary["count"] == 16  # 8 frames x 2 instances, not the number that would fit
    ex = pipeline.load_export(tmp_path / "vid.npz")
    assert [sorted(v) for v in ex.videos] == [list(range(8))] and all(len(ids) == 2 for ids in ex.videos[0].values())
    for kw in ({"augment": False}, {"stop_probability": 1.0}):
        a = cache.sequences(6, 8, np.random.default_rng(5), **kw)
        b = ex.sequences(6, 8, np.random.default_rng(5), **kw)
        assert a.keys() == b.keys()
        np.testing.assert_allclose(b["color"], a["color"], rtol=1e-3)
        np.testing.assert_array_equal(b["depth"], a["depth"])
    one = pipeline.load_export(tmp_path / "one.npz") if cache.export(
        tmp_path / "one.npz", n=100, whole=True, spps=(1,), instances=1)["count"] == 8 else None
    assert one is not None and all(len(ids) == 1 for ids in one.videos[0].values())
    s = one.sequences(10, 8, np.random.default_rng(0), stop_probability=1.0, augment=False)
    assert np.all(np.diff(s["depth"][:, :, 0, 0, 0], axis=1) == 1)  # 7 consecutive frames, no stop


def test_cache_fills_a_left_out_constant_buffer_and_keeps_the_camera(tmp_path):
    """A render without roughness (data_gen leaves a constant buffer out) gets the constant the
    method documents, the frame is listed as filled, and the camera matrices reach the crops."""
    from conftest import synthetic_frame
    from jaxdenoise.io import write_buffers, write_image

    shot = tmp_path / "data" / "shot"
    shot.mkdir(parents=True)
    f = synthetic_frame(8, 8, fields=("color", "albedo"))
    write_buffers(shot / "spp0001_00.exr", f.replace(spp=np.float32(1)))
    write_image(shot / "reference.exr", np.ones((8, 8, 3), np.float32))
    with pytest.raises(ValueError, match="lacks buffer"):
        pipeline.build_cache(tmp_path / "data", ["albedo", "roughness"], tmp_path / "cache")
    cache = pipeline.build_cache(tmp_path / "data", ["albedo", "roughness"], tmp_path / "cache", fill={"roughness": 1.0})
    assert cache.frames[0]["filled"] == ["roughness"]
    crop = cache.crops(1, 8, np.random.default_rng(0), augment=False)
    assert np.all(crop["roughness"] == 1.0)
    np.testing.assert_array_equal(crop["world_to_camera"][0], f.world_to_camera)
