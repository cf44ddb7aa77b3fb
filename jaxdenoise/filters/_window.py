"""The per-offset window engine (private): the non-local-means filters' engine, and the
cross-bilateral's reference engine (``engine="offsets"``; the cross-bilateral runs on the tiled
engine of `_tiles.py` by default, docs/methods/bilateral.md).

Every filter of Kalantari 2015 Eq. 1 is a normalized weighted sum over a square window,
``out_i = sum_j d_ij c_j / sum_j d_ij``. Materializing ``d`` as an ``H x W x (2r+1)^2`` tensor is
out of the question for a 55 x 55 window on a 1200 x 800 frame (3025 x 960 000 floats = 11.6 GB),
so `window_sums` walks the offsets and keeps only running sums: the numerator ``(H, W, C)`` and the
denominator ``(H, W, 1)``. Memory is O(H (W + 2r) C) (below).

Layout: internally planar, ``(C, H, W)`` (the public filters take and return HWC and transpose
once). XLA's CPU backend vectorizes along the minor axis, and a minor axis of 3 channels measured
2x slower than a minor axis of W pixels.

Loop structure: a ``lax.fori_loop`` over the window's rows; within a row, steps of consecutive
column offsets unrolled in Python (one loop step per offset measured 2.3x slower on CPU): the whole
row when it has at most ``2 unroll`` columns (``unroll`` = 8 by default: the prefilter's 11 columns
are one step), else equal steps of at most ``unroll`` columns (55 -> 7 x 8) in an inner
``fori_loop``. Steps never compute columns past the window's edge except to even them out: the
earlier rule, steps of exactly ``unroll``, computed 16 columns for the prefilter's 11, and the
prefilter ran 1.85x slower (1.33 s against 0.72 s a 3-channel feature at 1200x800, interleaved runs
in one process). XLA's CPU backend does not make that one pass over the image: a profile shows one
fusion per offset that writes the offset's weight plane (the weight feeds both sums, and XLA does
not duplicate the ``exp``), then one fusion per sum that adds the ``unroll`` weighted planes.

Row blocks: each row cuts every padded array once, by one ``dynamic_slice``, to the rows of its
``dy`` and the columns of all its offsets; with several steps a row that block is the inner loop's
carry, moved ``unroll`` columns left after each step, and every offset reads it by a *static* slice
(`Neighbours`). A loop carry is materialized; a ``dynamic_slice`` per offset (0.9.5 and before) was
fused into the per-offset passes, whose loops then re-loaded the slice's start from memory at every
pixel, and LLVM did not vectorize them (XLA's LLVM dump: scalar divisions). `cross_nlm` (r = 27, 5x5
patches, 5 features) ran 1.49x faster this way at 1200x800 (34.1 s against 50.7 s), 2.4x at
400x600 and 2.8-3.6x at 256x384, within 2e-6 relative (interleaved in one process; the shift's
copies cost more at large frames). A row of one step (the prefilter's 11 columns) reads the padded
arrays by a ``dynamic_slice`` per offset, as 0.9.5 did: the row block made LBF's prefilter 1.2x
slower (2.44 s against 2.09 s at 1200x800, medians of five interleaved processes; outputs identical).

Memory: each row is wrapped in ``jax.checkpoint`` and its sums are added to the carry outside it,
and each inner step is checkpointed too, so reverse-mode AD stores the row index per row and, while
it recomputes a row, the carry of each of its steps: backward temporaries are O(H (W + 2r) C
steps), growing with the window's width (the number of steps), not its area (at 32x256, r = 12 ->
24: 1.05x forward, 1.4x backward; `tests/test_filters.py`). The forward holds the row blocks, about
twice the neighbour arrays.

Log-space weights: the caller returns ``log d_ij`` (always ``<= 0``, and exactly 0 at the centre
offset, where every distance is 0). Hence the centre weight is exactly 1, the denominator is >= 1,
and the output is a convex combination of in-image pixels. When every other weight underflows
(huge bandwidth parameters, or a pixel unlike all its neighbours) the filter returns the centre
pixel unchanged: this is the documented fallback, never a 0/0.

Edge handling: neighbours outside the image get weight exactly 0 (a validity mask multiplies the
weight), so nothing is invented beyond the border and border pixels average over fewer neighbours.
Offsets larger than the image are dropped statically (``ry = min(r, H - 1)``): they would only ever
read outside pixels, so the output is identical and the work is smaller.

Small blocks: block statistics over a tiny window (the ``3 x 3`` spike test, LBF's mean and median
absolute deviation features) need every value of the block at once (a median has no running sum),
so `jaxdenoise.arrays.edge_blocks` does materialize the ``(2r+1)^2`` neighbourhood of every pixel. It
works in HWC (with any leading axes) and completes border blocks by edge replication (`pad_edge`), so every block
has ``(2r+1)^2`` values. It is meant for radius 1 to 2, not for the filter windows above.
"""
from __future__ import annotations

