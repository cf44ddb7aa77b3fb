"""Tests of jaxdenoise.filters: brute-force NumPy references on 8x8 inputs, properties, gradients,
extreme inputs and argument errors. Tiny sizes and radii keep the number and cost of jit compiles
low (the whole file runs in well under a minute on 2 cores)."""
from __future__ import annotations

import jax
import numpy as np
import pytest
from jax.test_util import check_grads as _check_grads

from jaxdenoise.filters import (DELTA, ZETA, FilterError, bilateral, clamp_outliers, cross_bilateral, cross_nlm,
                                drop_constant_features, gaussian, input_gain, level_gain, match_level, match_to_input,
                                prefilter_features,
                                remove_spikes, spatiotemporal_cross_bilateral)

H, W = 8, 8


def rng(seed=0):
    return np.random.default_rng(seed)


def frame(seed=0, h=H, w=W):
    """A random frame: colour, colour variance, two features (3 and 1 channels) and their variances."""
    g = rng(seed)
    c = g.random((h, w, 3)).astype(np.float32)
    v = (0.05 * g.random((h, w, 3))).astype(np.float32)
    f = [g.random((h, w, 3)).astype(np.float32), g.random((h, w, 1)).astype(np.float32)]
    fv = [(0.01 * g.random((h, w))).astype(np.float32), None]
    return c, v, f, fv


def _map(x, h, w):
    x = np.asarray(x, np.float64)
    return np.broadcast_to(x.reshape(x.shape[:2]) if x.ndim else x, (h, w))


# ----------------------------------------------------------------------------------------------
# brute-force NumPy references (direct transcriptions of the equations, one pixel pair at a time)


def ref_cross_bilateral(c, v, feats, fvars, ls, lc, lfs, r, frames=None, lt=0.0):
    """Kalantari 2015 Eq. 1-2, 11-12 with lambda = 1/(2 theta^2); ``frames``: (T, ...) volume mode."""
    if frames is None:
        vol = [(c, v, feats)]
        centre = 0
        dts = [0]
    else:
        vol, centre, dts = frames
    c0, v0, f0 = vol[centre]
    h, w = c0.shape[:2]
    ls, lc, lt = _map(ls, h, w), _map(lc, h, w), _map(lt, h, w)
    lfs = [_map(l, h, w) for l in lfs]
    out = np.zeros(c0.shape)
    for i in range(h):
        for j in range(w):
            num, den = np.zeros(c0.shape[-1]), 0.0
            for (ct, vt, ft), dt in zip(vol, dts):
                for y in range(max(0, i - r), min(h, i + r + 1)):
                    for x in range(max(0, j - r), min(w, j + r + 1)):
                        lw = -ls[i, j] * ((y - i) ** 2 + (x - j) ** 2) - lt[i, j] * dt ** 2
                        if v0 is not None:
                            lw -= lc[i, j] * np.sum((c0[i, j] - ct[y, x]) ** 2 / (v0[i, j] + vt[y, x] + ZETA))
                        for k in range(len(f0)):
                            var = 0.0 if fvars[k] is None else np.asarray(fvars[k]).reshape(h, w)[i, j]
                            lw -= lfs[k][i, j] * np.sum((f0[k][i, j] - ft[k][y, x]) ** 2) / max(var, DELTA)
                        wgt = np.exp(lw)
                        num += wgt * ct[y, x]
                        den += wgt
            out[i, j] = num / den
    return out


def ref_bilateral(c, ls, lr, r):
    h, w = c.shape[:2]
    out = np.zeros(c.shape)
    for i in range(h):
        for j in range(w):
            num, den = 0.0, 0.0
            for y in range(max(0, i - r), min(h, i + r + 1)):
                for x in range(max(0, j - r), min(w, j + r + 1)):
                    wgt = np.exp(-ls * ((y - i) ** 2 + (x - j) ** 2) - lr * np.sum((c[i, j] - c[y, x]) ** 2))
                    num, den = num + wgt * c[y, x], den + wgt
            out[i, j] = num / den
    return out


def _patch_dist(c, v, i, j, y, x, pr, cancel):
    h, w = c.shape[:2]
    tot, cnt = 0.0, 0
    for a in range(-pr, pr + 1):
        for b in range(-pr, pr + 1):
            p, q = (i + a, j + b), (y + a, x + b)
            if not (0 <= p[0] < h and 0 <= p[1] < w and 0 <= q[0] < h and 0 <= q[1] < w):
                continue
            d2 = (c[p] - c[q]) ** 2
            if cancel:
                tot += np.mean((d2 - (v[p] + np.minimum(v[p], v[q]))) / (v[p] + v[q] + ZETA))
            else:
                tot += np.sum(d2 / (v[p] + v[q] + ZETA))
            cnt += 1
    d = tot / cnt
    return max(d, 0.0) if cancel else d


def ref_cross_nlm(c, v, feats, fvars, lp, lfs, r, pr):
    """Appendix Eq. 16-17."""
    h, w = c.shape[:2]
    lp = _map(lp, h, w)
    lfs = [_map(l, h, w) for l in lfs]
    out = np.zeros(c.shape)
    for i in range(h):
        for j in range(w):
            num, den = 0.0, 0.0
            for y in range(max(0, i - r), min(h, i + r + 1)):
                for x in range(max(0, j - r), min(w, j + r + 1)):
                    lw = -lp[i, j] * _patch_dist(c, v, i, j, y, x, pr, False)
                    for k in range(len(feats)):
                        var = 0.0 if fvars[k] is None else np.asarray(fvars[k]).reshape(h, w)[i, j]
                        lw -= lfs[k][i, j] * np.sum((feats[k][i, j] - feats[k][y, x]) ** 2) / max(var, DELTA)
                    wgt = np.exp(lw)
                    num, den = num + wgt * c[y, x], den + wgt
            out[i, j] = num / den
    return out


