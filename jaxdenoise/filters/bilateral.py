"""Cross-bilateral filters of Kalantari, Bako & Sen 2015 ("LBF") and a plain bilateral baseline.

Signatures (the LBF method calls these; every ``lam_*`` is a scalar or a per-pixel ``(H, W)`` /
``(H, W, 1)`` map, differentiable, >= 0, and is the auxiliary parameter ``lambda = 1 / (2 theta^2)``
of the paper's Appendix, so ``lambda = 0`` switches a term off and ``lambda -> inf`` makes it
infinitely selective):

``cross_bilateral(color, color_var, features, feature_vars, lam_spatial, lam_color, lam_features, *, radius)``
    - ``color`` ``(H, W, C)``: noisy pixel means ``c``; ``color_var`` ``(H, W, C)`` or ``(H, W, 1)``:
      variance of the pixel mean, ``psi^2`` (``None``: the colour term is skipped, like
      ``lam_color = 0``);
    - ``features``: sequence of K arrays ``(H, W, C_k)`` (world position, normal, texture 1 and 2,
      visibility in the paper, Sec. 3.2); ``feature_vars``: sequence of K arrays ``(H, W)`` /
      ``(H, W, 1)`` (variance of the feature's pixel mean, ``psi_k^2``) or ``None`` entries
      (variance 0, so the floor ``delta`` applies);
    - ``lam_spatial``, ``lam_color``: scalars or maps; ``lam_features``: sequence of K scalars or maps;
    - ``radius``: keyword-only static int, window ``(2 radius + 1)^2`` (the paper's 55 x 55 is 27).

    Weight of neighbour ``j`` for pixel ``i`` (Eq. 2 with Eq. 11-12 and the auxiliary parameters)::

        log d_ij = - lam_s,i ||p_i - p_j||^2
                   - lam_c,i sum_ch (c_i - c_j)^2 / (psi_i^2 + psi_j^2 + zeta)          (Eq. 11)
                   - sum_k lam_k,i ||f_ik - f_jk||^2 / max(psi_k,i^2, delta)            (Eq. 12)

    with ``zeta = 1e-10`` and ``delta = 1e-4``; output (Eq. 1) ``sum_j d_ij c_j / sum_j d_ij``.
    The colour term divides channel by channel; with a one-channel ``color_var`` it is exactly
    Eq. 11 (docs/methods/bilateral.md). Returns ``(H, W, C)``.

``bilateral(image, lam_spatial, lam_range, *, radius)``
    The plain (non-cross) bilateral of Tomasi & Manduchi: ``log d_ij = -lam_s ||p_i - p_j||^2 -
    lam_r ||c_i - c_j||^2`` (un-normalized range distance).

``spatiotemporal_cross_bilateral(color, color_var, features, feature_vars, lam_spatial, lam_color, lam_features, *, radius, lam_temporal=0.0, center=None)``
    Sec. 5: the same weights over a ``(T, H, W, .)`` volume (the paper uses T = 7, three frames on
    each side); every array gets a leading time axis, the ``lam_*`` maps are those of the centre
    frame ``center`` (default ``T // 2``), and ``lam_temporal`` adds ``- lam_t (t_i - t_j)^2``.
    Returns the filtered centre frame ``(H, W, C)``.

Shared behaviour (see ``_window.py``): running sums over the window, O(H W C) memory forward and
backward; neighbours outside the image (or outside the frame range) get weight 0; the centre weight
is exactly 1, so when all other weights underflow the output is the centre pixel (documented
fallback, never NaN). A feature that is constant over the frame (checked on concrete inputs, i.e.
outside ``jit``) contributes a distance of exactly 0, so its term is dropped before tracing: the
output is bit-identical and the filter does less work. Under ``jit`` the check cannot see values and
the term is computed (same result); call `drop_constant_features` before ``jit`` to get the saving.
"""
from __future__ import annotations

from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import compute_dtype, is_concrete
from ._common import FilterError, as_image, as_param, check_radius
from ._window import Neighbours, channel_sum, channel_sum_sq, clamp_dist, from_planar, to_planar, window_sums

ZETA = 1e-10  # Eq. 11: keeps the colour distance finite where both variances are 0
DELTA = 1e-4  # Eq. 12: floor of a feature's variance


