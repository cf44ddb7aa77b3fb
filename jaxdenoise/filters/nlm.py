"""Cross non-local-means filter and the feature prefilter of Kalantari, Bako & Sen 2015.

``cross_nlm(color, color_var, features, feature_vars, lam_patch, lam_features, *, radius, patch_radius=2)``
    Appendix Eq. 16-17: the weight of neighbour ``j`` for pixel ``i`` is::

        log d_ij = - lam_p,i D(Q_i, Q_j) - sum_k lam_k,i ||f_ik - f_jk||^2 / max(psi_k,i^2, delta)
        D(Q_i, Q_j) = 1/|Q| sum_{o in patch} sum_ch (c_{i+o} - c_{j+o})^2 / (psi_{i+o}^2 + psi_{j+o}^2 + zeta)

    with ``5 x 5`` patches (``patch_radius=2``), ``zeta = 1e-10``, ``delta = 1e-4``. Arguments are
    those of `cross_bilateral` minus the spatial and colour terms (Eq. 16 has none), plus
    ``lam_patch`` (scalar or per-pixel map, ``= 1 / (2 rho^2)``). ``color_var`` is required here.

``prefilter_features(feature, feature_var, *, radius=5, patch_radius=3, lam=1.0)``
    Sec. 3.2: the additional features are prefiltered with non-local means in an ``11 x 11`` window
    with ``7 x 7`` patches (after Rousselle et al. 2013), and their variances are smoothed "using the
    same weights". The paper does not spell out this filter's distance; we use Rousselle et al.'s
    variance-cancelled NL-means distance per channel (docs/methods/bilateral.md)::

        D(P_i, P_j) = max(0, 1/(|P| C) sum_{o, ch} ((f_{i+o} - f_{j+o})^2 - (v_{i+o} + min(v_{i+o}, v_{j+o})))
                                                   / (v_{i+o} + v_{j+o} + zeta))
        d_ij = exp(-lam D)

    Returns ``(filtered feature (H, W, C), smoothed variance (H, W, 1))``; the variance map is
    averaged with exactly the weights of the feature.

Patch distances near the border average only over the patch offsets where both ``i + o`` and
``j + o`` are inside the image (``|Q|`` is that count); window neighbours outside the image get
weight 0; the centre's log-weight is exactly 0 (every patch distance of a patch with itself is 0,
and the cancelled distance is clamped at 0), so the output is a convex combination that falls back
to the centre pixel when all other weights underflow. Memory is O(H (W + 2r) C) (``_window.py``).
"""
from __future__ import annotations

from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import compute_dtype
from ._common import FilterError, as_image, as_param, check_radius
from ._window import Neighbours, channel_sum_sq, clamp_dist, from_planar, sum_channels, to_planar, window_sums
from .bilateral import DELTA, ZETA, check_color_var, feature_inputs, sq_over_var, var_map


def _box(x: jax.Array, r: int, h: int, w: int) -> jax.Array:
    """Sum of a planar (C, h + 2r, w + 2r) array over (2r+1)^2 boxes -> (C, h, w); separable."""
    rows = x[:, 0:h, :]
    for a in range(1, 2 * r + 1):
        rows = rows + x[:, a:a + h, :]
    out = rows[:, :, 0:w]
    for b in range(1, 2 * r + 1):
        out = out + rows[:, :, b:b + w]
    return out


def _pair_count(n: int, offset, pr: int, dtype) -> jax.Array:
    """For each of ``n`` positions ``y`` along one axis, how many patch offsets ``o`` in ``[-pr, pr]``
    keep both ``y + o`` and ``y + offset + o`` inside ``[0, n)`` (0 when none does)."""
    y = jnp.arange(n)
    lo = jnp.maximum(jnp.maximum(-pr, -y), -y - offset)
    hi = jnp.minimum(jnp.minimum(pr, n - 1 - y), n - 1 - y - offset)
    return jnp.maximum(hi - lo + 1, 0).astype(dtype)


