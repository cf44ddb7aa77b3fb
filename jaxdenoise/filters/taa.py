"""Temporal anti-aliasing (TAA) of a denoised sequence: each frame's output blended with the previous
frames' result reprojected through the scene's geometry (Karis 2014, "High quality temporal
supersampling"). Chaitanya et al. 2017 (Sec. 5.4, "Temporal antialiasing ... we apply TAA as a
supplemental post-process pass to all methods. Our method also benefits from TAA because the
recurrent loops at finer resolutions have insufficient temporal receptive field to reproject the
high-frequency features") evaluate every method so; the paper gives no TAA parameters (ours,
docs/methods/rae.md "Temporal anti-aliasing").

``taa_init(shape) -> TaaState``; ``taa_step(state, current, position, normal, world_to_ndc, *, alpha,
window, tolerance) -> (state, out)``; ``reproject(state, position, normal, *, tolerance, knee) -> (image,
count, valid)``; ``hdr_weight(x, knee)``; ``check_taa_settings(owner, alpha, window, tolerance)``;
``accumulate_step(state, current, position, normal, world_to_ndc, *, frames, tolerance, clamp) -> (state,
mean, length)``: the same reprojection averaging a sequence's noisy inputs (no HDR weights, no
neighbourhood clamp; its docstring).

One step, for the frame ``t`` whose denoised output is ``current`` ``(H, W, C)``:

1. **Reproject**: every pixel's world ``position`` (a surface hit: ``normal`` non-zero) goes through
   the previous frame's ``world_to_ndc`` (`jaxdenoise.view` conventions: NDC ``x`` left to right,
   ``y`` bottom to top, in [-1, 1]) to a point of the previous frame's pixel grid, and the previous
   result is read there bilinearly. A tap counts only if it lies in the frame and hit a surface and,
   with ``tolerance`` > 0, its world position lies within ``tolerance`` times the point's depth in
   the previous camera (its ``w``) of the pixel's tangent plane (the distance along the pixel's
   normal: a neighbour on the same surface passes at any angle, a disocclusion or a tap across a
   silhouette fails). The taps that pass are renormalised; below half a tap's weight in all, the
   pixel has no history. ``tolerance`` 0 leaves the rejection to the clamp (Karis 2014).
2. **Clamp** (``window`` > 0, Karis 2014 Sec. "Clamping"): the reprojected colour is clipped per
   channel to the minimum and maximum of ``current`` over the pixel's ``window`` x ``window``
   neighbourhood (the border repeated), which limits ghosting where the shading changed (a moving
   highlight) at the price of keeping less history. 0: no clamp.
3. **Blend**: ``out = (w_c current + w_h history) / (w_c + w_h)`` with ``w_c = s(current) / n`` and
   ``w_h = s(history) (1 - 1 / n)``, ``n`` the pixel's history length plus one, capped at ``1 /
   alpha``: a running mean over the first frames, then an exponential one of weight ``alpha`` (Karis
   blends at a fixed ``alpha``; the running start makes a short sequence's first frames count). A
   pixel without history (no hit, a failed reprojection, the first frame) takes ``current``, ``n = 1``.

**HDR** (Karis 2014, "weigh by the inverse of luminance"): ``s(x) = 1 / (1 + luminance(x) / knee)``
(`hdr_weight`) weighs every colour in the bilinear read and the blend, with ``knee`` the frame's
exposure level (`jaxdenoise.color.exposure_level` of ``current``, constant in the gradient; a black
frame, level <= 1e-12, weighs every colour 1). Without it a light's pixel read into a neighbour's
history by one bilinear tap, or let through by a clamp whose neighbourhood holds the light, brightens
a dark surface by orders of magnitude (measured: docs/methods/rae.md). The price: the weights favour
darker colours, so a noisy sequence comes out a few percent darker (`rae` runs TAA before its level
match, which puts the level back).

Every output is a convex combination of ``current`` and reprojected previous results, and the knee
scales with the frame, so ``taa(k x) = k taa(x)`` for ``k > 0`` (up to rounding): an exposure-
normalised method stays so. The state is a pytree (`TaaState`): the last result, its positions, hit
mask, camera and history lengths. Static settings (``alpha``, ``window``, ``tolerance``) are
keyword-only and checked by `check_taa_settings`; no parameter gradients.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import is_concrete
from ..color import exposure_level, luminance
from ..view import has_hit
from ._common import FilterError, as_image, require_finite


class TaaState(NamedTuple):
    """What `taa_step` carries from one frame to the next (a pytree; ``count`` 0 = no history)."""

    image: jax.Array  # (H, W, C) the last result
    position: jax.Array  # (H, W, 3) its world positions
    hit: jax.Array  # (H, W, 1) float 0 / 1: its pixels that hit a surface
    world_to_ndc: jax.Array  # (4, 4) its camera
    count: jax.Array  # (H, W, 1) its history lengths (frames blended), 0 before the first frame


def _check_settings(alpha: Any, window: Any, tolerance: Any, names: tuple[str, str, str]) -> None:
    if not (isinstance(alpha, (int, float, np.floating)) and 0 < alpha <= 1):
        raise FilterError(f"{names[0]} must be in (0, 1] (1: no history kept), got {alpha!r}")
    if not (isinstance(window, (int, np.integer)) and not isinstance(window, bool)
            and (window == 0 or window >= 3 and window % 2)):
        raise FilterError(f"{names[1]} must be 0 (no clamp) or an odd number of pixels >= 3, got {window!r}")
    if not (isinstance(tolerance, (int, float, np.floating)) and np.isfinite(tolerance) and tolerance >= 0):
        raise FilterError(f"{names[2]} must be a finite number >= 0 (a fraction of the depth; 0: no geometric "
                          f"test), got {tolerance!r}")


def check_taa_settings(owner: str, alpha: Any, window: Any, tolerance: Any) -> None:
    """Refuse, naming ``owner`` (e.g. ``"rae: config."``) and its ``taa_alpha`` / ``taa_window`` /
    ``taa_tolerance``, settings `taa_step` cannot take."""
    _check_settings(alpha, window, tolerance, (f"{owner}taa_alpha", f"{owner}taa_window", f"{owner}taa_tolerance"))


def taa_init(shape: tuple[int, ...]) -> TaaState:
    """The state before the first frame, for frames of ``shape`` ``(..., H, W, C)`` (leading axes: a
    batch of independent sequences)."""
    if len(shape) < 3:
        raise FilterError(f"taa_init: expected a frame's shape (..., H, W, C), got {tuple(shape)}")
    *lead, h, w, c = (int(s) for s in shape)
    lead = tuple(lead)
    return TaaState(jnp.zeros(lead + (h, w, c), jnp.float32), jnp.zeros(lead + (h, w, 3), jnp.float32),
                    jnp.zeros(lead + (h, w, 1), jnp.float32),
                    jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), lead + (4, 4)),
                    jnp.zeros(lead + (h, w, 1), jnp.float32))


def reproject(state: TaaState, position: Any, normal: Any, *, tolerance: float = 0.0, knee: Any = None
              ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``state``'s result and history lengths read at where this frame's surface points were in the
    previous frame (step 1 of the module docstring): ``(image (H, W, C), count (H, W, 1), valid
    (H, W, 1) bool)``; image and count are 0 where not valid. With ``knee`` (a luminance), each tap's
    colour is weighted by `hdr_weight` as well (the history lengths are not)."""
    h, w = state.image.shape[:2]
    p = as_image(position, "position", hw=(h, w), channels=3).astype(jnp.float32)
    n = as_image(normal, "normal", hw=(h, w), channels=3).astype(jnp.float32)
    hit = has_hit(n)[..., 0]
    unit = n * jax.lax.rsqrt(jnp.where(hit, jnp.sum(n * n, axis=-1), 1.0))[..., None]  # finite gradient at 0
    m = jnp.asarray(state.world_to_ndc, jnp.float32)
    q = jnp.einsum("ij,hwj->hwi", m[:, :3], p) + m[:, 3]
    depth = q[..., 3]
    ok = hit & (depth > 0)
    safe = jnp.where(ok, depth, 1.0)
    col = (q[..., 0] / safe + 1.0) * 0.5 * w - 0.5
    row = (1.0 - q[..., 1] / safe) * 0.5 * h - 0.5
    ok = ok & (col > -1) & (col < w) & (row > -1) & (row < h)
    col, row = jnp.where(ok, col, 0.0), jnp.where(ok, row, 0.0)
    c0, r0 = jnp.floor(col), jnp.floor(row)
    fx, fy = col - c0, row - r0
    c0, r0 = c0.astype(jnp.int32), r0.astype(jnp.int32)
    flat = lambda a: a.reshape(h * w, a.shape[-1])  # noqa: E731
    img, pos, was_hit, cnt = (flat(state.image), flat(state.position), flat(state.hit), flat(state.count))
    total = jnp.zeros((h, w), jnp.float32)
    acc = jnp.zeros(state.image.shape, jnp.float32)
    acc_w = jnp.zeros((h, w, 1), jnp.float32)
    acc_n = jnp.zeros((h, w), jnp.float32)
    for dr, dc, wt in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):
        r, c = r0 + dr, c0 + dc
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        idx = jnp.clip(r, 0, h - 1) * w + jnp.clip(c, 0, w - 1)
        tap_pos = jnp.take(pos, idx, axis=0)
        near = (jnp.abs(jnp.sum(unit * (tap_pos - p), axis=-1)) <= tolerance * depth) if tolerance else True
        good = ok & inside & (jnp.take(was_hit, idx, axis=0)[..., 0] > 0) & near
        wt = jnp.where(good, wt, 0.0)
        total = total + wt
        tap = jnp.take(img, idx, axis=0)
        wc = wt[..., None] * (1.0 if knee is None else hdr_weight(tap, knee))
        acc, acc_w = acc + wc * tap, acc_w + wc
        acc_n = acc_n + wt * jnp.take(cnt, idx, axis=0)[..., 0]
    valid = total >= 0.5
    norm = jnp.where(valid, total, 1.0)
    good_w = valid[..., None] & (acc_w > 0)  # acc_w is 0 only if every tap's weight underflowed
    image = jnp.where(good_w, acc / jnp.where(good_w, acc_w, 1.0), 0.0)
    count = jnp.where(valid, jnp.round(acc_n / norm), 0.0)[..., None]
    return image, count, good_w & (count > 0)