def drop_constant_features(features: Sequence[Any], feature_vars: Sequence[Any], lam_features: Sequence[Any]):
    """Remove features whose value is the same at every pixel (concrete arrays only).

    Such a feature has ``||f_i - f_j|| = 0`` for every pair, so its factor in Eq. 2 is exactly 1:
    dropping it leaves the output bit-identical and saves its share of the work. Traced features
    (under ``jit``) are kept. Returns the three filtered lists.
    """
    return _drop_constant(features, features, feature_vars, lam_features)


def _drop_constant(raw_features: Sequence[Any], *lists: Sequence[Any]) -> tuple[list, ...]:
    """Filter each of ``lists`` (parallel to ``raw_features``) to the non-constant features.

    Constancy is judged on the raw inputs, which are concrete outside ``jit`` even when the filter's
    converted copies are traced (so a closed-over constant feature is dropped under ``jit`` too).
    """
    keep = [k for k, f in enumerate(raw_features) if not _is_constant(f)]
    return tuple([lst[k] for k in keep] for lst in lists)


def check_color_var(color_var: Any, col: Any, hw: tuple[int, int]) -> Any:
    """The colour variance as an image with 1 or C channels, checked to be >= 0 (when concrete)."""
    cvar = as_image(color_var, "color_var", hw=hw)
    if cvar.shape[-1] not in (1, col.shape[-1]):
        raise FilterError(f"argument 'color_var' has {cvar.shape[-1]} channels; expected 1 or {col.shape[-1]}")
    if is_concrete(color_var) and np.any(np.asarray(color_var) < 0):
        raise FilterError("argument 'color_var' has negative values; a variance must be >= 0")
    return cvar


def feature_inputs(features, feature_vars, lam_features, hw) -> tuple[list, list, list]:
    """Check and convert the feature stacks of the 2-D cross filters; constant features are dropped."""
    _check_features(features, feature_vars, lam_features, hw)
    feats = [as_image(f, f"features[{k}]", hw=hw) for k, f in enumerate(features)]
    fvars = [var_map(v, f"feature_vars[{k}]", hw) for k, v in enumerate(feature_vars)]
    lams_f = [as_param(l, f"lam_features[{k}]", hw) for k, l in enumerate(lam_features)]
    return _drop_constant(features, feats, fvars, lams_f)


def _is_constant(f: Any) -> bool:
    if f is None or not is_concrete(f):
        return False
    a = np.asarray(f)
    flat = a.reshape(-1, a.shape[-1])
    return bool(np.all(flat == flat[:1]))


def _check_features(features, feature_vars, lam_features, hw, lead=()):
    if not isinstance(features, (list, tuple)):
        raise FilterError("argument 'features' must be a sequence of (H, W, C_k) arrays")
    k = len(features)
    if not isinstance(feature_vars, (list, tuple)) or len(feature_vars) != k:
        raise FilterError(f"argument 'feature_vars' must be a sequence of {k} arrays or None (one per feature)")
    if not isinstance(lam_features, (list, tuple)) or len(lam_features) != k:
        raise FilterError(f"argument 'lam_features' must be a sequence of {k} scalars or (H, W) maps")


def _as_volume(x, name, t, hw, channels=None):
    """Validate a (T, H, W, C) array by validating each frame."""
    if np.ndim(x) != 4 or np.shape(x)[0] != t:
        raise FilterError(f"argument '{name}' has shape {np.shape(x)}; expected ({t}, H, W, C)")
    as_image(x[0] if not is_concrete(x) else np.asarray(x).reshape((-1,) + tuple(np.shape(x)[2:])), name)
    a = jnp.asarray(x)
    if a.shape[1:3] != tuple(hw):
        raise FilterError(f"argument '{name}' has pixel grid {a.shape[1:3]}; expected {tuple(hw)}")
    if channels is not None and a.shape[-1] != channels:
        raise FilterError(f"argument '{name}' has {a.shape[-1]} channel(s); expected {channels}")
    return a


def var_map(v, name, hw, lead=()):
    """A feature variance as (..., H, W, 1); accepts (..., H, W) too; None means 0."""
    if v is None:
        return None
    shp = tuple(np.shape(v))
    if shp == tuple(lead) + tuple(hw):
        v = jnp.asarray(v)[..., None]
    elif shp != tuple(lead) + tuple(hw) + (1,):
        raise FilterError(f"argument '{name}' has shape {shp}; expected {tuple(lead) + tuple(hw)} or "
                          f"{tuple(lead) + tuple(hw) + (1,)}")
    if is_concrete(v):
        a = np.asarray(v)
        bad = int(a.size - np.count_nonzero(np.isfinite(a)))
        if bad:
            raise FilterError(f"argument '{name}' has {bad} NaN/Inf value(s); expected finite variances")
        if np.any(a < 0):
            raise FilterError(f"argument '{name}' has negative values; a variance must be >= 0")
    return jnp.asarray(v)