def _cancelled_term(ci, cj, vi, vj):
    diff = ci - cj
    return (diff * diff - (vi + jnp.minimum(vi, vj))) / (vi + vj + ZETA)


def _patch_distance(nb: Neighbours, centre: dict, pr: int, h: int, w: int, *, cancel: bool) -> jax.Array:
    """Mean patch distance D(Q_i, Q_j) as (1, h, w) for the current offset (Eq. 17, or the
    variance-cancelled form of the prefilter when ``cancel``)."""
    cj = nb.get("color", pr)
    vj = nb.get("color_var", pr)
    ci, vi = centre["color_pad"], centre["color_var_pad"]
    pair = centre["valid_pad"] * nb.get("valid", pr)  # both i+o and j+o inside the image
    if cancel:
        # Rousselle et al.: subtract the expected squared difference due to noise.
        d = sum_channels(_cancelled_term, (ci, cj, vi, vj)) * (1.0 / ci.shape[0])
    else:
        d = sum_channels(sq_over_var, (ci, cj, vi, vj))  # Eq. 17
    # |Q|, the number of patch offsets with both i + o and j + o inside, is separable: a row count
    # times a column count (`_pair_count`), exactly the box sum of ``pair`` without its second box
    # filter per offset (1.4x faster prefilter, bit-identical). count >= 1 wherever j is inside the
    # image (o = 0 pairs i with j); the maximum only guards the outside neighbours, whose weight is
    # zeroed by the validity mask anyway.
    count = _pair_count(h, nb.dy, pr, d.dtype)[None, :, None] * _pair_count(w, nb.dx, pr, d.dtype)[None, None, :]
    dist = _box(d * pair, pr, h, w) / jnp.maximum(count, 1.0)
    if cancel:
        dist = jnp.maximum(dist, 0.0)
    return clamp_dist(dist)


def _nlm_sums(color, color_var, feats, scales, lam_patch, values, *, radius, patch_radius, cancel):
    """Planar window sums of the (cross) NLM: returns (num, den) for the planar ``values``."""
    c, h, w = color.shape
    pr = patch_radius
    pad = ((0, 0), (pr, pr), (pr, pr))
    centre = {
        "color_pad": jnp.pad(color, pad),
        "color_var_pad": jnp.pad(color_var, pad),
        "valid_pad": jnp.pad(jnp.ones((1, h, w), color.dtype), pad),
    }
    nbrs = {"color": color, "color_var": color_var, "value": values}
    for k, f in enumerate(feats):
        nbrs[f"feat{k}"] = f

    def log_weight(nb: Neighbours):
        lw = -lam_patch * _patch_distance(nb, centre, pr, h, w, cancel=cancel)
        for k, f in enumerate(feats):
            d = f - nb.get(f"feat{k}")
            lw = lw - scales[k] * clamp_dist(channel_sum_sq(d))
        return lw

    return window_sums(log_weight, nbrs, "value", radius=radius, halo=pr)