def hdr_weight(x: jax.Array, knee: Any) -> jax.Array:
    """Karis 2014's weight of an HDR colour in a blend, ``1 / (1 + luminance / knee)`` ``(..., 1)``: a
    sample far brighter than the knee (a light, a firefly) counts little against darker ones, so a
    blend of a few cannot spread it; at luminance 0 the weight is 1."""
    return 1.0 / (1.0 + luminance(jnp.maximum(x, 0.0))[..., None] / knee)


def _neighbourhood(x: jax.Array, window: int) -> tuple[jax.Array, jax.Array]:
    r = window // 2
    xp = jnp.pad(x, ((r, r), (r, r), (0, 0)), mode="edge")
    dims, strides = (window, window, 1), (1, 1, 1)
    lo = jax.lax.reduce_window(xp, jnp.inf, jax.lax.min, dims, strides, "VALID")
    hi = jax.lax.reduce_window(xp, -jnp.inf, jax.lax.max, dims, strides, "VALID")
    return lo, hi


def _check_frame(owner: str, current: Any, position: Any, normal: Any, world_to_ndc: Any) -> bool:
    """Refuse a missing or non-finite argument of `taa_step` / `accumulate_step` (``owner``) by name; True
    when ``current`` has leading axes (the caller then maps itself over them; inside that map the values
    are traced, so the images are checked here, else by `as_image`)."""
    args = (("current", current), ("position", position), ("normal", normal), ("world_to_ndc", world_to_ndc))
    for name, a in args:
        if a is None:
            raise FilterError(f"{owner}: argument '{name}' is None; it reprojects through the world positions, "
                              f"normals and camera of every frame")
    require_finite(world_to_ndc, "world_to_ndc")
    if np.ndim(current) <= 3:
        return False
    for name, a in args[:3]:
        require_finite(a, name)
    return True


