"""Metrics against closed forms and scikit-image's SSIM (jaxdenoise.metrics)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from jaxdenoise import color, metrics
from jaxdenoise.errors import JaxdenoiseError


def _pair(shape, seed=0, noise=0.2):
    rng = np.random.default_rng(seed)
    ref = rng.uniform(0.0, 1.4, shape).astype(np.float32)  # some values above 1 exercise the clip
    x = (ref + rng.normal(0.0, noise, shape)).astype(np.float32)
    return x, ref


def _skimage_ssim(x, ref):
    # Wang et al. 2004 settings (docs/metrics.md) on the tone-mapped images, in float64
    return structural_similarity(np.asarray(color.tonemap(x), np.float64), np.asarray(color.tonemap(ref), np.float64),
                                 gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
                                 channel_axis=-1)


def test_relmse_closed_form():
    ref = np.array([[[0.0, 1.0, 3.0]]], np.float32)
    x = np.array([[[0.1, 1.5, 3.0]]], np.float32)
    want = (0.01 / 0.01 + 0.25 / 1.01 + 0.0) / 3
    assert abs(float(metrics.relmse(x, ref)) - want) < 1e-6  # float32 tolerance
    assert abs(float(metrics.relmse(x, ref, eps=1.0)) - (0.01 / 1 + 0.25 / 2) / 3) < 1e-6


def test_mse_psnr_closed_form():
    ref = np.full((4, 4, 3), 0.25, np.float32)
    x = np.full((4, 4, 3), 0.5, np.float32)
    assert abs(float(metrics.mse(x, ref)) - 0.0625) < 1e-7
    d = 0.5 ** (1 / 2.2) - 0.25 ** (1 / 2.2)  # PSNR on tone-mapped values, data range 1
    assert abs(float(metrics.psnr(x, ref)) - (-10 * math.log10(d * d))) < 1e-3  # dB
    # values above 1 are clipped by the tone map: 2 and 5 both map to 1 -> identical -> +inf
    assert float(metrics.psnr(np.full((2, 2, 3), 2.0), np.full((2, 2, 3), 5.0))) == math.inf


def test_identical_images():
    x, _ = _pair((12, 13, 3))
    assert float(metrics.relmse(x, x)) == 0.0
    assert abs(float(metrics.ssim(x, x)) - 1.0) < 1e-6  # float32 rounding only


@pytest.mark.parametrize("shape,seed", [((11, 11, 3), 0), ((32, 24, 3), 1), ((19, 40, 1), 2), ((16, 16, 4), 3)])
def test_ssim_matches_skimage(shape, seed):
    x, ref = _pair(shape, seed)
    got = float(metrics.ssim(x, ref))
    want = _skimage_ssim(x, ref)
    assert abs(got - want) < 1e-4, (got, want)  # the brief's agreement tolerance


def test_ssim_matches_skimage_structured_image():
    # a smooth gradient with an edge and an HDR highlight, plus noise
    yy, xx = np.mgrid[0:24, 0:30].astype(np.float32)
    ref = np.stack([xx / 30, yy / 24, (xx > 15).astype(np.float32) * 0.8], -1)
    ref[5:8, 5:8] = 20.0
    x = ref + np.random.default_rng(4).normal(0, 0.05, ref.shape).astype(np.float32)
    assert abs(float(metrics.ssim(x, ref)) - _skimage_ssim(x, ref)) < 1e-4


def test_ssim_map_is_what_ssim_averages_and_matches_skimages_full_map():
    """`ssim_map`: the (H - 10, W - 10, C) values inside the border; their mean is `ssim_per_image`,
    and each channel equals scikit-image's full SSIM image cropped by its 5-pixel border."""
    xs, refs = zip(*[_pair((17, 21, 3), s) for s in range(2)])
    x, ref = np.stack(xs), np.stack(refs)
    m = np.asarray(metrics.ssim_map(x, ref))
    assert m.shape == (2, 7, 11, 3)
    np.testing.assert_allclose(m.mean(axis=(1, 2, 3)), np.asarray(metrics.ssim_per_image(x, ref)), atol=1e-6)
    tx, tr = np.asarray(color.tonemap(xs[0])), np.asarray(color.tonemap(refs[0]))
    _, full = structural_similarity(tx, tr, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=1.0, channel_axis=-1, full=True)
    np.testing.assert_allclose(m[0], full[5:-5, 5:-5], atol=1e-4)  # the brief's agreement tolerance
    with pytest.raises(JaxdenoiseError, match="ssim_map: images are 10x21"):
        metrics.ssim_map(x[:, :10], ref[:, :10])


def test_batched_and_per_image():
    xs, refs = zip(*[_pair((12, 14, 3), s) for s in range(3)])
    x, ref = np.stack(xs), np.stack(refs)
    per = np.asarray(metrics.ssim_per_image(x, ref))
    assert per.shape == (3,)
    for i in range(3):
        assert abs(per[i] - _skimage_ssim(xs[i], refs[i])) < 1e-4
    assert abs(float(metrics.ssim(x, ref)) - per.mean()) < 1e-6
    rel = np.asarray(metrics.relmse_per_image(x, ref))
    np.testing.assert_allclose(rel, [float(metrics.relmse(a, b)) for a, b in zip(xs, refs)], rtol=1e-6)
    assert abs(float(metrics.relmse(x, ref)) - rel.mean()) < 1e-6 * rel.mean()
    ps = np.asarray(metrics.psnr_per_image(x, ref))
    np.testing.assert_allclose(ps, [float(metrics.psnr(a, b)) for a, b in zip(xs, refs)], rtol=1e-6)
    assert np.asarray(metrics.mse_per_image(x, ref)).shape == (3,)
    # two batch axes
    assert np.asarray(metrics.relmse_per_image(x[None], ref[None])).shape == (1, 3)