def ref_prefilter(f, v, r, pr, lam):
    h, w = f.shape[:2]
    v = v.reshape(h, w, 1)
    vb = np.broadcast_to(v, f.shape)
    out_f, out_v = np.zeros(f.shape), np.zeros((h, w, 1))
    for i in range(h):
        for j in range(w):
            nf, nv, den = 0.0, 0.0, 0.0
            for y in range(max(0, i - r), min(h, i + r + 1)):
                for x in range(max(0, j - r), min(w, j + r + 1)):
                    wgt = np.exp(-lam * _patch_dist(f, vb, i, j, y, x, pr, True))
                    nf, nv, den = nf + wgt * f[y, x], nv + wgt * v[y, x], den + wgt
            out_f[i, j], out_v[i, j] = nf / den, nv / den
    return out_f, out_v


def ref_gaussian(c, sigma, r):
    """The normalized Gaussian window sum in float64, one NumPy pass per window offset (the equation
    summed offset by offset over every pixel whose neighbour is inside the image; vectorized over
    pixels only, so the 40x150 r = 12 case takes well under a second instead of ~15 s)."""
    h, w = c.shape[:2]
    c = np.asarray(c, np.float64)
    num, den = np.zeros(c.shape), np.zeros(c.shape[:2] + (1,))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if abs(dy) >= h or abs(dx) >= w:  # no pixel has this neighbour inside the image
                continue
            wgt = np.exp(-(dy ** 2 + dx ** 2) / (2 * sigma ** 2))
            yi, xi = slice(max(0, -dy), min(h, h - dy)), slice(max(0, -dx), min(w, w - dx))
            yj, xj = slice(max(0, dy), min(h, h + dy)), slice(max(0, dx), min(w, w + dx))
            num[yi, xi] += wgt * c[yj, xj]
            den[yi, xi] += wgt
    return num / den


def ref_spikes(c, n_std):
    h, w = c.shape[:2]
    p = np.pad(c, ((1, 1), (1, 1), (0, 0)), mode="edge")
    out = c.astype(np.float64).copy()
    for i in range(h):
        for j in range(w):
            block = p[i:i + 3, j:j + 3].reshape(9, -1).astype(np.float64)
            if np.any(np.abs(c[i, j] - block.mean(0)) > n_std * block.std(0)):
                out[i, j] = np.median(block, axis=0)
    return out


# ----------------------------------------------------------------------------------------------
# agreement with the references (tolerance: 2e-5 absolute on values in [0, 1], float32 vs float64)


def test_gaussian_matches_reference():
    c = frame()[0]
    np.testing.assert_allclose(gaussian(c, 0.9, radius=2), ref_gaussian(c, 0.9, 2), atol=2e-5)
    # per-pixel sigma (window engine): a constant map equals the separable path (tolerance 2e-6)
    np.testing.assert_allclose(gaussian(c, np.full((H, W), 0.9, np.float32), radius=2),
                               gaussian(c, 0.9, radius=2), atol=2e-6)


# 7x300 under `slow` (25 s, 26th session): 40x150 keeps several tiles with a partial last one
@pytest.mark.parametrize("h,w,radius", [(9, 13, 3), (40, 150, 12), pytest.param(7, 300, 20, marks=pytest.mark.slow)])
def test_gaussian_banded_passes_match_the_reference(h, w, radius, monkeypatch):
    """The banded matrix-product passes (every radius forced onto them; 150 and 300 columns span
    several 128-wide tiles with a partial last one, 7 rows fewer than the radius) equal the float64
    reference and the shifted-slice path in value (2e-5 absolute), and both paths' gradient in sigma
    equals the reference's float64 central difference (1e-3 relative: float32 sums over the frame,
    measured 3.5e-4 banded and 5.6e-4 slices at 40x150)."""
    import importlib

    gmod = importlib.import_module("jaxdenoise.filters.gaussian")
    c = rng(4).random((h, w, 3)).astype(np.float32)
    sigma = radius / 3.0
    monkeypatch.setattr(gmod, "BANDED_MIN_RADIUS", 0)
    banded = np.asarray(gaussian(c, sigma, radius=radius))
    g_banded = float(jax.grad(lambda s: gaussian(c, s, radius=radius).sum())(sigma))
    monkeypatch.setattr(gmod, "BANDED_MIN_RADIUS", 10 ** 9)
    slices = np.asarray(gaussian(c, sigma, radius=radius))
    g_slices = float(jax.grad(lambda s: gaussian(c, s, radius=radius).sum())(sigma))
    np.testing.assert_allclose(banded, ref_gaussian(c, sigma, radius), atol=2e-5)
    np.testing.assert_allclose(banded, slices, atol=2e-5)
    fd = (ref_gaussian(c, sigma + 1e-4, radius).sum() - ref_gaussian(c, sigma - 1e-4, radius).sum()) / 2e-4
    np.testing.assert_allclose([g_banded, g_slices], [fd, fd], rtol=1e-3)


def test_cross_bilateral_matches_reference_with_per_pixel_parameters():
    # 8 x 12 with radius 5: 11 column offsets, so the engine's 8-offset chunks include a masked tail
    h, w = 8, 12
    c, v, f, fv = frame(1, h, w)
    g = rng(2)
    ls = 0.05
    lc = g.random((h, w)).astype(np.float32)
    lfs = [0.002, (0.001 * g.random((h, w, 1))).astype(np.float32)]
    out = cross_bilateral(c, v, f, fv, ls, lc, lfs, radius=5)
    np.testing.assert_allclose(out, ref_cross_bilateral(c, v, f, fv, ls, lc, lfs, 5), atol=2e-5)