def _one_frame(owner: str, state: TaaState, current: Any, world_to_ndc: Any) -> tuple[jax.Array, jax.Array]:
    """``current`` as a checked float32 image of the history's shape and ``world_to_ndc`` as a (4, 4) matrix."""
    x = as_image(current, "current").astype(jnp.float32)
    if state.image.shape != x.shape:
        raise FilterError(f"{owner}: the frame has shape {tuple(x.shape)} but the carried history "
                          f"{tuple(state.image.shape)}")
    m = jnp.asarray(world_to_ndc, jnp.float32)
    if m.shape != (4, 4):
        raise FilterError(f"{owner}: argument 'world_to_ndc' has shape {tuple(m.shape)}; expected (4, 4)")
    return x, m


def taa_step(state: TaaState, current: Any, position: Any, normal: Any, world_to_ndc: Any, *,
             alpha: float = 0.25, window: int = 3, tolerance: float = 0.0) -> tuple[TaaState, jax.Array]:
    """One frame of TAA (module docstring): ``current`` ``(H, W, C)`` blended with ``state``'s
    reprojected result; returns the new state and the frame's result. Leading axes (``(..., H, W,
    C)``, with ``world_to_ndc`` ``(4, 4)`` or ``(..., 4, 4)`` and a state from `taa_init` of the same
    shape) are independent sequences."""
    _check_settings(alpha, window, tolerance, ("argument 'alpha'", "argument 'window'", "argument 'tolerance'"))
    if _check_frame("taa", current, position, normal, world_to_ndc):
        x = jnp.asarray(current, jnp.float32)
        lead = x.shape[:-3]
        m = jnp.broadcast_to(jnp.asarray(world_to_ndc, jnp.float32), lead + (4, 4))
        flat = lambda a: a.reshape((-1,) + a.shape[len(lead):])  # noqa: E731
        one = lambda st, *a: taa_step(st, *a, alpha=alpha, window=window, tolerance=tolerance)  # noqa: E731
        st, out = jax.vmap(one)(jax.tree_util.tree_map(flat, state), flat(x),
                                flat(jnp.asarray(position, jnp.float32)), flat(jnp.asarray(normal, jnp.float32)),
                                flat(m))
        return jax.tree_util.tree_map(lambda a: a.reshape(lead + a.shape[1:]), st), out.reshape(x.shape)
    x, m = _one_frame("taa", state, current, world_to_ndc)
    level = jax.lax.stop_gradient(exposure_level(x))  # a frame statistic, as `color.exposure_scale` holds it
    knee = jnp.where(level > 1e-12, level, jnp.inf)  # a black frame: no weighting (every weight 1)
    hist, count, valid = reproject(state, position, normal, tolerance=tolerance, knee=knee)  # checks both
    p, n = jnp.asarray(position, jnp.float32), jnp.asarray(normal, jnp.float32)
    if window:
        lo, hi = _neighbourhood(x, window)
        hist = jnp.clip(hist, lo, hi)
    length = jnp.where(valid, jnp.minimum(count + 1.0, 1.0 / alpha), 1.0)
    wx, wh = hdr_weight(x, knee) / length, hdr_weight(hist, knee) * (1.0 - 1.0 / length)
    den = wx + wh
    blend = valid & (den > 0)  # den is 0 only for colours beyond float range over the knee
    out = jnp.where(blend, (wx * x + wh * hist) / jnp.where(blend, den, 1.0), x)
    return TaaState(out, p, has_hit(n).astype(jnp.float32), m, length), out


