"""Array helpers shared by filters, solvers and methods: concreteness test for eager validation,
the floating compute dtype, edge-replicated padding, pixel blocks and their median, a quantile without
sorting (not re-exported by `jaxdenoise`; `filters`, `solvers` and `methods` are peers, so none of
them owns these)."""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds values (not a tracer under ``jit``/``grad``/``vmap``), so value checks
    such as NaN/Inf or sign tests can run eagerly."""
    return not isinstance(x, jax.core.Tracer)


def compute_dtype(*xs: Any) -> Any:
    """The floating dtype to compute in: the promoted dtype of ``xs`` (``None`` entries skipped),
    but float32 at least. float16/bfloat16 and non-float inputs become float32 because squared
    distances and window sums of HDR radiance (filters), and the DC-mode division by a tiny alpha
    and the squared residuals (solvers), overflow or lose all precision below 32 bits."""
    dt = jnp.result_type(*[x for x in xs if x is not None])
    if not jnp.issubdtype(dt, jnp.floating) or jnp.finfo(dt).bits < 32:
        return jnp.float32
    return dt


def pad_edge(x: jax.Array, r: int) -> jax.Array:
    """Edge-replicate ``r`` pixels on the two spatial axes of an ``(..., H, W, C)`` array."""
    pad = [(0, 0)] * (x.ndim - 3) + [(r, r), (r, r), (0, 0)]
    return jnp.pad(x, pad, mode="edge")


def edge_blocks(x: jax.Array, r: int, *, axis: int = -1) -> jax.Array:
    """The ``(2r+1)^2`` values of the edge-padded ``(2r+1) x (2r+1)`` block around every pixel of an
    ``(..., H, W, C)`` array, stacked on a new axis ``axis`` (``-1``: ``(..., H, W, C, (2r+1)^2)``;
    ``0``: ``((2r+1)^2, ..., H, W, C)``).

    Entry ``k = (dy + r) (2r+1) + (dx + r)`` holds the neighbour at offset ``(dy, dx)`` (row-major,
    the centre pixel at ``k = 2r (r+1)``); outside pixels are edge-replicated (`pad_edge`). This
    materializes the whole stack: for small blocks only (module docstring).
    """
    return jnp.stack(edge_views(x, r), axis=axis)


def edge_views(x: jax.Array, r: int) -> list[jax.Array]:
    """The ``(2r+1)^2`` shifted views of `edge_blocks`, in its order, as a list (nothing stacked:
    block statistics over the views fuse into one elementwise pass, where XLA's CPU backend ran the
    stacked form about 10x slower for LBF's 3x3 mean deviation at 1200x800)."""
    h, w = x.shape[-3], x.shape[-2]
    p = pad_edge(x, r)
    return [p[..., dy:dy + h, dx:dx + w, :] for dy in range(2 * r + 1) for dx in range(2 * r + 1)]


# Devillard's 19 compare-exchanges for the median of 9 ("Fast median search: an ANSI C
# implementation", 1998, opt_med9, after Paeth, Graphics Gems 1990): after them, slot 4 holds the median.
_MED9 = ((1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 3), (5, 8), (4, 7),
         (3, 6), (1, 4), (2, 5), (4, 7), (4, 2), (6, 4), (4, 2))


def median9(values) -> jax.Array:
    """Elementwise median of nine same-shaped arrays (a sequence, or an array whose leading axis
    has 9 entries), by a sorting network of compare-exchanges.

    The result is one of the nine inputs, so it equals ``jnp.median(jnp.stack(values), axis=0)``
    exactly (finite inputs; with a NaN among the nine the result is unspecified, and the callers
    refuse NaN inputs). It fuses into one elementwise pass and is differentiable almost everywhere
    (the gradient goes to the selected input; at ties to one of them); ``jnp.median`` sorts, which
    XLA's CPU backend runs about 10x slower on a 3x3 block of every pixel (LBF's MAD feature: 3.2 s
    against 0.2 s for a 1200x800x3 image, measured). Each compare-exchange is one comparison and two
    selects: ``jnp.minimum`` / ``jnp.maximum`` (0.9.5 and before) propagate NaN, which XLA's CPU backend
    emits as extra compares and blends: LBF's MAD feature (two medians of nine) alone ran 2.6x slower
    that way (73 ms against 28 ms for a 1200x800x3 image, the same values, ties included), LBF's 36
    secondary features at 1200x800 0.50 s against 0.46 s (min of 8, interleaved in one process).
    """
    v = list(values)
    if len(v) != 9:
        raise ValueError(f"median9 takes 9 arrays, got {len(v)}")
    for a, b in _MED9:
        lt = v[a] < v[b]
        v[a], v[b] = jnp.where(lt, v[a], v[b]), jnp.where(lt, v[b], v[a])
    return v[4]


def _order_key(x: jax.Array) -> jax.Array:
    """float32 values as uint32 keys in the same order (the radix-sort map: a negative number's bits
    inverted, a non-negative one's sign bit set); -0.0 first made +0.0, so equal values share a key."""
    i = jax.lax.bitcast_convert_type(x.astype(jnp.float32) + jnp.float32(0.0), jnp.uint32)
    return jnp.where((i >> 31) == 1, ~i, i | jnp.uint32(0x80000000))


def quantile_lower(x: Any, q: float) -> jax.Array:
    """``jnp.quantile(x, q, axis=-1, method="lower")`` for float32 (or narrower) values without NaN, the
    same value without sorting (a zero may come back with the other sign): the element at sorted index
    ``floor(q (n - 1))`` (computed in float32, as jnp does) found by bisection over the values' order-
    preserving 32-bit keys, 32 counting passes over the axis. XLA's CPU sort of a 1280x720 frame's
    luminance took 280 ms, this 8 ms (docs/training.md "Speed on this CPU": the exposure statistic).
    ``q`` is a static number in [0, 1]; leading axes are independent. The gradient goes to the selected
    element (to each of equal ones, shared)."""
    x = jnp.asarray(x)
    q = float(q)
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"quantile_lower: q must be in [0, 1], got {q}")
    n = x.shape[-1]
    if n == 0:
        raise ValueError("quantile_lower: the last axis is empty")
    k = int(min(max(np.floor(np.float32(q) * (np.float32(n) - np.float32(1))), 0), n - 1))  # as jnp rounds it
    key = _order_key(x)

    def halve(_, bounds):  # the smallest key with at least k + 1 values at or below it lies in [lo, hi]
        lo, hi = bounds
        mid = lo + (hi - lo) // 2
        enough = jnp.sum(key <= mid[..., None], axis=-1) >= k + 1
        return jnp.where(enough, lo, mid + 1), jnp.where(enough, mid, hi)

    lo = jnp.zeros(x.shape[:-1], jnp.uint32)
    lo, _ = jax.lax.fori_loop(0, 32, halve, (lo, jnp.full(x.shape[:-1], 0xFFFFFFFF, jnp.uint32)))
    return jnp.max(jnp.where(key <= lo[..., None], x, -jnp.inf), axis=-1)