def test_cross_bilateral_one_channel_variance_is_eq_11():
    c, v, f, fv = frame(3)
    v1 = v[..., :1]
    out = cross_bilateral(c, v1, [], [], 0.1, 0.5, [], radius=2)
    np.testing.assert_allclose(out, ref_cross_bilateral(c, v1, [], [], 0.1, 0.5, [], 2), atol=2e-5)


def test_bilateral_matches_reference():
    c = frame(4)[0]
    np.testing.assert_allclose(bilateral(c, 0.3, 4.0, radius=2), ref_bilateral(c, 0.3, 4.0, 2), atol=2e-5)


def test_cross_nlm_matches_reference_5x5_patches():
    c, v, f, fv = frame(5)
    lp = rng(6).random((H, W)).astype(np.float32)
    lfs = [0.001, 0.0005]
    out = cross_nlm(c, v, f, fv, lp, lfs, radius=2)  # default patch_radius=2: 5x5 patches (Eq. 17)
    np.testing.assert_allclose(out, ref_cross_nlm(c, v, f, fv, lp, lfs, 2, 2), atol=2e-5)


def test_prefilter_matches_reference_and_uses_same_weights_for_variance():
    g = rng(7)
    f = g.random((H, W, 3)).astype(np.float32)
    v = (0.1 * g.random((H, W))).astype(np.float32)
    of, ov = prefilter_features(f, v, radius=2, patch_radius=1, lam=0.7)
    rf, rv = ref_prefilter(f, v, 2, 1, 0.7)
    np.testing.assert_allclose(of, rf, atol=2e-5)
    np.testing.assert_allclose(ov, rv, atol=2e-6)


def test_spatiotemporal_matches_reference():
    g = rng(8)
    t = 3
    c = g.random((t, 6, 5, 3)).astype(np.float32)
    v = (0.05 * g.random((t, 6, 5, 1))).astype(np.float32)
    f = [g.random((t, 6, 5, 3)).astype(np.float32)]
    fv = [(0.01 * g.random((t, 6, 5))).astype(np.float32)]
    out = spatiotemporal_cross_bilateral(c, v, f, fv, 0.3, 0.4, [0.001], radius=1, lam_temporal=0.2)
    vol = [(c[s], v[s], [f[0][s]]) for s in range(t)]
    ref = ref_cross_bilateral(None, None, None, [fv[0][1]], 0.3, 0.4, [0.001], 1,
                              frames=(vol, 1, [s - 1 for s in range(t)]), lt=0.2)
    np.testing.assert_allclose(out, ref, atol=2e-5)


def test_remove_spikes_matches_reference_and_removes_a_firefly():
    c = frame(9)[0]
    c[3, 4] = [1e6, 0.2, 0.3]
    out = remove_spikes(c)
    np.testing.assert_allclose(out, ref_spikes(c, 2.0), rtol=1e-6)
    assert float(np.max(out)) <= 1.0, "the 1e6 firefly must be replaced by the block median (<= 1)"


def test_clamp_outliers_cuts_isolated_spikes_only():
    """An isolated spike far above its neighbours and the floor is cut to factor x max(neighbours,
    floor), its hue kept; a bright 2x2 patch (a light), a pixel below factor x floor and the pixels
    around are left alone; leading axes pass through; bad arguments are refused by name."""
    lum = lambda v: 0.2126 * v[..., 0] + 0.7152 * v[..., 1] + 0.0722 * v[..., 2]
    c = np.full((8, 9, 3), 0.1, np.float32)
    c[2, 2] = [300.0, 200.0, 100.0]  # an isolated firefly
    c[5:7, 5:7] = 50.0  # a small light: every pixel has a bright neighbour
    c[0, 8] = 0.6  # brighter than its neighbours, below 4x the floor
    out = np.asarray(clamp_outliers(c, 4.0, 0.2))
    np.testing.assert_allclose(lum(out[2, 2]), 0.8, rtol=1e-5)  # neighbours below the floor: 4 x 0.2
    np.testing.assert_allclose(out[2, 2] / out[2, 2, 0], c[2, 2] / c[2, 2, 0], rtol=1e-5)  # hue
    keep = np.ones((8, 9), bool)
    keep[2, 2] = False
    np.testing.assert_array_equal(out[keep], c[keep])
    d = np.full((5, 5, 3), 0.02, np.float32)
    d[2, 2], d[2, 3] = 1000.0, 2.0  # a spike beside a moderately bright neighbour: 4x that neighbour
    np.testing.assert_allclose(lum(np.asarray(clamp_outliers(d, 4.0, 0.2))[2, 2]), 8.0, rtol=1e-5)
    batch = np.stack([c, c[::-1]])[None]  # (1, 2, 8, 9, 3)
    np.testing.assert_allclose(np.asarray(clamp_outliers(batch, 4.0, 0.2))[0, 1],
                               np.asarray(clamp_outliers(c[::-1], 4.0, 0.2)))
    alone = np.zeros((8, 9), bool)
    alone[0, 8] = alone[3, 3] = True  # no floor there: the pixel below 4x the floor is cut to 4x its neighbours
    cut = np.asarray(clamp_outliers(c, 4.0, 0.2, unfloored=alone))
    np.testing.assert_allclose(lum(cut[0, 8]), 0.4, rtol=1e-5)
    keep[0, 8] = False
    np.testing.assert_array_equal(cut[keep], c[keep])  # [3, 3] is no spike: unchanged
    np.testing.assert_array_equal(cut[2, 2], out[2, 2])
    for mask, match in ((alone[:, :4], "'unfloored' has shape"), (alone.astype(np.int32), "'unfloored' has dtype")):
        with pytest.raises(FilterError, match=match):
            clamp_outliers(c, 4.0, 0.2, unfloored=mask)
    per_image = np.asarray(clamp_outliers(np.stack([c, c[::-1]]), np.float32([4.0, 1e4]), 0.2))  # a factor per image
    np.testing.assert_array_equal(per_image[0], out)
    np.testing.assert_array_equal(per_image[1], c[::-1])
    for bad, match in (((c[..., :2], 4.0, 0.2), "'color'"), ((c, -1.0, 0.2), "'factor'"),
                       ((c, np.float32([4.0, 2.0]), 0.2), "'factor' has shape"),
                       ((np.stack([c, c]), np.float32([4.0, np.nan]), 0.2), "'factor' holds"),
                       ((c, 4.0, float("nan")), "'floor'"), ((c, 4.0, 0.0), "'floor'")):
        with pytest.raises(FilterError, match=match):
            clamp_outliers(*bad)
    bad_pixel = c.copy()
    bad_pixel[1, 1, 0] = np.nan
    with pytest.raises(FilterError, match="argument 'color' has 1 NaN/Inf"):
        clamp_outliers(bad_pixel, 4.0, 0.2)