def cross_sums(centre: dict, frames: list[dict], lam: dict, *, radius: int, dt_weights: list[Any]):
    """Sum the window sums of Eq. 1 over neighbour frames (one frame for the 2-D filters).

    ``centre``: the centre pixel's arrays: ``color``, optional ``color_var``, ``feat{k}`` and the
    precomputed per-pixel feature scales ``scale{k} = lam_k / max(psi_k^2, delta)``. ``frames``: per
    neighbour frame, the arrays read at ``j``. ``dt_weights``: per frame, an additive log-weight
    (``-lam_t dt^2``) or None.
    """
    nfeat = sum(1 for k in centre if k.startswith("feat"))
    num = den = None
    for frame, dt_lw in zip(frames, dt_weights):

        def log_weight(nb: Neighbours, frame=frame, dt_lw=dt_lw):
            dyf = jnp.asarray(nb.dy).astype(centre["color"].dtype)
            dxf = jnp.asarray(nb.dx).astype(centre["color"].dtype)
            lw = -lam["spatial"] * (dyf * dyf + dxf * dxf)
            if dt_lw is not None:
                lw = lw + dt_lw
            if lam.get("color") is not None:
                diff = centre["color"] - nb.get("color")
                if "color_var" in centre:
                    # Eq. 11 per channel; ZETA keeps 0/0 out where both variances are 0.
                    dist = channel_sum(diff * diff / (centre["color_var"] + nb.get("color_var") + ZETA))
                else:
                    dist = channel_sum_sq(diff)
                lw = lw - lam["color"] * clamp_dist(dist)
            for k in range(nfeat):
                d = centre[f"feat{k}"] - nb.get(f"feat{k}")
                lw = lw - centre[f"scale{k}"] * clamp_dist(channel_sum_sq(d))
            return lw

        n, d = window_sums(log_weight, frame, "color", radius=radius)
        num = n if num is None else num + n
        den = d if den is None else den + d
    return num, den


def prepare_window(color, color_var, features, feature_vars, lam_spatial, lam_color, lam_features, hw, dt):
    """Cast to ``dt``, go planar, and build the centre dict and lam dict shared by the 2-D and 3-D filters."""
    centre = {"color": to_planar(color.astype(dt))}
    lam = {"spatial": to_planar(lam_spatial.astype(dt))}
    lam["color"] = None if lam_color is None else to_planar(lam_color.astype(dt))
    if color_var is not None and lam_color is not None:
        centre["color_var"] = to_planar(color_var.astype(dt))
    for k, (f, v, l) in enumerate(zip(features, feature_vars, lam_features)):
        centre[f"feat{k}"] = to_planar(f.astype(dt))
        # Eq. 12: the centre pixel's variance, floored at DELTA (which also keeps the division safe).
        floor = jnp.asarray(DELTA, dt) if v is None else jnp.maximum(to_planar(v.astype(dt)), DELTA)
        centre[f"scale{k}"] = to_planar(l.astype(dt)) / floor
    return centre, lam


