"""Temporal anti-aliasing (`jaxdenoise.filters.taa_step`): reprojection through positions and cameras,
the running mean, the clamp, disocclusions, exposure, bad settings; and `rae`'s `taa_alpha`. The input
accumulation (`jaxdenoise.filters.accumulate_step`): an unweighted running mean, the taps' HDR weights,
disocclusions, exposure, leading axes, bad settings."""
from __future__ import annotations

import numpy as np
import pytest

from jaxdenoise import color
from jaxdenoise.filters import FilterError, accumulate_step, check_taa_settings, reproject, taa_init, taa_step

H, W = 6, 8


def plane(z: float = 1.0):
    """World positions of the pixel centres on the plane ``z`` seen by an orthographic camera whose
    world_to_ndc maps (x, y) to NDC (x, y) with w = 1, the normals facing it, and that camera."""
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    pos = np.stack([(cols + 0.5) / W * 2 - 1, 1 - (rows + 0.5) / H * 2, np.full((H, W), z)], -1).astype(np.float32)
    cam = np.eye(4, dtype=np.float32)
    cam[2, 2] = 0.0  # NDC z unused; w = 1 (row 3 = (0, 0, 0, 1))
    normal = np.broadcast_to(np.asarray([0, 0, -1], np.float32), (H, W, 3)).copy()
    return pos, normal, cam


def blend(x, h, n):
    """The module docstring's blend, in NumPy: ``x`` and history ``h`` weighted by 1 / n and 1 - 1 / n
    times Karis's 1 / (1 + luminance / the frame's exposure level)."""
    knee = float(np.asarray(color.exposure_level(x))[0])
    s = lambda v: 1.0 / (1.0 + np.asarray(color.luminance(v))[..., None] / knee)  # noqa: E731
    wx, wh = s(x) / n, s(h) * (1.0 - 1.0 / n)
    return (wx * x + wh * h) / (wx + wh)


def test_a_still_camera_blends_a_running_mean_then_by_alpha():
    pos, nrm, cam = plane()
    rng = np.random.default_rng(0)
    frames = rng.random((6, H, W, 3)).astype(np.float32)
    frames[2, 1, 1] = 500.0  # a firefly: weighed down by its luminance
    state, outs = taa_init((H, W, 3)), []
    for f in frames:
        state, o = taa_step(state, f, pos, nrm, cam, alpha=0.25, window=0)
        outs.append(np.asarray(o))
    np.testing.assert_array_equal(outs[0], frames[0])
    for k in range(1, 6):  # history lengths 2, 3, 4, then capped at 1 / alpha = 4
        np.testing.assert_allclose(outs[k], blend(frames[k], outs[k - 1], min(k + 1, 4)), rtol=1e-5, atol=1e-6)
    assert float(np.max(state.count)) == 4.0
    assert outs[2][1, 1].max() < 5.0  # a plain mean of three frames would give 500 / 3 there


def test_history_follows_the_camera():
    pos, nrm, cam = plane()
    img = np.random.default_rng(1).random((H, W, 3)).astype(np.float32)
    state, _ = taa_step(taa_init((H, W, 3)), img, pos, nrm, cam, alpha=0.5, window=0)
    moved_pos = pos.copy()
    moved_pos[..., 0] += 2.0 / W  # the camera moved one pixel to the right: each pixel now sees the next point
    warped, count, valid = (np.asarray(a) for a in reproject(state, moved_pos, nrm, tolerance=0.02))
    assert valid[:, :-1].all() and not valid[:, -1].any()  # the last column's points were not in view
    np.testing.assert_allclose(warped[:, :-1], img[:, 1:], rtol=1e-5, atol=1e-6)
    assert (count[:, :-1] == 1).all()