def test_clamp_outliers_radius_cuts_blobs_and_keeps_lines_edges_and_corners():
    """With ``radius`` r the reference is the largest luminance at Chebyshev distance exactly r (a NumPy
    evaluation, zeros outside the image): a 3x3 blob (narrower than 2r - 1 = 5 px) is cut to factor x
    its ring's level, its hue kept; a 1-px line, a bright half-plane's edge and a bright square's corner
    cross the ring and pass unchanged; a radius above 1 with the median, or not an int >= 1, is refused."""
    lum = lambda v: 0.2126 * v[..., 0] + 0.7152 * v[..., 1] + 0.0722 * v[..., 2]
    rng = np.random.default_rng(3)
    x = (0.05 + rng.random((17, 19, 3)) * rng.random((17, 19, 1)) ** 6 * 40).astype(np.float32)
    for r in (2, 3):
        p = np.pad(lum(x.astype(np.float64)), r)
        ring = np.max([p[r + dy:r + dy + 17, r + dx:r + dx + 19] for dy in range(-r, r + 1)
                       for dx in range(-r, r + 1) if max(abs(dy), abs(dx)) == r], axis=0)
        limit = 1.5 * np.maximum(ring, 0.01)
        want = x * np.where(lum(x) > limit, limit / lum(x), 1.0)[..., None]
        np.testing.assert_allclose(np.asarray(clamp_outliers(x, 1.5, 0.01, radius=r)), want, rtol=2e-5)
    scene = np.full((24, 24, 3), 0.1, np.float32)
    scene[3:6, 3:6] = [30.0, 20.0, 10.0]  # a blob the network let through
    scene[12, 2:22] = 8.0  # a 1-px bright line
    scene[14:24, 14:24] = 5.0  # a bright square (its corner at (14, 14)) meeting the frame's edge
    out = np.asarray(clamp_outliers(scene, 2.0, 1e-3, radius=3))
    np.testing.assert_allclose(lum(out[4, 4]), 0.2, rtol=1e-5)  # 2 x the dim ring
    np.testing.assert_allclose(out[4, 4] / out[4, 4, 0], scene[4, 4] / scene[4, 4, 0], rtol=1e-5)
    keep = np.ones((24, 24), bool)
    keep[3:6, 3:6] = False
    np.testing.assert_array_equal(out[keep], scene[keep])
    assert np.all(lum(np.asarray(clamp_outliers(scene, 2.0, 1e-3))[3:6, 3:6]) > 10)  # radius 1: the blob passes
    for kw, match in (({"radius": 0}, "'radius'"), ({"radius": 2.0}, "'radius'"), ({"radius": True}, "'radius'"),
                      ({"radius": 2, "against": "median"}, "'radius' is 2 with against='median'")):
        with pytest.raises(FilterError, match=match):
            clamp_outliers(scene, 2.0, 1e-3, **kw)