from typing import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp

# Column offsets fused per loop step (see the module docstring).
UNROLL = 8

# Upper clamp on a squared distance before it is multiplied by a bandwidth parameter: keeps
# 0 * inf = NaN out of the exponent when a parameter is 0 and a distance overflowed float32
# (e.g. colour differences of 1e19 over the 1e-10 floor of Eq. 11). exp(-lam * 1e30) is 0 anyway
# for any lam that matters, so the clamp does not change a representable result.
MAX_DIST = 1e30


def to_planar(x: jax.Array) -> jax.Array:
    """(H, W, C) -> (C, H, W); scalars and (H, W, 1) parameter maps -> () / (1, H, W)."""
    return x if x.ndim == 0 else jnp.moveaxis(x, -1, 0)


def from_planar(x: jax.Array) -> jax.Array:
    """(C, H, W) -> (H, W, C)."""
    return jnp.moveaxis(x, 0, -1)


def channel_sum(x: jax.Array) -> jax.Array:
    """Sum of a planar (C, H, W) array over channels as (1, H, W), unrolled over the few channels."""
    out = x[0:1]
    for c in range(1, x.shape[0]):
        out = out + x[c:c + 1]
    return out


def sum_channels(term: Callable[..., jax.Array], arrays: Sequence[jax.Array], split: bool = True) -> jax.Array:
    """``sum_c term(*(a_c for a in arrays))`` over the channels (axis 0) as a one-channel array; an
    array with one channel serves every channel. ``split``: one term per channel slice, summed in
    channel order. A `channel_sum` of the term over the whole stack (``split=False``) is the same
    sum, but XLA's CPU backend then writes the stack's term for every channel to memory before
    summing: the tiled cross-bilateral ran 1.5x slower that way and the NLM prefilter wrote a 3-plane
    array per window offset. The cross-bilateral's offset engine keeps ``split=False``, its form
    as measured."""
    if not split:
        return channel_sum(term(*arrays))
    out = None
    for c in range(max(a.shape[0] for a in arrays)):
        t = term(*(a[min(c, a.shape[0] - 1):][:1] for a in arrays))
        out = t if out is None else out + t
    return out


def channel_sum_sq(d: jax.Array) -> jax.Array:
    """``sum_c d_c^2`` of a planar (C, H, W) difference as (1, H, W)."""
    return channel_sum(d * d)


def clamp_dist(d: jax.Array) -> jax.Array:
    """Clamp a non-negative distance to `MAX_DIST` (see the constant's comment)."""
    return jnp.minimum(d, MAX_DIST)


class Neighbours:
    """Accessor the per-offset term uses to read neighbour arrays at offset ``(dy, dx)``.

    ``get(name, halo=0)`` returns the ``(C, H + 2 halo, W + 2 halo)`` block of the padded array
    ``name`` whose centre block is shifted by the current offset; outside pixels read as 0 and the
    ``"valid"`` array (1 inside, 0 outside) says which they are.

    It reads the loop step's blocks (`window_sums`): each padded array cut to the rows of the step's
    ``dy`` (with the halo) and to columns starting at its first offset's, so ``get`` is a static
    slice at the offset's column ``col`` within the step.
    """

    def __init__(self, blocks: Mapping[str, jax.Array], halo: int, hw: tuple[int, int], dy, dx, col: int,
                 row=None):
        self._blocks = blocks
        self._halo = halo
        self._hw = hw
        self._col = col
        self._row = row  # None: the blocks hold the offset's rows; else (traced) the first of them in the blocks
        self.dy = dy  # traced int: offset row in [-ry, ry]
        self.dx = dx  # traced int: offset column in [-rx, rx] (or past rx in a masked last chunk)

    def get(self, name: str, halo: int = 0) -> jax.Array:
        a = self._blocks[name]
        h, w = self._hw
        x0 = self._col + self._halo - halo
        if self._row is None:
            y0 = self._halo - halo
            return a[:, y0:y0 + h + 2 * halo, x0:x0 + w + 2 * halo]
        start = (0, self._row + self._halo - halo, x0)
        return jax.lax.dynamic_slice(a, start, (a.shape[0], h + 2 * halo, w + 2 * halo))