def test_jit_and_grad():
    x, ref = _pair((12, 12, 3))
    f = jax.jit(lambda a, b: jnp.stack([metrics.relmse(a, b), metrics.mse(a, b), metrics.psnr(a, b),
                                        metrics.ssim(a, b)]))
    eager = np.array([float(metrics.relmse(x, ref)), float(metrics.mse(x, ref)), float(metrics.psnr(x, ref)),
                      float(metrics.ssim(x, ref))])
    np.testing.assert_allclose(np.asarray(f(x, ref)), eager, rtol=1e-5)
    for fn in (metrics.relmse, metrics.ssim, metrics.psnr):
        g = jax.grad(lambda a: fn(a, ref))(jnp.asarray(x))
        assert np.all(np.isfinite(np.asarray(g))), fn.__name__


def test_float16_inputs_promoted():
    x = np.full((2, 2, 3), 300.0, np.float16)
    ref = np.zeros((2, 2, 3), np.float16)
    # (300^2) / 0.01 = 9e6 overflows float16; computed in float32 it is exact
    assert abs(float(metrics.relmse(x, ref)) - 9e6) < 1.0


def test_temporal_error():
    t = np.arange(4, dtype=np.float32)[:, None, None, None]
    refs = np.broadcast_to(0.5 + 0.1 * t, (4, 3, 3, 3)).astype(np.float32)
    # following the reference's change exactly, even with a constant offset: zero temporal error
    assert abs(float(metrics.temporal_error(refs + 0.3, refs))) < 1e-10
    # a flicker of +-0.2 on a static reference of 0.5
    static = np.full((3, 2, 2, 3), 0.5, np.float32)
    flick = static + np.array([0.2, -0.2, 0.2], np.float32)[:, None, None, None]
    want = 0.4 ** 2 / (0.25 + 0.01)
    per = np.asarray(metrics.temporal_error_per_frame(flick, static))
    np.testing.assert_allclose(per, [want, want], rtol=1e-5)
    assert abs(float(metrics.temporal_error(flick, static)) - want) < 1e-5 * want
    # a batch of two sequences
    assert np.asarray(metrics.temporal_error_per_frame(np.stack([flick, static]), np.stack([static, static]))).shape \
        == (2, 2)


def test_halo_pixels_counts_light_far_above_the_references_local_maximum():
    """A pixel counts when its channel mean is above 4x the reference's largest channel mean within 4 px
    (Chebyshev; the square clipped at the border), against a direct loop; a mask keeps its pixels only;
    a non-finite pixel counts; a batch sums its images."""
    rng = np.random.default_rng(3)
    ref = (rng.random((23, 17, 3)) ** 8).astype(np.float32)
    x = (ref * rng.random((23, 17, 3)) * 12).astype(np.float32)
    o, r = x.mean(-1), ref.mean(-1)
    want = np.array([[o[i, j] > 4 * r[max(i - 4, 0):i + 5, max(j - 4, 0):j + 5].max() + 1e-6
                      for j in range(17)] for i in range(23)])
    assert 0 < want.sum() < want.size and metrics.halo_pixels(x, ref) == want.sum()
    mask = rng.random((23, 17)) > 0.5
    assert metrics.halo_pixels(x, ref, mask) == (want & mask).sum()
    assert metrics.halo_pixels(ref * 3.9, ref) == 0  # within 4x of itself everywhere
    bad = x.copy()
    bad[0, 0] = np.nan
    assert metrics.halo_pixels(bad, ref) == want.sum() + (not want[0, 0])
    assert metrics.halo_pixels(np.stack([x, ref]), np.stack([ref, ref])) == want.sum()
    with pytest.raises(ValueError, match=r"halo_pixels: 'mask' has shape \(23, 16\)"):
        metrics.halo_pixels(x, ref, mask[:, :16])


def test_bad_input():
    x, ref = _pair((12, 12, 3))
    with pytest.raises(ValueError, match=r"'x' has shape \(12, 12, 3\) but 'ref' has shape \(12, 11, 3\)"):
        metrics.relmse(x, ref[:, :11])
    with pytest.raises(ValueError, match=r"'x' has shape \(12, 12\); expected \(\.\.\., H, W, C\)"):
        metrics.mse(x[..., 0], ref[..., 0])
    with pytest.raises(ValueError, match="7x5 pixels .* needs at least 11x11"):
        metrics.ssim(x[:7, :5], ref[:7, :5])
    with pytest.raises(ValueError, match="'eps' must be > 0"):
        metrics.relmse(x, ref, eps=0.0)
    with pytest.raises(ValueError, match="T >= 2"):
        metrics.temporal_error(x[None], ref[None])