def test_a_disocclusion_keeps_no_history_and_the_clamp_bounds_it():
    pos, nrm, cam = plane()
    old = np.full((H, W, 3), 10.0, np.float32)
    state, _ = taa_step(taa_init((H, W, 3)), old, pos, nrm, cam, alpha=0.5, window=0)
    near = pos.copy()
    near[:3, ..., 2] = 0.5  # the top rows now see a surface in front of the old one
    cur = np.random.default_rng(2).random((H, W, 3)).astype(np.float32)
    _, out = taa_step(state, cur, near, nrm, cam, alpha=0.5, window=0, tolerance=0.02)
    out = np.asarray(out)
    np.testing.assert_array_equal(out[:3], cur[:3])  # no history across the disocclusion
    np.testing.assert_allclose(out[3:], blend(cur, old, 2)[3:], rtol=1e-5)
    _, clamped = taa_step(state, cur, near, nrm, cam, alpha=0.5, window=3, tolerance=0.02)
    clamped = np.asarray(clamped)
    pad = np.pad(cur, ((1, 1), (1, 1), (0, 0)), mode="edge")
    hi = np.max([pad[i:i + H, j:j + W] for i in range(3) for j in range(3)], axis=0)
    np.testing.assert_allclose(clamped[3:], blend(cur, hi, 2)[3:], rtol=1e-5)  # history clipped to the 3x3 max
    _, loose = taa_step(state, cur, near, nrm, cam, alpha=0.5, window=0, tolerance=0.0)  # no geometric test
    np.testing.assert_allclose(np.asarray(loose)[:3], blend(cur, old, 2)[:3], rtol=1e-5)  # the old surface's history


def test_exposure_and_leading_axes():
    pos, nrm, cam = plane()
    rng = np.random.default_rng(3)
    a, b = rng.random((2, H, W, 3)).astype(np.float32)
    moved = pos + np.asarray([0.3 / W, 0.0, 0.0], np.float32)

    def two(k):
        s, _ = taa_step(taa_init((H, W, 3)), k * a, pos, nrm, cam, alpha=0.2)
        return np.asarray(taa_step(s, k * b, moved, nrm, cam, alpha=0.2)[1])
    base = two(1.0)
    for k in (1 / 16, 16.0):
        np.testing.assert_allclose(two(k), k * base, rtol=1e-5, atol=1e-7)
    s, _ = taa_step(taa_init((2, H, W, 3)), np.stack([a, b]), np.stack([pos, pos]), np.stack([nrm, nrm]), cam,
                    alpha=0.2)
    _, both = taa_step(s, np.stack([b, a]), np.stack([moved, moved]), np.stack([nrm, nrm]), cam, alpha=0.2)
    np.testing.assert_allclose(np.asarray(both)[0], base, rtol=1e-6)


@pytest.mark.parametrize("kw, name", [({"alpha": 0.0}, "'alpha'"), ({"alpha": 1.5}, "'alpha'"),
                                      ({"window": 2}, "'window'"), ({"tolerance": -1.0}, "'tolerance'"),
                                      ({"tolerance": float("nan")}, "'tolerance'")])
def test_bad_settings_are_refused_by_name(kw, name):
    pos, nrm, cam = plane()
    with pytest.raises(FilterError, match=name):
        taa_step(taa_init((H, W, 3)), pos, pos, nrm, cam, **kw)
    with pytest.raises(FilterError, match="rae: config.taa_"):
        check_taa_settings("rae: config.", kw.get("alpha", 0.1), kw.get("window", 3), kw.get("tolerance", 0.02))


def test_bad_inputs_are_refused_by_name():
    pos, nrm, cam = plane()
    with pytest.raises(FilterError, match="history"):
        taa_step(taa_init((H + 1, W, 3)), pos, pos, nrm, cam)
    with pytest.raises(FilterError, match="'position' is None"):
        taa_step(taa_init((H, W, 3)), pos, None, nrm, cam)
    bad = pos.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(FilterError, match="'position' has 1 NaN"):
        taa_step(taa_init((H, W, 3)), pos, bad, nrm, cam)