def cross_bilateral(color, color_var, features: Sequence[Any], feature_vars: Sequence[Any],
                    lam_spatial, lam_color, lam_features: Sequence[Any], *, radius: int) -> jax.Array:
    """Cross-bilateral filter, Kalantari 2015 Eq. 1-2 with the distances of Eq. 11-12 (module docstring)."""
    radius = check_radius(radius)
    col = as_image(color, "color")
    hw = col.shape[:2]
    cvar = None
    if color_var is not None:
        cvar = check_color_var(color_var, col, hw)
    feats, fvars, lams_f = feature_inputs(features, feature_vars, lam_features, hw)
    lam_s = as_param(lam_spatial, "lam_spatial", hw)
    lam_c = None if cvar is None else as_param(lam_color, "lam_color", hw)

    out_dtype = col.dtype if jnp.issubdtype(col.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(col, lam_s, *feats, *lams_f, *([lam_c] if lam_c is not None else []))
    centre, lam = prepare_window(col, cvar, feats, fvars, lam_s, lam_c, lams_f, hw, dt)
    frame = {"color": centre["color"]}
    if "color_var" in centre:
        frame["color_var"] = centre["color_var"]
    for k in range(len(feats)):
        frame[f"feat{k}"] = centre[f"feat{k}"]
    num, den = cross_sums(centre, [frame], lam, radius=radius, dt_weights=[None])
    return from_planar(num / den).astype(out_dtype)  # den >= 1: the centre weight is exactly 1


def bilateral(image, lam_spatial, lam_range, *, radius: int) -> jax.Array:
    """Plain bilateral filter (Tomasi & Manduchi 1998), the non-cross baseline (module docstring)."""
    radius = check_radius(radius)
    img = as_image(image, "image")
    hw = img.shape[:2]
    lam_s = as_param(lam_spatial, "lam_spatial", hw)
    lam_r = as_param(lam_range, "lam_range", hw)
    out_dtype = img.dtype if jnp.issubdtype(img.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(img, lam_s, lam_r)
    centre, lam = prepare_window(img, None, [], [], lam_s, lam_r, [], hw, dt)
    num, den = cross_sums(centre, [{"color": centre["color"]}], lam, radius=radius, dt_weights=[None])
    return from_planar(num / den).astype(out_dtype)  # den >= 1 (centre weight 1)


def spatiotemporal_cross_bilateral(color, color_var, features: Sequence[Any], feature_vars: Sequence[Any],
                                   lam_spatial, lam_color, lam_features: Sequence[Any], *, radius: int,
                                   lam_temporal: Any = 0.0, center: int | None = None) -> jax.Array:
    """Spatio-temporal cross-bilateral over a (T, H, W, C) volume, Kalantari 2015 Sec. 5 (module docstring)."""
    radius = check_radius(radius)
    if np.ndim(color) != 4:
        raise FilterError(f"argument 'color' has shape {np.shape(color)}; expected (T, H, W, C), e.g. T = 7")
    t, h, w, c = np.shape(color)
    if center is None:
        center = t // 2
    if not isinstance(center, (int, np.integer)) or not 0 <= center < t:
        raise FilterError(f"argument 'center' is {center!r}; expected an int in [0, {t})")
    hw = (h, w)
    col = _as_volume(color, "color", t, hw)
    cvar = None
    if color_var is not None:
        cvar = _as_volume(color_var, "color_var", t, hw)
        if cvar.shape[-1] not in (1, c):
            raise FilterError(f"argument 'color_var' has {cvar.shape[-1]} channels; expected 1 or {c}")
    _check_features(features, feature_vars, lam_features, hw)
    feats = [_as_volume(f, f"features[{k}]", t, hw) for k, f in enumerate(features)]
    fvars = [var_map(v, f"feature_vars[{k}]", hw, lead=(t,)) for k, v in enumerate(feature_vars)]
    lams_f = [as_param(l, f"lam_features[{k}]", hw) for k, l in enumerate(lam_features)]
    lam_s = as_param(lam_spatial, "lam_spatial", hw)
    lam_c = None if cvar is None else as_param(lam_color, "lam_color", hw)
    lam_t = as_param(lam_temporal, "lam_temporal", hw)
    feats, fvars, lams_f = _drop_constant(features, feats, fvars, lams_f)

    out_dtype = col.dtype if jnp.issubdtype(col.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(col, lam_s, lam_t, *feats, *lams_f)
    centre, lam = prepare_window(col[center], None if cvar is None else cvar[center], [f[center] for f in feats],
                           [None if v is None else v[center] for v in fvars], lam_s, lam_c, lams_f, hw, dt)
    frames, dts = [], []
    for s in range(t):
        fr = {"color": to_planar(col[s].astype(dt))}
        if "color_var" in centre:
            fr["color_var"] = to_planar(cvar[s].astype(dt))
        for k, f in enumerate(feats):
            fr[f"feat{k}"] = to_planar(f[s].astype(dt))
        frames.append(fr)
        dts.append(None if s == center else -to_planar(lam_t.astype(dt)) * float((s - center) ** 2))
    num, den = cross_sums(centre, frames, lam, radius=radius, dt_weights=dts)
    return from_planar(num / den).astype(out_dtype)  # den >= 1: centre pixel of the centre frame has weight 1
