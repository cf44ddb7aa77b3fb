"""Image error metrics (docs/architecture.md "Error against run time"; conventions in ``docs/metrics.md``).

All functions take a result ``x`` and a reference ``ref`` of the same shape ``(..., H, W, C)``
(one HWC image, or any number of leading batch axes), numpy or jax arrays, and are jittable
(shape checks happen at trace time). Computation is in at least float32 (float16 inputs are
promoted: squared HDR errors overflow float16).

- `relmse`: mean((x - ref)^2 / (ref^2 + eps)), eps = 0.01 (Kalantari et al. 2015 Eq. 8 without the
  n/2 training factor; Rousselle et al. 2011), over pixels and channels, on linear radiance.
- `mse`: mean squared error on linear radiance.
- `psnr`, `ssim`: on tone-mapped images ``clip(x, 0, 1) ** (1/2.2)`` (`jaxdenoise.color.tonemap`)
  with data range 1. `ssim` is the Gaussian-window SSIM of Wang et al. 2004 (sigma 1.5, 11 taps,
  K1 = 0.01, K2 = 0.03, population covariances), computed per channel and averaged, with the
  (win_size - 1) // 2 = 5 pixel border excluded exactly as scikit-image's
  ``structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1, channel_axis=-1)`` does.
- `temporal_error`: RelMSE-style error of the temporal differences of a sequence against those of
  its references (Chaitanya et al. 2017, Sec. 4.4, temporal loss L_t, as a squared relative error).
- `halo_pixels`: how many pixels draw light the reference has nowhere near: the result (mean of the
  channels) above `HALO_FACTOR` (4) times the reference's largest value in the `HALO_WINDOW` (9x9)
  square around the pixel (issue 34's check; a count, per image, not a mean).

The plain functions return one scalar: the mean over every image of the batch (for `relmse` and
`mse` that equals the pooled mean; for `psnr` and `ssim` it is the mean of the per-image values).
The ``*_per_image`` versions return an array of the leading (batch) shape, ``()`` for one image.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdenoise.color import tonemap
from .errors import JaxdenoiseError

RELMSE_EPS = 0.01  # Kalantari et al. 2015, Eq. 8: "0.01 in our implementation"
SSIM_SIGMA = 1.5  # Wang et al. 2004, Sec. III-C: 11x11 circular-symmetric Gaussian, sigma 1.5
SSIM_TRUNCATE = 3.5  # scikit-image's truncation for gaussian_weights: radius int(3.5*1.5+0.5) = 5
SSIM_K1, SSIM_K2 = 0.01, 0.03  # Wang et al. 2004, Eq. 7-9 constants
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)
SSIM_WIN = 2 * SSIM_RADIUS + 1  # 11


def _as_float(name: str, fn: str, a: Any) -> jnp.ndarray:
    if not hasattr(a, "shape"):
        a = np.asarray(a)
    a = jnp.asarray(a)
    if not (jnp.issubdtype(a.dtype, jnp.floating) or jnp.issubdtype(a.dtype, jnp.integer)):
        raise TypeError(f"{fn}: '{name}' must be a real array, got dtype {a.dtype}")
    return a.astype(jnp.promote_types(a.dtype, jnp.float32))


def _pair(fn: str, x: Any, ref: Any, *, min_ndim: int = 3, layout: str = "(..., H, W, C)"):
    x = _as_float("x", fn, x)
    ref = _as_float("ref", fn, ref)
    for name, a in (("x", x), ("ref", ref)):
        if a.ndim < min_ndim:
            raise JaxdenoiseError(f"{fn}: '{name}' has shape {tuple(a.shape)}; expected {layout}")
    if x.shape != ref.shape:
        raise JaxdenoiseError(f"{fn}: 'x' has shape {tuple(x.shape)} but 'ref' has shape {tuple(ref.shape)}; "
                         "they must match")
    dt = jnp.promote_types(x.dtype, ref.dtype)
    return x.astype(dt), ref.astype(dt)


def _check_eps(fn: str, eps: Any) -> None:
    if isinstance(eps, (int, float)) and not eps > 0:
        raise JaxdenoiseError(f"{fn}: 'eps' must be > 0 (it guards division by a zero reference), got {eps}")


# -- RelMSE / MSE ----------------------------------------------------------------------------------
@jax.jit
def _relmse_map(x, ref, eps):
    # eps keeps the denominator >= eps where the reference is black (the papers' 0.01). The ratio is
    # formed before squaring, with hypot(ref, sqrt(eps)) = sqrt(ref^2 + eps): squaring a radiance
    # above ~1.8e19 would overflow float32 and turn a valid (huge) reference into inf / inf = NaN.
    return jnp.square((x - ref) / jnp.hypot(ref, jnp.sqrt(jnp.asarray(eps, ref.dtype))))


def relmse_per_image(x: Any, ref: Any, eps: float = RELMSE_EPS) -> jnp.ndarray:
    """RelMSE of each image: mean over H, W, C of (x - ref)^2 / (ref^2 + eps)."""
    _check_eps("relmse_per_image", eps)
    x, ref = _pair("relmse_per_image", x, ref)
    return jnp.mean(_relmse_map(x, ref, eps), axis=(-3, -2, -1))


def relmse(x: Any, ref: Any, eps: float = RELMSE_EPS) -> jnp.ndarray:
    """Relative MSE, mean((x - ref)^2 / (ref^2 + eps)) over pixels, channels and images.

    Kalantari et al. 2015, Eq. 8 (without its n/2 sample-count weight, which only serves training);
    eps = 0.01 as in the papers.
    """
    _check_eps("relmse", eps)
    x, ref = _pair("relmse", x, ref)
    return jnp.mean(_relmse_map(x, ref, eps))


def mse_per_image(x: Any, ref: Any) -> jnp.ndarray:
    """MSE of each image on linear radiance, mean over H, W, C."""
    x, ref = _pair("mse_per_image", x, ref)
    return jnp.mean(jnp.square(x - ref), axis=(-3, -2, -1))


def mse(x: Any, ref: Any) -> jnp.ndarray:
    """Mean squared error on linear radiance over pixels, channels and images."""
    x, ref = _pair("mse", x, ref)
    return jnp.mean(jnp.square(x - ref))


# -- PSNR ------------------------------------------------------------------------------------------
@jax.jit
def _psnr_per_image(x, ref):
    err = jnp.mean(jnp.square(tonemap(x) - tonemap(ref)), axis=(-3, -2, -1))
    # Data range 1 after tone mapping. Identical images give +inf (the standard convention), which
    # stays a valid float for sorting and tables rather than an error.
    return -10.0 * jnp.log10(err)


def psnr_per_image(x: Any, ref: Any) -> jnp.ndarray:
    """PSNR in dB of each image, 10 log10(1 / MSE) on tone-mapped images (data range 1); +inf if equal."""
    x, ref = _pair("psnr_per_image", x, ref)
    return _psnr_per_image(x, ref)


def psnr(x: Any, ref: Any) -> jnp.ndarray:
    """Mean over images of `psnr_per_image` (one image: its PSNR)."""
    x, ref = _pair("psnr", x, ref)
    return jnp.mean(_psnr_per_image(x, ref))


# -- SSIM ------------------------------------------------------------------------------------------
def _gauss_taps() -> np.ndarray:
    # scipy.ndimage.gaussian_filter1d's kernel: exp(-t^2 / (2 sigma^2)), t = -r..r, normalized.
    t = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    w = np.exp(-0.5 * (t / SSIM_SIGMA) ** 2)
    return (w / w.sum()).astype(np.float32)


_TAPS = _gauss_taps()


def _blur_valid(a: jnp.ndarray) -> jnp.ndarray:
    """Separable 11-tap Gaussian over the H and W axes (-3, -2), 'valid' part only.

    scikit-image filters with mode='reflect' and then discards a (win - 1) // 2 = radius border;
    every kept pixel's window lies inside the image, so the valid convolution is exactly the kept
    region and the padding mode never matters.
    """
    h, w = a.shape[-3], a.shape[-2]
    n = 2 * SSIM_RADIUS
    a = sum(float(_TAPS[k]) * a[..., k:h - n + k, :, :] for k in range(SSIM_WIN))
    return sum(float(_TAPS[k]) * a[..., :, k:w - n + k, :] for k in range(SSIM_WIN))


def _ssim_map(x, ref):
    x, y = tonemap(x), tonemap(ref)
    c1 = (SSIM_K1 * 1.0) ** 2  # data range 1
    c2 = (SSIM_K2 * 1.0) ** 2
    ux, uy = _blur_valid(x), _blur_valid(y)
    vx = _blur_valid(x * x) - ux * ux  # population (co)variances: cov_norm = 1 (Wang 2004)
    vy = _blur_valid(y * y) - uy * uy
    vxy = _blur_valid(x * y) - ux * uy
    return ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))


@jax.jit
def _ssim_per_image(x, ref):
    # mean over the kept pixels of each channel, then over channels (skimage's channel_axis mean)
    return jnp.mean(_ssim_map(x, ref), axis=(-3, -2, -1))


def _ssim_check(fn: str, x: Any, ref: Any):
    x, ref = _pair(fn, x, ref)
    h, w = x.shape[-3], x.shape[-2]
    if h < SSIM_WIN or w < SSIM_WIN:
        raise JaxdenoiseError(f"{fn}: images are {h}x{w} pixels (H x W); SSIM's {SSIM_WIN}x{SSIM_WIN} Gaussian "
                         f"window (sigma {SSIM_SIGMA}) needs at least {SSIM_WIN}x{SSIM_WIN}")
    return x, ref


def ssim_map(x: Any, ref: Any) -> jnp.ndarray:
    """The SSIM of every pixel and channel whose window lies inside the image, ``(..., H - 10, W - 10,
    C)``: what `ssim_per_image` averages (where in a frame a method wins or loses SSIM)."""
    x, ref = _ssim_check("ssim_map", x, ref)
    return jax.jit(_ssim_map)(x, ref)


def ssim_per_image(x: Any, ref: Any) -> jnp.ndarray:
    """SSIM of each image on tone-mapped images (Wang et al. 2004, Gaussian window; see module doc)."""
    x, ref = _ssim_check("ssim_per_image", x, ref)
    return _ssim_per_image(x, ref)


def ssim(x: Any, ref: Any) -> jnp.ndarray:
    """Mean over images of `ssim_per_image` (one image: its SSIM). Images need H, W >= 11."""
    x, ref = _ssim_check("ssim", x, ref)
    return jnp.mean(_ssim_per_image(x, ref))


# -- temporal stability ----------------------------------------------------------------------------
@jax.jit
def _temporal_map(frames, refs, eps):
    d = frames[..., 1:, :, :, :] - frames[..., :-1, :, :, :]
    dr = refs[..., 1:, :, :, :] - refs[..., :-1, :, :, :]
    # Normalized by the squared mean reference radiance of the two frames (RelMSE's relative
    # weighting); eps keeps the denominator >= eps where the reference is black.
    scale = jnp.square(0.5 * (refs[..., 1:, :, :, :] + refs[..., :-1, :, :, :])) + eps
    return jnp.square(d - dr) / scale


def _temporal_check(fn: str, frames: Any, refs: Any, eps: Any):
    _check_eps(fn, eps)
    frames, refs = _pair(fn, frames, refs, min_ndim=4, layout="(..., T, H, W, C) with T >= 2 frames")
    if frames.shape[-4] < 2:
        raise JaxdenoiseError(f"{fn}: 'frames' has {frames.shape[-4]} frame(s) on the time axis (axis -4 of "
                         f"shape {tuple(frames.shape)}); a temporal error needs T >= 2")
    return frames, refs


def temporal_error_per_frame(frames: Any, refs: Any, eps: float = RELMSE_EPS) -> jnp.ndarray:
    """Temporal error of each consecutive frame pair: shape ``(..., T - 1)``.

    For frames x_t and references r_t (time axis -4), pair t (t = 1..T-1) scores
    mean over H, W, C of ((x_t - x_{t-1}) - (r_t - r_{t-1}))^2 / (((r_t + r_{t-1}) / 2)^2 + eps):
    a flicker (a change the reference does not have) or a lag (a change it does have but the result
    misses) is penalized relative to the local brightness, like RelMSE. Chaitanya et al. 2017,
    Sec. 4.4, train on the L1 of the same temporal differences (their loss L_t).
    """
    frames, refs = _temporal_check("temporal_error_per_frame", frames, refs, eps)
    return jnp.mean(_temporal_map(frames, refs, eps), axis=(-3, -2, -1))


def temporal_error(frames: Any, refs: Any, eps: float = RELMSE_EPS) -> jnp.ndarray:
    """Mean of `temporal_error_per_frame` over frame pairs and sequences (one scalar)."""
    frames, refs = _temporal_check("temporal_error", frames, refs, eps)
    return jnp.mean(_temporal_map(frames, refs, eps))


# -- halos -----------------------------------------------------------------------------------------
HALO_FACTOR, HALO_WINDOW = 4.0, 9  # issue 34: "no surface pixel above 4x the reference's 9x9 local maximum"


@jax.jit
def _halo_map(x, ref):
    """Per image ``(..., H, W)``: the channel mean of ``x`` above `HALO_FACTOR` x the 9x9 maximum of
    the reference's channel mean (the square clipped at the border: scipy's ``maximum_filter`` with
    ``mode="nearest"``), with 1e-6 of slack for black references."""
    o, r = jnp.mean(x, -1), jnp.mean(ref, -1)
    h = HALO_WINDOW // 2
    ones = (1,) * (r.ndim - 2)
    local = jax.lax.reduce_window(r, -jnp.inf, jax.lax.max, ones + (HALO_WINDOW, HALO_WINDOW), ones + (1, 1),
                                  [(0, 0)] * (r.ndim - 2) + [(h, h), (h, h)])
    return o > HALO_FACTOR * local + 1e-6


def halo_pixels(x: Any, ref: Any, mask: Any = None) -> int:
    """How many pixels of ``x`` (of ``mask``, a boolean ``(..., H, W)`` array, where given: issue 34
    counts surface pixels) are brighter (channel mean) than `HALO_FACTOR` times the reference's
    largest channel mean in the `HALO_WINDOW` square around them: light drawn where the reference has
    none near (a ring around a bright object, a surviving firefly). Over every image of a batch."""
    x, ref = _pair("halo_pixels", x, ref)
    halo = _halo_map(jnp.nan_to_num(x, nan=jnp.inf), ref)  # a non-finite output counts as a halo
    if mask is not None:
        mask = jnp.asarray(mask, bool)
        if mask.shape != halo.shape[-mask.ndim:] and mask.shape != halo.shape:
            raise JaxdenoiseError(f"halo_pixels: 'mask' has shape {tuple(mask.shape)}; expected the images' "
                                  f"(..., H, W) = {tuple(halo.shape)}")
        halo = halo & mask
    return int(jnp.sum(halo))


__all__ = [
    "RELMSE_EPS", "relmse", "relmse_per_image", "mse", "mse_per_image", "psnr", "psnr_per_image",
    "ssim", "ssim_map", "ssim_per_image", "temporal_error", "temporal_error_per_frame",
    "HALO_FACTOR", "HALO_WINDOW", "halo_pixels",
]
