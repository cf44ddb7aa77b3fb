"""A feature-guided cross-bilateral pass over a denoiser's output (ours, issues 33 and 34;
docs/methods/demc.md and docs/methods/rae.md "Refinement").

``refine(image, albedo, normal, *, sigma, range_sigma, albedo_sigma, normal_sigma, radius=None) -> image``;
``check_refine_settings(owner, sigma, range_sigma, albedo_sigma, normal_sigma)``.

A network's output keeps some low-amplitude noise in flat regions (DEMC's 4-spp SSIM is lost to LBF's
there: docs/methods/demc.md "Where the 4-spp SSIM is lost"). This pass averages each pixel ``y_i`` with
its neighbours ``y_j`` in a ``(2 radius + 1)^2`` window (``radius`` = ceil(2 ``sigma``) unless given),
weighted by

    exp(- |p_i - p_j|^2 / (2 sigma^2)                               (pixel distance)
        - sum_ch (y_i - y_j)^2 / (2 range_sigma^2 (m_i^2 + m_j^2))  (relative range; m = mean |y| over channels)
        - |a_i - a_j|^2 / (2 albedo_sigma^2)                         (first-hit albedo)
        - |n_i - n_j|^2 / (2 normal_sigma^2))                        (first-hit normal)

and normalised (the centre's weight is 1). It is Kalantari et al.'s cross-bilateral filter
(`cross_bilateral`, Eq. 1-2, 11-12) with a range term relative to the pixels' own brightness and
fixed, hand-set feature bandwidths: the features keep it from averaging across geometry and texture
edges, the relative range from averaging across a shadow or a highlight. The range term is scale-free,
so ``refine(k y) = k refine(y)`` for ``k > 0`` up to `ZETA` (call it in a frame's exposure-normalised
units for an exact scaling). Leading axes (``(..., H, W, C)``, features with the same leading axes)
are independent images. Static settings, keyword-only; differentiable in the image.
"""
from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._common import FilterError, require_finite
from .bilateral import DELTA, cross_bilateral


def _check(values: tuple[Any, ...], names: tuple[str, ...]) -> None:
    for v, name in zip(values, names):
        if not (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                and np.isfinite(v) and v > 0):
            raise FilterError(f"{name} must be a finite number > 0, got {v!r}")


def check_refine_settings(owner: str, sigma: Any, range_sigma: Any, albedo_sigma: Any, normal_sigma: Any) -> None:
    """Refuse, naming ``owner`` (e.g. ``"demc: config."``) and its ``refine_sigma`` / ``refine_range`` /
    ``refine_albedo`` / ``refine_normal``, settings `refine` cannot take."""
    _check((sigma, range_sigma, albedo_sigma, normal_sigma),
           tuple(f"{owner}refine_{k}" for k in ("sigma", "range", "albedo", "normal")))


def refine(image: Any, albedo: Any, normal: Any, *, sigma: float, range_sigma: float, albedo_sigma: float,
           normal_sigma: float, radius: int | None = None) -> jax.Array:
    """The feature-guided pass of the module docstring over ``image`` ``(..., H, W, C)`` with the
    first-hit ``albedo`` and ``normal`` ``(..., H, W, 3)``."""
    _check((sigma, range_sigma, albedo_sigma, normal_sigma),
           ("argument 'sigma'", "argument 'range_sigma'", "argument 'albedo_sigma'", "argument 'normal_sigma'"))
    radius = math.ceil(2 * sigma) if radius is None else radius
    for name, a in (("image", image), ("albedo", albedo), ("normal", normal)):
        if a is None:
            raise FilterError(f"refine: argument '{name}' is None; expected an (..., H, W, C) array")
    y = jnp.asarray(image)
    a, n = jnp.asarray(albedo), jnp.asarray(normal)
    if y.ndim < 3:
        raise FilterError(f"refine: argument 'image' has shape {tuple(y.shape)}; expected (..., H, W, C)")
    for name, f in (("albedo", a), ("normal", n)):
        if f.shape[:-1] != y.shape[:-1]:
            raise FilterError(f"refine: argument '{name}' has shape {tuple(f.shape)}; expected the image's "
                              f"{tuple(y.shape[:-1])} plus channels")
    if y.ndim > 3:
        for name, v in (("image", y), ("albedo", a), ("normal", n)):
            require_finite(v, name)
        lead = y.shape[:-3]
        flat = lambda v: v.reshape((-1,) + v.shape[len(lead):])  # noqa: E731
        one = lambda yy, aa, nn: refine(yy, aa, nn, sigma=sigma, range_sigma=range_sigma,  # noqa: E731
                                        albedo_sigma=albedo_sigma, normal_sigma=normal_sigma, radius=radius)
        return jax.vmap(one)(flat(y), flat(a), flat(n)).reshape(y.shape)
    m = jnp.mean(jnp.abs(y), axis=-1, keepdims=True)
    lam_features = [DELTA / (2.0 * albedo_sigma ** 2), DELTA / (2.0 * normal_sigma ** 2)]  # over the floor DELTA
    return cross_bilateral(y, (range_sigma * m) ** 2, [a, n], [None, None], 1.0 / (2.0 * sigma ** 2), 0.5,
                           lam_features, radius=radius)


__all__ = ["check_refine_settings", "refine"]