def cross_nlm(color, color_var, features: Sequence[Any], feature_vars: Sequence[Any], lam_patch,
              lam_features: Sequence[Any], *, radius: int, patch_radius: int = 2) -> jax.Array:
    """Cross non-local means, Kalantari 2015 Appendix Eq. 16-17 (module docstring)."""
    radius = check_radius(radius)
    patch_radius = check_radius(patch_radius, "patch_radius")
    col = as_image(color, "color")
    hw = col.shape[:2]
    if color_var is None:
        raise FilterError("argument 'color_var' is None; cross_nlm needs the colour variance (Eq. 17)")
    cvar = check_color_var(color_var, col, hw)
    feats, fvars, lams_f = feature_inputs(features, feature_vars, lam_features, hw)
    lam_p = as_param(lam_patch, "lam_patch", hw)

    out_dtype = col.dtype if jnp.issubdtype(col.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(col, cvar, lam_p, *feats, *lams_f)
    colp = to_planar(col.astype(dt))
    varp = to_planar(cvar.astype(dt))
    featp = [to_planar(f.astype(dt)) for f in feats]
    # Eq. 12 on the centre pixel: variance floored at DELTA (also keeps the division safe).
    scales = [to_planar(l.astype(dt)) / (DELTA if v is None else jnp.maximum(to_planar(v.astype(dt)), DELTA))
              for l, v in zip(lams_f, fvars)]
    num, den = _nlm_sums(colp, varp, featp, scales, to_planar(lam_p.astype(dt)), colp,
                         radius=radius, patch_radius=patch_radius, cancel=False)
    return from_planar(num / den).astype(out_dtype)  # den >= 1: the centre weight is exactly 1


def prefilter_features(feature, feature_var, *, radius: int = 5, patch_radius: int = 3,
                       lam: Any = 1.0) -> tuple[jax.Array, jax.Array]:
    """NL-means prefilter of one feature and its variance, Kalantari 2015 Sec. 3.2 (module docstring)."""
    radius = check_radius(radius)
    patch_radius = check_radius(patch_radius, "patch_radius")
    f = as_image(feature, "feature")
    hw = f.shape[:2]
    if feature_var is None:
        raise FilterError("argument 'feature_var' is None; the prefilter needs the feature's variance")
    v = var_map(feature_var, "feature_var", hw)
    lam_p = as_param(lam, "lam", hw)
    out_dtype = f.dtype if jnp.issubdtype(f.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(f, v, lam_p)
    fp = to_planar(f.astype(dt))
    vp = to_planar(v.astype(dt))
    values = jnp.concatenate([fp, vp], axis=0)
    num, den = _nlm_sums(fp, vp, [], [], to_planar(lam_p.astype(dt)), values,
                         radius=radius, patch_radius=patch_radius, cancel=True)
    out = from_planar(num / den)  # den >= 1: the centre weight is exactly 1
    return out[..., :-1].astype(out_dtype), out[..., -1:].astype(out_dtype)


def prefilter_guides(features: dict, variances: dict, *, prefilter: bool = True, radius: int = 5,
                     patch_radius: int = 3) -> tuple[dict, dict]:
    """The feature prefilter pipeline of Kalantari 2015 Sec. 3.2 for a set of named features (the
    one shared by ``lbf`` and ``bilateral``/``nlm``): ``{name: feature}`` / ``{name: variance}`` ->
    the same dicts with every feature and its variance NL-means prefiltered (`prefilter_features`,
    11x11 window, 7x7 patches by default). A feature that is ``None`` (absent from the frame) is
    left out of both results; one without a variance, or every one when ``prefilter`` is False, is
    passed through unfiltered.

    Features of the same shape are filtered by one `jax.vmap` of `prefilter_features` (LBF's four
    3-channel features: one traced and compiled filter instead of four, 4.4 s against 2.4 s of
    compilation at 1200x800 and the same run time, measured in one process; outputs equal to the
    one-by-one calls to float32 rounding, 2.4e-7 at most on the demo frame). Each input is checked
    on its own first, as the one-by-one call does, so a bad concrete array is still refused by
    name."""
    out, groups = {}, {}
    for name, f in features.items():
        if f is None:
            continue
        v = variances.get(name)
        if prefilter and v is not None:
            f, v = as_image(f, "feature"), var_map(v, "feature_var", np.shape(f)[:2])
            groups.setdefault((f.shape, f.dtype, v.shape, v.dtype), []).append(name)
        out[name] = (f, v)
    for names in groups.values():
        stack = [jnp.stack([out[n][i] for n in names]) for i in (0, 1)]
        fs, vs = jax.vmap(lambda f, v: prefilter_features(f, v, radius=radius, patch_radius=patch_radius))(*stack)
        for k, n in enumerate(names):
            out[n] = (fs[k], vs[k])
    return {n: fv[0] for n, fv in out.items()}, {n: fv[1] for n, fv in out.items()}