def accumulate_step(state: TaaState, current: Any, position: Any, normal: Any, world_to_ndc: Any, *,
                    frames: Any = 4.0, tolerance: float = 0.02, clamp: float = 4.0
                    ) -> tuple[TaaState, jax.Array, jax.Array]:
    """One frame of temporal accumulation of a *noisy input* with `reproject` (step 1 of the module
    docstring): ``current`` ``(H, W, C)``, a Monte Carlo estimate, is averaged with the previous frames'
    accumulated estimate read where this frame's surface points were, as a running mean of at most
    ``frames`` frames (a number, or per pixel ``(H, W, 1)``: a frame of fewer samples may keep a longer
    history; then exponential, of weight ``1 / frames``; ``frames`` <= 1: no history). Returns ``(state,
    mean, length)``, ``length`` ``(H, W, 1)`` the frames averaged per pixel (1 without history), so a
    caller can tell each pixel's samples (its rate times ``length``; an exponential tail counted as a
    running mean).

    Unlike `taa_step` no colour is weighed by its luminance, in the read or the blend (a mean of unbiased
    estimates stays unbiased; Karis's weights, tried as the read's tap weights, darkened 1-spp inputs by
    5-12 % over a 7-frame sequence: docs/methods/rae.md "Input accumulation"), and the history is not
    clamped to the frame's range (one noisy sample's neighbourhood does not bound a mean). Two guards
    stand in: the tangent-plane test (``tolerance``, a fraction of the depth, as in `reproject`; 0: none)
    keeps a disocclusion or a silhouette from blending another surface in, and with ``clamp`` > 0 the
    read history's luminance is limited to ``clamp`` times the larger of the frame's exposure level and
    the current frame's 3x3 luminance maximum (hue kept), so a light's or a firefly's pixel next to the
    point read cannot bleed into a dark surface's history frame after frame (without it, a pixel 0.07 in
    the reference reached 12-20). Shading that changes from frame to frame (a moving highlight) lags by
    up to ``frames`` frames. Homogeneous: ``accumulate(k x) = k accumulate(x)``. Leading axes:
    independent sequences, as in `taa_step` (``frames`` then a number or ``(..., H, W, 1)``)."""
    for name, v in (("tolerance", tolerance), ("clamp", clamp)):
        if not (isinstance(v, (int, float, np.floating)) and np.isfinite(v) and v >= 0):
            raise FilterError(f"argument '{name}' must be a finite number >= 0 (0: off), got {v!r}")
    if frames is None or (is_concrete(frames) and not np.all(np.isfinite(np.asarray(frames, np.float64)))):
        raise FilterError(f"argument 'frames' must be finite (the longest history, in frames), got {frames!r}")
    if _check_frame("accumulate", current, position, normal, world_to_ndc):
        x = jnp.asarray(current, jnp.float32)
        lead = x.shape[:-3]
        m = jnp.broadcast_to(jnp.asarray(world_to_ndc, jnp.float32), lead + (4, 4))
        cap = jnp.broadcast_to(jnp.asarray(frames, jnp.float32).reshape(np.shape(frames) or (1, 1, 1)),
                               lead + x.shape[-3:-1] + (1,))
        flat = lambda a: a.reshape((-1,) + a.shape[len(lead):])  # noqa: E731
        one = lambda st, *a: accumulate_step(st, *a[:4], frames=a[4], tolerance=tolerance, clamp=clamp)  # noqa: E731
        st, out, n = jax.vmap(one)(jax.tree_util.tree_map(flat, state), flat(x),
                                   flat(jnp.asarray(position, jnp.float32)),
                                   flat(jnp.asarray(normal, jnp.float32)), flat(m), flat(cap))
        unflat = lambda a: a.reshape(lead + a.shape[1:])  # noqa: E731
        return jax.tree_util.tree_map(unflat, st), unflat(out), unflat(n)
    x, m = _one_frame("accumulate", state, current, world_to_ndc)
    hist, count, valid = reproject(state, position, normal, tolerance=tolerance)  # checks both
    if clamp:
        level = jax.lax.stop_gradient(exposure_level(x))
        _, hi = _neighbourhood(luminance(jnp.maximum(x, 0.0))[..., None], 3)
        bound = clamp * jnp.maximum(hi, level)
        lum = luminance(jnp.maximum(hist, 0.0))[..., None]
        hist = hist * jnp.where(lum > bound, bound / jnp.where(lum > bound, lum, 1.0), 1.0)
    cap = jnp.maximum(jnp.asarray(frames, jnp.float32), 1.0)
    length = jnp.where(valid, jnp.minimum(count + 1.0, cap), 1.0)
    out = jnp.where(valid, x / length + hist * (1.0 - 1.0 / length), x)
    p, n = jnp.asarray(position, jnp.float32), jnp.asarray(normal, jnp.float32)
    return TaaState(out, p, has_hit(n).astype(jnp.float32), m, length), out, length


__all__ = ["TaaState", "accumulate_step", "check_taa_settings", "hdr_weight", "reproject", "taa_init", "taa_step"]
