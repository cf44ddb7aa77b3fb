"""Denoiser-guided adaptive sampling: the error estimates that drive a sampling map, and the map
itself (issue 40; the renderer's side, passes and unbiased pooling, is `data_gen.adaptive`).

Every estimate is a small pure function of a frame's buffers (or of denoised images) returning an
(H, W) map of the *relative* squared error of a pixel, in the units of the RelMSE metric
(``(x - ref)^2 / (ref^2 + eps)``, ``eps = 0.01``, averaged over the colour channels):

- `relative_variance` (a): the renderer's classic, the variance of the pixel mean over the squared
  pixel value; given a denoised image, that image is the denominator (c: far less noisy than the
  pixel's own few-sample mean, which puts the fireflies' large means in the denominator).
- `halves_error` (b): the denoiser's own error from two independent half-buffers: denoise each
  half, compare. ``a - b`` has the variance of two half-frame outputs, about four times the
  full frame's (a half has half the samples), so ``(a - b)^2 / 4`` estimates the variance of the
  full frame's output; the denoiser's bias is not seen by it (docs/methods/adaptive.md).

`allocate` turns a map into integer per-pixel sample counts for the next pass: the counts that
minimize the summed estimated error when a pixel's error falls as one over its samples (``c_i``
proportional to the square root of the per-sample error ``e_i n_i``, divided by the sample's cost
where one is given), between a floor (no pixel starves) and a cap, with the pass's total exact.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .errors import JaxdenoiseError
from .methods.lbf_features import box_mean

__all__ = ["EPS", "SMOOTH", "relative_variance", "halves_error", "smooth", "allocate"]

EPS = 0.01      # the RelMSE metric's eps (docs/metrics.md)
SMOOTH = 5      # side of the box the maps are averaged over before allocation (a pixel's estimate is noisy)


def _check(name: str, x, channels: int | None = None):
    x = jnp.asarray(x, jnp.float32)
    if x.ndim != 3 or (channels is not None and x.shape[-1] != channels):
        want = f"(H, W, {channels})" if channels is not None else "(H, W, C)"
        raise JaxdenoiseError(f"adaptive: '{name}' has shape {tuple(x.shape)}; expected {want}")
    return x


def relative_variance(color, color_var, *, denoised=None, eps: float = EPS):
    """(H, W) ``mean_c var / (d^2 + eps)``: the variance of the pixel mean relative to the squared
    value ``d`` (the noisy ``color``, or ``denoised`` where given)."""
    color = _check("color", color)
    var = _check("color_var", color_var, color.shape[-1])
    d = color if denoised is None else _check("denoised", denoised, color.shape[-1])
    return jnp.mean(jnp.maximum(var, 0.0) / (d * d + eps), axis=-1)


def halves_error(denoised_a, denoised_b, *, eps: float = EPS):
    """(H, W) ``mean_c (a - b)^2 / 4 / (m^2 + eps)`` with ``m = (a + b) / 2``: the variance of a
    full-frame denoised output estimated from the outputs ``a``, ``b`` of two independent halves."""
    a = _check("denoised_a", denoised_a)
    b = _check("denoised_b", denoised_b, a.shape[-1])
    m = 0.5 * (a + b)
    return jnp.mean(0.25 * (a - b) ** 2 / (m * m + eps), axis=-1)


def smooth(error, *, size: int = SMOOTH):
    """An (H, W) map averaged over a ``size`` x ``size`` box (edge-replicated)."""
    e = jnp.asarray(error, jnp.float32)
    if e.ndim != 2:
        raise JaxdenoiseError(f"adaptive: the error map has shape {tuple(e.shape)}; expected (H, W)")
    return box_mean(e[..., None], size=size)[..., 0]


def allocate(error, counts, total: int, *, floor: int = 1, cap: float = 8.0, cost=None, base=0) -> np.ndarray:
    """Integer samples per pixel for the next pass, (H, W) int64 summing to exactly ``total``.

    ``error``: the estimated relative error of each pixel now (H, W); ``counts``: the samples each
    pixel has so far (H, W). A pixel whose error falls as ``e_i n_i / N`` with ``N`` samples gets
    ``c_i = clip(lam sqrt(e_i n_i), floor, cap * total / npix)``, ``lam`` found by bisection so the
    counts sum to ``total`` (the minimizer of the summed error under those bounds), then rounded
    by largest remainder. A map without signal (all zero) gives uniform counts.

    ``cost`` (H, W, positive; None: equal): the time a sample of each pixel takes, relative to the
    others. The counts then minimize the summed error for a fixed *time*,
    ``c_i ~ sqrt(e_i n_i / t_i)`` (still scaled to ``total`` samples), so an expensive pixel (long
    glass paths) gets fewer samples than its error alone would give it.

    ``base`` (scalar or (H, W), non-negative): samples each pixel will have in its estimate besides
    this pass's, pooled with them by count (`data_gen.adaptive`'s frame part of the pilot). The pass
    then tops the pixels up: ``c_i = clip(lam sqrt(e_i n_i / t_i) - base_i, floor, cap m)``, the
    least summed error for ``base_i + c_i`` samples (water-filling).
    """
    e = np.asarray(error, np.float64)
    n = np.asarray(counts, np.float64)
    if e.ndim != 2 or n.shape != e.shape:
        raise JaxdenoiseError(f"allocate: error {e.shape} and counts {n.shape} must be the same (H, W)")
    if not np.all(np.isfinite(e)) or np.any(e < 0):
        raise JaxdenoiseError("allocate: the error map must be finite and non-negative")
    npix = e.size
    if isinstance(total, bool) or int(total) != total or total < 0:
        raise JaxdenoiseError(f"allocate: total is {total!r}; expected a non-negative integer")
    total = int(total)
    if floor < 0 or floor * npix > total:
        raise JaxdenoiseError(f"allocate: floor {floor} per pixel needs {floor * npix} samples; the pass has {total}")
    hi = max(float(cap) * total / npix, floor + 1.0)
    if hi * npix < total:
        raise JaxdenoiseError(f"allocate: cap {cap} is below the pass's mean {total / npix}")
    s = e * np.maximum(n, 1.0)
    if cost is not None:
        t = np.asarray(cost, np.float64)
        if t.shape != e.shape or not np.all(np.isfinite(t)) or np.any(t <= 0):
            raise JaxdenoiseError(f"allocate: cost must be finite and positive, shape {e.shape}")
        s = s / t
    s = np.sqrt(s).reshape(-1)
    b = np.asarray(base, np.float64)
    if b.ndim and b.shape != e.shape or not np.all(np.isfinite(b)) or np.any(b < 0):
        raise JaxdenoiseError(f"allocate: base must be finite and non-negative, a scalar or shape {e.shape}")
    b = np.broadcast_to(b, e.shape).reshape(-1)
    if not np.any(s > 0):
        s = np.ones_like(s)
    lo_lam, hi_lam = 0.0, ((hi + b.max()) / s[s > 0].min()) * 2
    for _ in range(100):                       # bisection on lam: sum(clip(lam s - b)) is monotone in it
        lam = 0.5 * (lo_lam + hi_lam)
        if np.clip(lam * s - b, floor, hi).sum() < total:
            lo_lam = lam
        else:
            hi_lam = lam
    c = np.clip(hi_lam * s - b, floor, hi)
    c *= total / c.sum()                       # exact total before rounding (bisection tolerance)
    out = np.floor(c).astype(np.int64)
    out = np.maximum(out, floor)
    left = total - int(out.sum())
    if left > 0:
        order = np.argsort(-(c - np.floor(c)), kind="stable")
        out[order[:left]] += 1
    elif left < 0:                             # flooring up to `floor` overshot: take from the largest
        order = np.argsort(-out, kind="stable")
        i = 0
        while left < 0:
            p = order[i % npix]
            if out[p] > floor:
                out[p] -= 1
                left += 1
            i += 1
    return out.reshape(e.shape)
