"""Gaussian blur: the baseline of every filter comparison (issue 4, item 1).

``gaussian(image, sigma, *, radius=None) -> image``

- ``image``: ``(H, W, C)`` float array (float16/bfloat16 are computed in float32 and cast back).
- ``sigma``: standard deviation in pixels (differentiable; a traced value needs an explicit
  ``radius``). ``sigma -> 0`` gives the identity exactly. A scalar runs the separable path below;
  a per-pixel ``(H, W)`` / ``(H, W, 1)`` map (each output pixel with its own kernel, which is not
  separable) runs the window engine of the bilateral filters with ``lambda = 1 / (2 sigma^2)``.
- ``radius``: keyword-only, static; the window is ``(2 radius + 1)^2``. Default ``ceil(3 sigma)``
  (needs a concrete ``sigma``).

Separable: one horizontal and one vertical pass (planar layout) with the unnormalized kernel
``exp(-d^2 / (2 sigma^2))`` (centre weight 1): shifted-slice sums below `BANDED_MIN_RADIUS`, tiled
banded matrix products from it (the same sums; GradNet's radius-45 post-process 5.6x faster).

Edge handling: pixels outside the image get zero weight and each output pixel is divided by the
sum of the weights that fell inside the image, i.e. the kernel is renormalized at the border (no
padding values are invented, and a constant image stays constant up to the border). Because the
centre weight is 1 and the in-image region is a rectangle, the normalizer is the product of the
two 1-D normalizers, which is >= 1, so the division is always safe.
"""
from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import compute_dtype, is_concrete
from ._common import FilterError, as_image, as_param, check_radius
from ._window import from_planar, to_planar
from .bilateral import cross_sums, prepare_window  # per-pixel sigma: the window engine

# Smallest sigma^2 used in the kernel exponent. Below it every off-centre weight underflows to
# exactly 0 (d^2 >= 1), so clamping changes nothing but avoids 0/0 at sigma = 0.
_MIN_SIGMA2 = 1e-12


def gaussian_kernel_1d(sigma: Any, radius: int, dtype: Any = jnp.float32) -> jax.Array:
    """Unnormalized 1-D Gaussian taps ``exp(-d^2 / (2 sigma^2))`` for ``d = -radius..radius``."""
    d = jnp.arange(-radius, radius + 1, dtype=dtype)
    s2 = jnp.maximum(jnp.asarray(sigma, dtype) ** 2, _MIN_SIGMA2)  # guard: sigma = 0 -> identity
    return jnp.exp(-(d * d) / (2.0 * s2))


def _correlate(x: jax.Array, taps: jax.Array, axis: int) -> jax.Array:
    """Zero-padded 1-D correlation of a planar (C, H, W) array along ``axis`` (1 = rows, 2 = columns).

    A sum of ``2r + 1`` shifted slices, which XLA fuses into one pass; measured 9x less CPU time than
    a depthwise ``conv_general_dilated`` for a 55-tap kernel on a 1200 x 800 RGB frame.
    """
    k = taps.shape[0]
    r = (k - 1) // 2
    widths = [(0, 0)] * 3
    widths[axis] = (r, r)
    xp = jnp.pad(x, widths)
    n = x.shape[axis]
    out = None
    for i in range(k):
        term = jax.lax.slice_in_dim(xp, i, i + n, axis=axis) * taps[i]
        out = term if out is None else out + term
    return out


# Output samples per tile of `_correlate_banded`; each tile is one (T + 2r) x T matrix product.
BAND_TILE = 128
# Radii from which a pass runs as banded matrix products instead of shifted-slice sums. Measured on
# this CPU (jax 0.10.2, 2 cores), the whole `gaussian` of a 1280x720 image, slices / banded ms:
# 3 channels r = 8: 7.1 / 17.4, r = 16: 48.2 / 16.7, r = 27: 86.9 / 31.5; 6 channels r = 8:
# 64.5 / 46.6, r = 16: 114 / 51, r = 45 (GradNet's Eq. 13): 399 / 71.
BANDED_MIN_RADIUS = 12