def test_match_level_puts_the_low_pass_level_at_the_target_and_keeps_the_detail():
    """A textured image 20 % dark (red) and 10 % bright (blue) against a noisy target that is right on
    average comes back at the target's level, its detail (the ratio between neighbouring pixels) kept;
    degree 1 in (image, target, eps); frames of a batch matched one by one; bad arguments named."""
    rng = np.random.default_rng(3)
    truth = (0.5 + 0.4 * np.sin(np.arange(48)[:, None, None] / 3.0) * np.ones((48, 40, 3))).astype(np.float32)
    image = truth * np.float32([0.8, 1.0, 1.1])
    target = (truth * rng.gamma(16.0, 1 / 16, truth.shape)).astype(np.float32)  # noisy, right on average
    out = np.asarray(match_level(image, target, 8.0, 1e-3))
    level = out[8:-8, 8:-8].mean((0, 1)) / truth[8:-8, 8:-8].mean((0, 1))
    np.testing.assert_allclose(level, 1.0, atol=0.03)
    before = image[8:-8, 8:-8].mean((0, 1)) / truth[8:-8, 8:-8].mean((0, 1))
    assert abs(before[0] - 1) > 0.19 and abs(before[2] - 1) > 0.09
    gain = out / image
    assert float(np.max(np.abs(np.diff(gain, axis=0)))) < 0.05  # a smooth gain: detail kept
    np.testing.assert_allclose(np.asarray(match_level(4 * image, 4 * target, 8.0, 4e-3)), 4 * out, rtol=1e-5)
    batch = np.stack([image, image[::-1]])[None]
    np.testing.assert_allclose(np.asarray(match_level(batch, np.stack([target, target[::-1]])[None], 8.0, 1e-3))[0, 0],
                               out, rtol=1e-6)
    ints = match_level((image * 100).astype(np.int32), (target * 100).astype(np.int32), 8.0, 0.1)
    assert ints.dtype == np.float32 and float(np.max(np.abs(np.asarray(ints) / 100 - out))) < 0.02 * float(out.max())
    spiky = target.copy()
    spiky[20, 20] = 1e4  # an isolated firefly and a 2x2 cluster: cut before they count as level the image lacks
    spiky[30:32, 10:12] = 1e4
    lum = spiky @ np.float32([0.2126, 0.7152, 0.0722])
    pad = np.pad(lum, 1, mode="edge")
    med = np.median([pad[dy:dy + 48, dx:dx + 40] for dy in range(3) for dx in range(3)], axis=0)
    cut = np.minimum(lum, 2.0 * np.maximum(med, 0.1)) / lum
    np.testing.assert_allclose(np.asarray(match_to_input(image, spiky, 8.0, spike=2.0, floor=0.1, max_gain=1.5)),
                               np.asarray(match_level(image, spiky * cut[..., None], 8.0, 1e-3, max_gain=1.5)),
                               rtol=1e-5)
    assert float(np.max(np.asarray(match_to_input(image, spiky, 8.0, spike=2.0, floor=0.1)))) < 2.0
    np.testing.assert_allclose(image * np.asarray(input_gain(image, spiky, 8.0, spike=2.0, floor=0.1, max_gain=1.5)),
                               np.asarray(match_to_input(image, spiky, 8.0, spike=2.0, floor=0.1, max_gain=1.5)),
                               rtol=1e-6)  # the gains the two multiply by
    np.testing.assert_allclose(image * np.asarray(level_gain(image, target, 8.0, 1e-3)), out, rtol=1e-6)
    # output_cut: the target cut again at the factor times the output's brightest neighbour (or the floor), so a
    # light the output drew dark brightens its surroundings less; clamp_outliers reads that neighbourhood from
    # `reference`
    lit = target.copy()
    lit[23:26, 19:22] = 500.0  # a small light the image (the "output") does not have; the median cut keeps it
    twice = clamp_outliers(clamp_outliers(lit, 2.0, 0.1, against="median"), 2.0, 0.1, reference=image)
    np.testing.assert_allclose(np.asarray(input_gain(image, lit, 8.0, spike=2.0, floor=0.1, output_cut=True)),
                               np.asarray(level_gain(image, twice, 8.0, 1e-3)), rtol=1e-6)
    near = (slice(16, 33), slice(12, 29), 1)  # green: the image is right there
    assert float(np.max(np.asarray(input_gain(image, lit, 8.0, spike=2.0, floor=0.1))[near])) > 2.0
    assert float(np.max(np.asarray(input_gain(image, lit, 8.0, spike=2.0, floor=0.1, output_cut=True))[near])) < 1.2
    img_ring = np.pad(image @ np.float32([0.2126, 0.7152, 0.0722]), 1)
    ring = np.max([img_ring[1 + dy:49 + dy, 1 + dx:41 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                   if dy or dx], axis=0)
    lum_lit = lit @ np.float32([0.2126, 0.7152, 0.0722])
    want = lit * (np.minimum(lum_lit, 2.0 * np.maximum(ring, 0.1)) / lum_lit)[..., None]
    np.testing.assert_allclose(np.asarray(clamp_outliers(lit, 2.0, 0.1, reference=image)), want, rtol=1e-5)
    with pytest.raises(FilterError, match="'reference'"):
        clamp_outliers(lit, 2.0, 0.1, reference=image[:-1])
    assert float(np.max(np.asarray(match_level(image, clamp_outliers(spiky, 2.0, 0.1), 8.0, 1e-3)))) > 10.0
    np.testing.assert_allclose(np.asarray(clamp_outliers(spiky, 2.0, 0.1, against="median")),
                               spiky * cut[..., None], rtol=1e-6)
    with pytest.raises(FilterError, match="'against'"):
        clamp_outliers(spiky, 2.0, 0.1, against="mean")
    for kw, match in (({"spike": 0.0, "floor": 0.1}, "'spike'"), ({"spike": 2.0, "floor": np.nan}, "'floor'")):
        with pytest.raises(FilterError, match=match):
            match_to_input(image, spiky, 8.0, **kw)
    for spp in (1, 4, 16):  # by rate: a single sample's factor, cut at 1 + (spike - 1) / sqrt(spp)
        cut = 1 + 8 / spp ** 0.5
        np.testing.assert_array_equal(np.asarray(match_to_input(image, spiky, 8.0, spike=9.0, floor=0.1, spp=spp)),
                                      np.asarray(match_to_input(image, spiky, 8.0, spike=cut, floor=0.1)))
    frames = np.stack([spiky, spiky[::-1]])  # one rate per frame, also traced
    by_frame = jax.jit(lambda x, n: match_to_input(x, frames, 8.0, spike=9.0, floor=0.1, spp=n))
    np.testing.assert_allclose(np.asarray(by_frame(np.stack([image, image]), np.float32([1.0, 16.0])))[1],
                               np.asarray(match_to_input(image, spiky[::-1], 8.0, spike=3.0, floor=0.1)), rtol=1e-6)
    for kw, match in (({"spike": 0.5, "spp": 4}, "'spike'"), ({"spike": 2.0, "spp": 0}, "'spp'")):
        with pytest.raises(FilterError, match=match):
            match_to_input(image, spiky, 8.0, floor=0.1, **kw)
    dark = np.asarray(match_level(image, np.zeros_like(image), 8.0, 1e-3))  # a black target: gain eps / (G + eps)
    assert np.all(np.isfinite(dark)) and float(dark.max()) < 0.02 * float(image.max())
    for bad, match in (((image, target[:-1], 8.0, 1e-3), "'target'"), ((image[0], target[0], 8.0, 1e-3), "'image'"),
                       ((image, target, -1.0, 1e-3), "'sigma'"), ((image, target, 8.0, 0.0), "'eps'"),
                       ((image, target, float("nan"), 1e-3), "'sigma'")):
        with pytest.raises(FilterError, match=match):
            match_level(*bad)
    bad_pixel = target.copy()
    bad_pixel[1, 1, 0] = np.inf
    with pytest.raises(FilterError, match="'target'"):
        match_level(image, bad_pixel, 8.0, 1e-3)


# ----------------------------------------------------------------------------------------------
# properties


def test_constant_in_constant_out_every_filter():
    k = np.full((H, W, 3), 2.5, np.float32)
    v = np.full((H, W, 3), 0.01, np.float32)
    f, fv = frame(10)[2:]
    outs = {
        "gaussian": gaussian(k, 1.5, radius=3),
        "bilateral": bilateral(k, 0.1, 1.0, radius=3),
        "cross_bilateral": cross_bilateral(k, v, f, fv, 0.1, 1.0, [0.001, 0.002], radius=3),
        "cross_nlm": cross_nlm(k, v, f, fv, 1.0, [0.001, 0.002], radius=2),
        "prefilter": prefilter_features(k, v[..., 0], radius=2, patch_radius=1)[0],
        "spikes": remove_spikes(k),
    }
    for name, out in outs.items():
        np.testing.assert_allclose(out, 2.5, rtol=1e-6, err_msg=name)


def test_spatial_sigma_to_zero_is_identity():
    c, v, f, fv = frame(11)
    np.testing.assert_array_equal(gaussian(c, 0.0, radius=3), c)  # exact (tolerance 0)
    # lambda = 1/(2 sigma^2) = 1e12: every off-centre weight underflows to exactly 0 -> exact identity
    np.testing.assert_array_equal(bilateral(c, 1e12, 0.0, radius=2), c)
    np.testing.assert_array_equal(cross_bilateral(c, v, f, fv, 1e12, 0.0, [0.0, 0.0], radius=2), c)


def test_weights_sum_to_one_and_output_is_convex():
    """Filtering an all-ones image with non-constant guides returns ones (sum_j d_ij / sum_j d_ij = 1,
    tolerance 1e-6), and filtering a random image stays within its [min, max] (tolerance 1e-6)."""
    c, v, f, fv = frame(12)
    ones = np.ones_like(c)
    out = cross_bilateral(ones, v, f, fv, 0.05, 0.0, [0.001, 0.01], radius=3)
    np.testing.assert_allclose(out, 1.0, rtol=1e-6)
    out = cross_bilateral(c, v, f, fv, 0.05, 0.3, [0.001, 0.01], radius=3)
    assert float(out.min()) >= float(c.min()) - 1e-6 and float(out.max()) <= float(c.max()) + 1e-6


def test_underflow_falls_back_to_centre_pixel():
    """All off-centre weights underflow (lambda huge): the output is the centre pixel, exactly."""
    c, v, f, fv = frame(13)
    c = c * 1e6  # huge colour differences too
    out = cross_bilateral(c, v, f, fv, 0.0, 1e30, [0.0, 0.0], radius=3)
    np.testing.assert_array_equal(out, c)
    out = cross_nlm(c, v, f, fv, 1e30, [0.0, 0.0], radius=2)
    np.testing.assert_array_equal(out, c)
    g = jax.grad(lambda l: cross_bilateral(c, v, f, fv, 0.1, l, [0.0, 0.0], radius=1).sum())(1e30)
    assert np.isfinite(float(g)), "gradient at full underflow must be finite"


def _count_eqns(jaxpr) -> int:
    """Number of primitive applications in a jaxpr, nested jaxprs (checkpoint, loops) included."""
    n = 0
    for e in jaxpr.eqns:
        n += 1
        for p in e.params.values():
            inner = getattr(p, "jaxpr", p)
            if hasattr(inner, "eqns"):
                n += _count_eqns(inner)
    return n


def test_constant_feature_is_skipped_with_identical_output():
    c, v, f, fv = frame(14)
    const = np.full((H, W, 3), 0.7, np.float32)
    with_const = cross_bilateral(c, v, [f[0], const], [fv[0], None], 0.1, 0.5, [0.002, 5.0], radius=2)
    without = cross_bilateral(c, v, [f[0]], [fv[0]], 0.1, 0.5, [0.002], radius=2)
    np.testing.assert_array_equal(with_const, without)  # bit-identical (tolerance 0)
    kept = drop_constant_features([f[0], const], [fv[0], None], [0.002, 5.0])
    assert len(kept[0]) == 1 and kept[0][0] is f[0]
    # less work: the window loop traced with a constant feature is the loop traced without it
    def loop(fn):
        eqns = [e for e in jax.make_jaxpr(fn)(c).eqns if e.primitive.name == "scan"]  # fori_loop
        return _count_eqns(eqns[0].params["jaxpr"].jaxpr)
    assert loop(lambda x: cross_bilateral(x, v, [f[0], const], [fv[0], None], 0.1, 0.5, [0.002, 5.0], radius=2)) \
        == loop(lambda x: cross_bilateral(x, v, [f[0]], [fv[0]], 0.1, 0.5, [0.002], radius=2))


def test_jit_matches_eager_and_extreme_inputs_stay_finite():
    c, v, f, fv = frame(15)
    fn = jax.jit(lambda c, v, l: cross_bilateral(c, v, f, fv, l, 0.5, [0.002, 0.01], radius=2))
    np.testing.assert_allclose(fn(c, v, 0.1), cross_bilateral(c, v, f, fv, 0.1, 0.5, [0.002, 0.01], radius=2),
                               rtol=1e-6, atol=1e-7)
    black = np.zeros_like(c)
    assert np.all(np.isfinite(fn(black, np.zeros_like(v), 0.1))), "all-black, zero-variance frame"
    one = cross_bilateral(c[:1, :1], v[:1, :1], [], [], 0.1, 0.5, [], radius=27)
    np.testing.assert_array_equal(one, c[:1, :1])  # 1x1 image: only the centre exists
    odd = cross_nlm(c[:5, :3], v[:5, :3], [], [], 1.0, [], radius=3)
    assert odd.shape == (5, 3, 3) and np.all(np.isfinite(odd))
    half = cross_bilateral(c.astype(np.float16), v.astype(np.float16), [], [], 0.1, 0.5, [], radius=2)
    assert half.dtype == np.float16 and np.all(np.isfinite(np.asarray(half, np.float32)))


# ----------------------------------------------------------------------------------------------
# gradients against finite differences, every filter parameter (float64, tiny sizes)


def test_gradients_every_parameter():
    with jax.enable_x64(True):
        g = np.random.default_rng(16)
        h, w = 5, 6
        c = g.random((h, w, 3))
        v = 0.1 * g.random((h, w, 3)) + 0.01
        f = [g.random((h, w, 3)), g.random((h, w, 1))]
        fv = [0.05 * g.random((h, w)) + 0.01, None]
        ls, lc = 0.3 + 0.2 * g.random((h, w)), 0.5 + 0.2 * g.random((h, w))
        lf = [0.003 + 0.001 * g.random((h, w)), 0.0002]
        kw = dict(order=1, modes=("rev",), atol=1e-5, rtol=1e-4, eps=1e-7)  # float64: tiny steps are exact enough

        def check_grads(fn, args, **kw):  # jit once instead of dispatching op by op
            _check_grads(jax.jit(fn), args, **kw)
        check_grads(lambda s: gaussian(c, s, radius=2), (0.8,), **kw)
        check_grads(lambda s: gaussian(c, s, radius=1), (0.8 + 0.3 * g.random((h, w)),), **kw)
        check_grads(lambda a, b: bilateral(c, a, b, radius=1), (ls, 2.0), **kw)
        check_grads(lambda a, b, l0, l1: cross_bilateral(c, v, f, fv, a, b, [l0, l1], radius=1),
                    (ls, lc, lf[0], lf[1]), **kw)
        check_grads(lambda p, l0, l1: cross_nlm(c, v, f, fv, p, [l0, l1], radius=1, patch_radius=1),
                    (lc, lf[0], lf[1]), **kw)
        check_grads(lambda lam: prefilter_features(f[0], fv[0], radius=1, patch_radius=1, lam=lam)[0],
                    (0.8,), **kw)
        cv, vv = np.stack([c, c[::-1]]), np.stack([v, v])
        fvv = [np.stack([f[0], f[0][:, ::-1]])]
        check_grads(lambda a, b, l0, t: spatiotemporal_cross_bilateral(
            cv, vv, fvv, [None], a, b, [l0], radius=1, lam_temporal=t, center=0), (ls, lc, 0.003, 0.5), **kw)
        # and with respect to the image (the filters are differentiable in their inputs too)
        check_grads(lambda x: cross_bilateral(x, v, f, fv, 0.3, 0.5, lf, radius=1), (c,), **kw)


# ----------------------------------------------------------------------------------------------
# bad input


@pytest.mark.parametrize("call, match", [
    (lambda c, v: cross_bilateral(c[..., 0], v, [], [], 0.1, 0.1, [], radius=1), "'color'"),
    (lambda c, v: cross_bilateral(c, v[:4], [], [], 0.1, 0.1, [], radius=1), "'color_var'"),
    (lambda c, v: cross_bilateral(c, v, [c], [], 0.1, 0.1, [0.1], radius=1), "'feature_vars'"),
    (lambda c, v: cross_bilateral(c, v, [], [], -1.0, 0.1, [], radius=1), "'lam_spatial'"),
    (lambda c, v: cross_bilateral(c, v, [], [], np.ones((3, 3)), 0.1, [], radius=1), "'lam_spatial'"),
    (lambda c, v: cross_bilateral(c, v, [], [], 0.1, 0.1, [], radius=1.5), "'radius'"),
    (lambda c, v: cross_bilateral(np.where(c > 0.5, np.nan, c), v, [], [], 0.1, 0.1, [], radius=1), "NaN"),
    (lambda c, v: cross_nlm(c, None, [], [], 0.1, [], radius=1), "'color_var'"),
    (lambda c, v: gaussian(c, -1.0), "'sigma'"),
    (lambda c, v: spatiotemporal_cross_bilateral(c, v, [], [], 0.1, 0.1, [], radius=1), "'color'"),
    (lambda c, v: remove_spikes(c, n_std=float("nan")), "'n_std'"),
])
def test_bad_input_raises_naming_the_argument(call, match):
    c, v = frame(17)[:2]
    with pytest.raises(FilterError, match=match):
        call(c, v)


# ----------------------------------------------------------------------------------------------
# the registered `bilateral` and `nlm` methods


def test_methods_use_the_features_the_frame_has():
    from jaxdenoise.buffers import Buffers
    from jaxdenoise.methods import get
    from jaxdenoise.methods import bilateral as mod

    c, v, f, fv = frame(18)
    b = Buffers(color=c, color_var=v, normal=f[0] * 2 - 1, normal_var=fv[0][..., None], visibility=f[1])
    m = get("bilateral", radius=2, prefilter=False, spike_removal=False, feature_sigmas=(1.0, 0.5, 1.0, 1.0, 2.0))
    assert m.needs() >= {"color", "color_var", "normal", "position", "albedo", "albedo2", "visibility"}
    assert m.required() == {"color", "color_var"}
    out = m.apply({}, b)
    lam = mod.lambdas(m.config)  # lam_features in config.features order: position, normal, ..., visibility
    assert lam["lam_features"][1] == 0.5 / 0.5 ** 2 and lam["lam_features"][4] == 0.5 / 2.0 ** 2
    # position and both albedos are absent: their terms are left out; visibility has no variance
    want = cross_bilateral(c, v, [b.normal, b.visibility], [b.normal_var, None], lam["lam_spatial"],
                           lam["lam_color"], [lam["lam_features"][1], lam["lam_features"][4]], radius=2)
    np.testing.assert_allclose(out, want, rtol=1e-6, atol=1e-7)
    n = get("nlm", radius=1, patch_radius=1)  # with the prefilter and spike removal
    out = n.apply({}, b)
    assert out.shape == c.shape and np.all(np.isfinite(out))
    with pytest.raises(Exception, match="color_var"):
        m.apply({}, Buffers(color=c))


def test_memory_does_not_grow_with_the_window():
    """The per-offset engine: XLA's temporaries (forward and backward) stay flat from a 25x25 to a
    49x49 window, the weight tensor is never materialized (tolerance: at most 1.5x, where
    materializing would be 3.8x). Since the row blocks (`_window.py`, "Row blocks") the temporaries
    hold each neighbour array's rows over the window's width, and the backward pass one such block
    per column step: the frame is wide (32x256) so that W + 2r stays close to W, and both windows
    have several column steps (a 7x7 window is one step a row and holds no block carry)."""
    c, v, f, fv = frame(19, 32, 256)

    def temp(r, grad):
        def filt(ls):
            return cross_bilateral(c, v, f, fv, ls, 0.5, [0.01, 0.01], radius=r, engine="offsets")

        fn = jax.grad(lambda ls: filt(ls).sum()) if grad else filt
        return jax.jit(fn).lower(0.1).compile().memory_analysis().temp_size_in_bytes

    for grad in (False, True):
        small, large = temp(12, grad), temp(24, grad)
        assert large <= 1.5 * small, f"grad={grad}: {large} bytes at r=24 vs {small} at r=12"


def test_tiled_engine_memory_is_one_group_not_the_weight_tensor(monkeypatch):
    """The tiled engine holds one group of pixel pairs at a time (forward, and backward through its
    checkpoint): with a group budget of 2^14 pairs, XLA's temporaries at r = 12 on 128x128 stay below
    a quarter of the whole weight tensor (41 MB; measured 0.6 MB forward, 5.5 MB backward at 64x64)."""
    from jaxdenoise.filters import _tiles

    monkeypatch.setattr(_tiles, "GROUP_PAIRS", 1 << 14)
    c, v, f, fv = frame(19, 128, 128)
    r = 12
    full = 128 * 128 * (2 * r + 1) ** 2 * 4

    def filt(ls):
        return cross_bilateral(c, v, f, fv, ls, 0.5, [0.01, 0.01], radius=r)

    for fn in (filt, jax.grad(lambda ls: filt(ls).sum())):
        temp = jax.jit(fn).lower(0.1).compile().memory_analysis().temp_size_in_bytes
        assert temp <= full / 4, f"{temp} bytes of temporaries; the weight tensor is {full}"


@pytest.mark.parametrize("h,w,radius", [(13, 21, 4), (9, 7, 12), (1, 1, 3)])
def test_tiled_engine_equals_the_offset_engine(h, w, radius):
    """Values and gradients of the tiled engine (default) against the per-offset one on an odd size
    (3x3 tiles), a window larger than the frame (7x7 tiles) and a 1x1 frame (2x2 tiles). Values:
    2e-5 abs between the engines (the same float32 terms summed in another order). Gradients: each
    engine in float32 within 2e-3 of the float64 result, relative to |g| + 1e-3 (both engines
    measured up to 8e-4 here and on 17x10 with r = 1)."""
    c, v, f, fv = frame(20, h, w)
    g = rng(21)
    ls = (0.05 + 0.1 * g.random((h, w))).astype(np.float32)
    lf = [(0.002 * g.random((h, w))).astype(np.float32), 0.01]

    def run(engine, x64=False):
        with jax.enable_x64(x64):
            cast = (lambda a: np.asarray(a, np.float64)) if x64 else (lambda a: a)

            def loss(ls, l0, x):
                out = cross_bilateral(x, cast(v[..., :1]), [cast(a) for a in f], [None if a is None else cast(a)
                                      for a in fv], ls, 0.4, [l0, lf[1]], radius=radius, engine=engine)
                return (out * out).sum(), out
            (_, out), grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True))(
                cast(ls), cast(lf[0]), cast(c))
            return np.asarray(out, np.float64), [np.asarray(a, np.float64) for a in grads]

    (o1, g1), (o2, g2), (_, g64) = run("tiles"), run("offsets"), run("offsets", x64=True)
    np.testing.assert_allclose(o1, o2, atol=2e-5)
    for a, b, ref in zip(g1, g2, g64):
        assert np.max(np.abs(a - ref) / (np.abs(ref) + 1e-3)) <= 2e-3
        assert np.max(np.abs(b - ref) / (np.abs(ref) + 1e-3)) <= 2e-3



def test_every_cross_bilateral_takes_both_engines():
    """The plain bilateral and the spatio-temporal filter on both engines (17x10, r = 2, 2x2 tiles),
    tolerance 2e-5 abs; an unknown engine is refused by name."""
    h, w, radius = 17, 10, 2
    c, v, f, fv = frame(22, h, w)
    ls = (0.05 + 0.1 * rng(23).random((h, w))).astype(np.float32)
    np.testing.assert_allclose(bilateral(c, 0.2, 3.0, radius=radius),
                               bilateral(c, 0.2, 3.0, radius=radius, engine="offsets"), atol=2e-5)
    vol = np.stack([c, c[::-1], c[:, ::-1]])
    fvol = [np.stack([f[0]] * 3)]
    st = [spatiotemporal_cross_bilateral(vol, np.stack([v] * 3), fvol, [None], ls, 0.4, [0.01], radius=radius,
                                         lam_temporal=0.3, engine=e) for e in ("tiles", "offsets")]
    np.testing.assert_allclose(st[0], st[1], atol=2e-5)
    with pytest.raises(FilterError, match="'engine'"):
        bilateral(c, 0.2, 3.0, radius=radius, engine="fft")