def pad_arrays(arrays: Mapping[str, jax.Array], pad: int, extra_right: int = 0) -> dict[str, jax.Array]:
    """Zero-pad every planar (C, H, W) array by ``pad`` pixels (plus ``extra_right`` columns on the
    right) and add the ``"valid"`` mask (1 inside the image, 0 outside)."""
    any_a = next(iter(arrays.values()))
    h, w = any_a.shape[1:]
    widths = ((0, 0), (pad, pad), (pad, pad + extra_right))
    out = {k: jnp.pad(v, widths) for k, v in arrays.items()}
    out["valid"] = jnp.pad(jnp.ones((1, h, w), any_a.dtype), widths)
    return out


def window_sums(
    log_weight: Callable[[Neighbours], jax.Array],
    neighbours: Mapping[str, jax.Array],
    value: str,
    *,
    radius: int,
    halo: int = 0,
    unroll: int = UNROLL,
) -> tuple[jax.Array, jax.Array]:
    """Running sums ``(sum_j d_ij v_j, sum_j d_ij)`` over the ``(2r+1)^2`` window (module docstring).

    ``log_weight(nb)`` returns the ``(1, H, W)`` log-weight (``<= 0``) for the offset ``(nb.dy,
    nb.dx)``; ``neighbours`` are the unpadded planar ``(C, H, W)`` arrays it may read through ``nb.get``
    (``halo`` extra pixels around the block are readable, for patch distances); ``value`` names
    the array that is averaged. Weights of outside neighbours are zeroed here. ``unroll`` column
    offsets are fused per loop step.
    """
    v0 = neighbours[value]
    h, w = v0.shape[1:]
    ry, rx = min(radius, h - 1), min(radius, w - 1)
    ncol = 2 * rx + 1
    # A row of up to 2 * unroll columns is one step; longer rows equal steps of at most ``unroll``
    # columns (module docstring).
    nchunk = 1 if ncol <= 2 * unroll else -(-ncol // max(1, unroll))
    u = -(-ncol // nchunk)
    extra = nchunk * u - ncol  # column offsets past rx in the last chunk: read padding, masked below
    pad = max(ry, rx) + halo
    padded = pad_arrays(neighbours, pad, extra)
    bw = w + 2 * halo + nchunk * u - 1  # a row's block: the columns of all its offsets

    def chunk(num, den, blocks, dy, x0, col=0, row=None):
        for k in range(u):
            nb = Neighbours(blocks, halo, (h, w), dy, x0 + k, col + k, row)
            wgt = jnp.exp(log_weight(nb)) * nb.get("valid")
            if extra:
                wgt = jnp.where(x0 + k <= rx, wgt, 0.0)  # past the window's last column
            num = num + wgt * nb.get(value)
            den = den + wgt
        return num, den

    def row(i):
        dy = i - ry
        zero = (jnp.zeros(v0.shape, v0.dtype), jnp.zeros((1, h, w), v0.dtype))
        # The row's block of every array, cut by one dynamic_slice. With several steps per row it is the
        # column loop's carry, moved u columns left after each step: a loop carry is materialized, and
        # every offset then reads it by a static slice. Read by a dynamic_slice per offset instead, the
        # slice's start was re-loaded inside XLA's per-offset loops, which LLVM then did not vectorize:
        # `cross_nlm` ran 1.5-3.6x slower (docs/methods/bilateral.md).
        if nchunk == 1:  # one step: each offset slices the padded arrays (the row block measured 1.2x slower)
            return chunk(*zero, padded, dy, -rx, col=pad - rx - halo, row=pad + dy - halo)
        blocks = {k: jax.lax.dynamic_slice(a, (0, pad + dy - halo, pad - rx - halo), (a.shape[0], h + 2 * halo, bw))
                  for k, a in padded.items()}

        def step(j, c):
            num, den, blocks = c
            num, den = chunk(num, den, blocks, dy, j * u - rx)
            blocks = {k: jnp.concatenate([b[:, :, u:], jnp.zeros_like(b[:, :, :u])], 2) for k, b in blocks.items()}
            return num, den, blocks

        return jax.lax.fori_loop(0, nchunk, jax.checkpoint(step), (*zero, blocks))[:2]

    # Each row is wrapped in jax.checkpoint and its sums are added to the carry outside it, so reverse-mode
    # AD stores only the row index per row and recomputes the row in the backward pass.
    row = jax.checkpoint(row)

    def body(i, carry):
        num, den = carry
        dnum, dden = row(i)
        return num + dnum, den + dden

    init = (jnp.zeros(v0.shape, v0.dtype), jnp.zeros((1, h, w), v0.dtype))
    return jax.lax.fori_loop(0, 2 * ry + 1, body, init)
