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

Every filter here takes ``engine=`` (`ENGINES`): ``"tiles"`` (default, ``_tiles.py``: blocks of pixel
pairs in cache, memory O(H W C) plus one group of pairs) or ``"offsets"`` (``_window.py``: running
sums over the window offsets, O(H W C)); both evaluate the same per-pair log-weight and agree to
float32 rounding (docs/methods/bilateral.md). Shared behaviour: neighbours outside the image (or
outside the frame range) get weight 0; the centre weight is exactly 1, so when all other weights
underflow the output is the centre pixel (documented fallback, never NaN). A feature that is
constant over the frame (checked on concrete inputs, i.e.
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
from ._tiles import tile_sums
from ._window import Neighbours, clamp_dist, from_planar, sum_channels, to_planar, window_sums

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


# Window engines of the cross-bilateral family (the per-pair arithmetic below is shared by both):
# "tiles" (default, `_tiles.py`: blocks of pixel pairs in cache, the sums as matrix products) and
# "offsets" (`_window.py`: one pass over the frame per window offset; the previous engine, kept as
# the reference the tiled one is tested and benchmarked against).
ENGINES = ("tiles", "offsets")


def _sq(a, b):
    d = a - b
    return d * d


def sq_over_var(a, b, va, vb):
    """``(a - b)^2 / (va + vb + zeta)``: one channel of Eq. 11 (and of NLM's Eq. 17); ZETA keeps 0/0
    out where both variances are 0."""
    d = a - b
    return d * d / (va + vb + ZETA)


def _pair_log_weight(ci, nj, frame: int, d2, *, split: bool):
    """``log d_ij`` of Eq. 2 with Eq. 11-12 for frame ``frame`` of the window. ``ci`` / ``nj`` map
    names to the pixel-i / pixel-j arrays, channels on axis 0 and broadcastable against each other
    (planar frames for the offset engine, ``(C, g, P, 1)`` / ``(C, g, 1, N)`` pair blocks for the
    tiled one); ``d2`` is the squared pixel distance; ``split``: see `_window.sum_channels`. Returns the
    log-weight with a leading axis of 1."""
    lw = -ci["lam_s"] * d2
    if f"dt{frame}" in ci:  # Sec. 5: the temporal term of a neighbour frame
        lw = lw + ci[f"dt{frame}"]
    if "lam_c" in ci:
        if "color_var" in ci:  # Eq. 11 per channel
            dist = sum_channels(sq_over_var, (ci["color"], nj["color"], ci["color_var"], nj["color_var"]), split)
        else:
            dist = sum_channels(_sq, (ci["color"], nj["color"]), split)
        lw = lw - ci["lam_c"] * clamp_dist(dist)
    k = 0
    while f"feat{k}" in ci:  # Eq. 12
        lw = lw - ci[f"scale{k}"] * clamp_dist(sum_channels(_sq, (ci[f"feat{k}"], nj[f"feat{k}"]), split))
        k += 1
    return lw


def cross_sums(centre: dict, frames: list[dict], *, radius: int, engine: str = "tiles"):
    """The two sums of Eq. 1 over the window, summed over neighbour frames (one frame for the 2-D
    filters). Returns ``(num (H, W, C), den (H, W, 1))``; ``den >= 1`` (the centre weight is 1).

    ``centre``: the pixel-i arrays, HWC or scalars: ``color``, ``lam_s``, optional ``lam_c`` and
    ``color_var``, ``feat{k}`` with the precomputed scales ``scale{k} = lam_k / max(psi_k^2,
    delta)``, and ``dt{f}`` (``-lam_t dt^2``) for every neighbour frame ``f`` but the centre's.
    ``frames``: per neighbour frame, the pixel-j arrays (``color``, ``color_var``, ``feat{k}``).
    ``engine``: one of `ENGINES`.
    """
    if engine == "tiles":
        return tile_sums(lambda ci, nj, f, d2: _pair_log_weight(ci, nj, f, d2, split=True)[0], centre, frames,
                         "color", radius=radius)
    if engine != "offsets":
        raise FilterError(f"argument 'engine' is {engine!r}; expected one of {ENGINES}")
    cp = {k: to_planar(v) for k, v in centre.items()}
    num = den = None
    for f, frame in enumerate(frames):
        fp = {k: to_planar(v) for k, v in frame.items()}

        def log_weight(nb: Neighbours, f=f, fp=fp):
            dyf = jnp.asarray(nb.dy).astype(cp["color"].dtype)
            dxf = jnp.asarray(nb.dx).astype(cp["color"].dtype)
            return _pair_log_weight(cp, {k: nb.get(k) for k in fp}, f, dyf * dyf + dxf * dxf, split=False)

        n, d = window_sums(log_weight, fp, "color", radius=radius)
        num = n if num is None else num + n
        den = d if den is None else den + d
    return from_planar(num), from_planar(den)


def prepare_window(color, color_var, features, feature_vars, lam_spatial, lam_color, lam_features, dt):
    """Cast to ``dt`` and build the pixel-i dict of `cross_sums` shared by the 2-D and 3-D filters
    (``lam_color`` None: no colour term)."""
    centre = {"color": color.astype(dt), "lam_s": lam_spatial.astype(dt)}
    if lam_color is not None:
        centre["lam_c"] = lam_color.astype(dt)
        if color_var is not None:
            centre["color_var"] = color_var.astype(dt)
    for k, (f, v, l) in enumerate(zip(features, feature_vars, lam_features)):
        centre[f"feat{k}"] = f.astype(dt)
        # Eq. 12: the centre pixel's variance, floored at DELTA (which also keeps the division safe).
        floor = jnp.asarray(DELTA, dt) if v is None else jnp.maximum(v.astype(dt), DELTA)
        centre[f"scale{k}"] = l.astype(dt) / floor
    return centre


def _frame(centre: dict) -> dict:
    """The pixel-j arrays of a 2-D filter: those of `prepare_window`'s dict that are read at j."""
    return {k: v for k, v in centre.items() if k in ("color", "color_var") or k.startswith("feat")}


def cross_bilateral(color, color_var, features: Sequence[Any], feature_vars: Sequence[Any],
                    lam_spatial, lam_color, lam_features: Sequence[Any], *, radius: int,
                    engine: str = "tiles") -> jax.Array:
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
    centre = prepare_window(col, cvar, feats, fvars, lam_s, lam_c, lams_f, dt)
    num, den = cross_sums(centre, [_frame(centre)], radius=radius, engine=engine)
    return (num / den).astype(out_dtype)  # den >= 1: the centre weight is exactly 1


def bilateral(image, lam_spatial, lam_range, *, radius: int, engine: str = "tiles") -> jax.Array:
    """Plain bilateral filter (Tomasi & Manduchi 1998), the non-cross baseline (module docstring)."""
    radius = check_radius(radius)
    img = as_image(image, "image")
    hw = img.shape[:2]
    lam_s = as_param(lam_spatial, "lam_spatial", hw)
    lam_r = as_param(lam_range, "lam_range", hw)
    out_dtype = img.dtype if jnp.issubdtype(img.dtype, jnp.floating) else jnp.float32
    dt = compute_dtype(img, lam_s, lam_r)
    centre = prepare_window(img, None, [], [], lam_s, lam_r, [], dt)
    num, den = cross_sums(centre, [_frame(centre)], radius=radius, engine=engine)
    return (num / den).astype(out_dtype)  # den >= 1 (centre weight 1)


def spatiotemporal_cross_bilateral(color, color_var, features: Sequence[Any], feature_vars: Sequence[Any],
                                   lam_spatial, lam_color, lam_features: Sequence[Any], *, radius: int,
                                   lam_temporal: Any = 0.0, center: int | None = None,
                                   engine: str = "tiles") -> jax.Array:
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
    centre = prepare_window(col[center], None if cvar is None else cvar[center], [f[center] for f in feats],
                            [None if v is None else v[center] for v in fvars], lam_s, lam_c, lams_f, dt)
    frames = []
    for s in range(t):
        fr = {"color": col[s].astype(dt)}
        if "color_var" in centre:
            fr["color_var"] = cvar[s].astype(dt)
        for k, f in enumerate(feats):
            fr[f"feat{k}"] = f[s].astype(dt)
        frames.append(fr)
        if s != center:
            centre[f"dt{s}"] = -lam_t.astype(dt) * float((s - center) ** 2)
    num, den = cross_sums(centre, frames, radius=radius, engine=engine)
    return (num / den).astype(out_dtype)  # den >= 1: centre pixel of the centre frame has weight 1