def _correlate_banded(x: jax.Array, taps: jax.Array, axis: int) -> jax.Array:
    """`_correlate` as matrix products: the axis is cut into tiles of `BAND_TILE` outputs, each tile's
    ``T + 2r`` inputs (zero-padded like `_correlate`) times the ``(T + 2r, T)`` band matrix
    ``B[k, j] = taps[k - j]`` (zero off the band). The same sums in another order (float32
    rounding, relative 1e-6); it trades about ``(T + 2r) / (2r + 1)`` times the multiply-adds for
    the matmul's rate, which pays from `BANDED_MIN_RADIUS`."""
    k = taps.shape[0]
    r = (k - 1) // 2
    xm = jnp.moveaxis(x, axis, -1)
    n = xm.shape[-1]
    t = min(BAND_TILE, n)
    tiles = -(-n // t)
    xp = jnp.pad(xm, [(0, 0)] * (xm.ndim - 1) + [(r, tiles * t - n + r)])
    windows = jnp.stack([xp[..., i * t: i * t + t + 2 * r] for i in range(tiles)], axis=-2)  # (..., tiles, t + 2r)
    d = jnp.arange(t + 2 * r)[:, None] - jnp.arange(t)[None, :]
    band = jnp.where((d >= 0) & (d <= 2 * r), taps[jnp.clip(d, 0, 2 * r)], 0.0).astype(x.dtype)
    y = jnp.matmul(windows, band, precision=jax.lax.Precision.HIGHEST).reshape(xm.shape[:-1] + (tiles * t,))
    return jnp.moveaxis(y[..., :n], -1, axis)


def gaussian(image: Any, sigma: Any, *, radius: int | None = None) -> jax.Array:
    """Separable Gaussian blur of an ``(H, W, C)`` image with border renormalization (module docstring)."""
    img = as_image(image, "image")
    if is_concrete(sigma):
        s = np.asarray(sigma, np.float64)
        if not np.all(np.isfinite(s)) or np.any(s < 0):
            raise FilterError("argument 'sigma' has non-finite or negative values; expected finite values >= 0")
    if radius is None:
        if not is_concrete(sigma):
            raise FilterError("argument 'radius' is None but 'sigma' is traced; pass radius= (static)")
        # Offsets past the image edge only ever meet zero-weight (outside) pixels, so capping the
        # default window at the image size is exact; it also keeps sigma -> inf (1e30) finite and fast.
        radius = int(min(math.ceil(3.0 * float(np.max(np.asarray(sigma)))), max(img.shape[:2]) - 1))
    radius = check_radius(radius)
    if np.ndim(sigma) != 0:
        sig = as_param(sigma, "sigma", img.shape[:2])
        dt = compute_dtype(img, sig)
        # lambda = 1/(2 sigma^2); the floor keeps sigma = 0 finite (off-centre weights underflow to 0)
        lam = 0.5 / jnp.maximum(sig.astype(dt) ** 2, _MIN_SIGMA2)
        centre = prepare_window(img, None, [], [], lam, None, [], dt)
        num, den = cross_sums(centre, [{"color": centre["color"]}], radius=radius)
        out_dtype = img.dtype if jnp.issubdtype(img.dtype, jnp.floating) else jnp.float32
        return (num / den).astype(out_dtype)  # den >= 1 (centre weight 1)
    out_dtype = img.dtype if jnp.issubdtype(img.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(img, jnp.asarray(sigma))
    x = img.astype(dt)
    if radius == 0:
        return x.astype(out_dtype)
    taps = gaussian_kernel_1d(sigma, radius, dt)
    h, w = x.shape[:2]
    corr = _correlate_banded if radius >= BANDED_MIN_RADIUS else _correlate
    num = corr(corr(to_planar(x), taps, 2), taps, 1)
    # The in-image region is a rectangle, so the normalizer is the outer product of the 1-D ones;
    # each is >= 1 because the centre tap is 1 (module docstring).
    den = _correlate(jnp.ones((1, h, 1), dt), taps, 1) * _correlate(jnp.ones((1, 1, w), dt), taps, 2)
    return from_planar(num / den).astype(out_dtype)