def test_accumulation_is_an_unweighted_running_mean_then_exponential():
    pos, nrm, cam = plane()
    frames = np.random.default_rng(5).random((6, H, W, 3)).astype(np.float32)
    frames[2, 1, 1] = 5.0  # a bright sample counts as any sample (below the clamp): the mean stays unbiased
    state, outs = taa_init((H, W, 3)), []
    for k, f in enumerate(frames):
        state, o, n = accumulate_step(state, f, pos, nrm, cam, frames=4, tolerance=0.02, clamp=0)
        np.testing.assert_array_equal(np.asarray(n), min(k + 1, 4))
        outs.append(np.asarray(o))
    for k in range(4):
        np.testing.assert_allclose(outs[k], frames[:k + 1].mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(outs[4], 0.25 * frames[4] + 0.75 * outs[3], rtol=1e-5, atol=1e-6)
    cap = np.full((H, W, 1), 4.0, np.float32)
    cap[:, :4] = 1.0  # per pixel: the left half keeps no history
    s, _, _ = accumulate_step(taa_init((H, W, 3)), frames[0], pos, nrm, cam, frames=cap)
    _, o, n = accumulate_step(s, frames[1], pos, nrm, cam, frames=cap, clamp=0)
    np.testing.assert_array_equal(np.asarray(o)[:, :4], frames[1][:, :4])
    np.testing.assert_array_equal(np.asarray(n)[:, 4:], 2.0)


def test_accumulation_clamps_a_bright_history_and_rejects_disocclusions():
    pos, nrm, cam = plane()
    old = np.full((H, W, 3), 0.1, np.float32)
    old[:, 4] = 1000.0  # a light's column
    half = pos + np.asarray([0.5 * 2 / W, 0.0, 0.0], np.float32)  # half a pixel to the right: two equal taps
    cur = np.full((H, W, 3), 0.1, np.float32)
    state, _, _ = accumulate_step(taa_init((H, W, 3)), old, pos, nrm, cam, frames=2)
    _, plain, _ = accumulate_step(state, cur, half, nrm, cam, frames=2, clamp=0)
    np.testing.assert_allclose(np.asarray(plain)[:, 3], 0.5 * 0.1 + 0.5 * (0.5 * 0.1 + 0.5 * 1000.0), rtol=1e-5)
    _, clamped, _ = accumulate_step(state, cur, half, nrm, cam, frames=2, clamp=4.0)
    np.testing.assert_allclose(np.asarray(clamped)[:, 3], 0.5 * 0.1 + 0.5 * 4 * 0.1, rtol=1e-5)  # 4x the 3x3 max
    np.testing.assert_allclose(np.asarray(clamped)[:, 0], 0.1, rtol=1e-5)  # below the bound: untouched
    near = pos.copy()
    near[:3, ..., 2] = 0.5  # the top rows see a surface in front of the old one
    _, out, n = accumulate_step(state, cur, near, nrm, cam, frames=2, tolerance=0.02)
    np.testing.assert_array_equal(np.asarray(out)[:3], cur[:3])
    np.testing.assert_array_equal(np.asarray(n)[:3], 1.0)
    np.testing.assert_array_equal(np.asarray(n)[3:], 2.0)


def test_accumulation_exposure_leading_axes_and_bad_settings():
    pos, nrm, cam = plane()
    a, b = np.random.default_rng(6).random((2, H, W, 3)).astype(np.float32)
    a[2, 3] = 40.0  # a spike the next frame's clamp cuts
    moved = pos + np.asarray([0.3 / W, 0.0, 0.0], np.float32)

    def two(k, x=a, y=b):
        s, _, _ = accumulate_step(taa_init((H, W, 3)), k * x, pos, nrm, cam, frames=5)
        return np.asarray(accumulate_step(s, k * y, moved, nrm, cam, frames=5, clamp=2.0)[1])
    base = two(1.0)
    for k in (1 / 16, 16.0):
        np.testing.assert_allclose(two(k), k * base, rtol=1e-5, atol=1e-7)
    s, _, _ = accumulate_step(taa_init((2, H, W, 3)), np.stack([a, b]), np.stack([pos, pos]), np.stack([nrm, nrm]),
                              cam, frames=5)
    _, both, n = accumulate_step(s, np.stack([b, a]), np.stack([moved, moved]), np.stack([nrm, nrm]), cam,
                                 frames=5, clamp=2.0)
    np.testing.assert_allclose(np.asarray(both), np.stack([base, two(1.0, b, a)]), rtol=1e-6)
    assert np.shape(n) == (2, H, W, 1)
    for kw, name in (({"frames": np.nan}, "'frames'"), ({"tolerance": -1.0}, "'tolerance'"),
                     ({"clamp": np.inf}, "'clamp'")):
        with pytest.raises(FilterError, match=name):
            accumulate_step(taa_init((H, W, 3)), a, pos, nrm, cam, **kw)
    with pytest.raises(FilterError, match="'normal' is None"):
        accumulate_step(taa_init((H, W, 3)), a, pos, None, cam)
    with pytest.raises(FilterError, match="history"):
        accumulate_step(taa_init((H + 1, W, 3)), a, pos, nrm, cam)
