"""The tiled window engine of the cross-bilateral filters (private): Kalantari 2015 Eq. 1 as
cache-sized blocks of pixel pairs and two matrix products, instead of one pass over the frame
per window offset (`_window.py`).

The frame is cut into ``t x t`` tiles of centre pixels ``i`` (``P = t^2``). A tile's neighbours
``j`` are the ``(t + 2r) x (t + 2r)`` block around it (``N`` pixels), so every pair ``(i, j)`` of
the window is one entry of a ``(P, N)`` matrix. For a group of ``g`` tiles the engine

1. gathers the group's neighbour blocks (one ``dynamic_slice`` per tile) and centre pixels,
2. asks the caller for the ``(g, P, N)`` log-weights, computed element-wise from the pixels'
   values (exact differences: ``f_i - f_j`` is 0 at ``j = i``, so the centre weight is exactly 1
   as in `_window.py`, and nothing cancels for world positions far from the origin),
3. multiplies ``exp`` of them by the constant ``(P, N)`` window mask (``|dy|, |dx| <= r``), and
4. forms both sums of Eq. 1 as one matrix product with the neighbours' ``[value * valid, valid]``
   (``valid`` is 1 inside the image, 0 in the padding, so outside neighbours get weight 0).

A group's arrays are about `GROUP_PAIRS` pairs per frame (8 MB a float32 array), so they stay in
the last-level cache, and the per-pair work is one fused element-wise pass: the offset engine spent
most of its time re-reading every feature plane from memory once per offset (about 180 bytes
per pixel-offset) and on XLA fusions that recompute the weight per consumer. The cost is the
pairs outside the window inside a tile's block: ``((t + 2r) / (2r + 1))^2``, 1.27x for LBF's
``r = 27`` with ``t = 8`` (`tile_size`).

Memory: each group is a ``lax.map`` step wrapped in ``jax.checkpoint``, so reverse-mode AD keeps
only the group's inputs and recomputes its pairs in the backward pass: O(H W C) plus one group.

Pixels of the last tile row / column beyond the frame are padding: their sums are computed and
dropped before the caller divides, so no 0/0 reaches the output or the gradient.
"""
from __future__ import annotations

from typing import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

# Pairs per group: one (g, P, N) float32 array of the group is about 8 MB (measured at 200x600 with
# r = 27: 2^21 pairs ran 1.05 s, the offset engine 2.5-4.6 s on the same inputs).
GROUP_PAIRS = 1 << 21


def tile_size(radius: int) -> int:
    """Centre tile edge ``t`` for window radius ``r``: 8 from r = 12 (1.27x wasted pairs at r = 27),
    smaller below so the tile's block stays close to the window (2 at r <= 3: 1.4x at r = 2)."""
    return int(min(8, max(2, radius // 2 + 1)))


def _as_hwc(x, hw, dt) -> jax.Array:
    """A scalar or (H, W, C) array as (H, W, C) in ``dt``."""
    x = jnp.asarray(x, dt)
    return jnp.broadcast_to(x, tuple(hw) + (1,)) if x.ndim == 0 else x


def tile_sums(
    log_weight: Callable[[dict, dict, int, jax.Array], jax.Array],
    centre: Mapping[str, jax.Array],
    frames: Sequence[Mapping[str, jax.Array]],
    value: str,
    *,
    radius: int,
) -> tuple[jax.Array, jax.Array]:
    """``(sum_j d_ij v_j, sum_j d_ij)`` over the ``(2r+1)^2`` window of every pixel, summed over
    ``frames`` (module docstring); returns ``(H, W, C_v)`` and ``(H, W, 1)``.

    ``centre``: arrays read at pixel ``i``, each a scalar or ``(H, W, C)``. ``frames``: per
    neighbour frame, the ``(H, W, C)`` arrays read at ``j`` (the same names in every frame;
    ``value`` among them). ``log_weight(ci, nj, f, d2)`` returns the ``(g, P, N)`` log-weight
    (``<= 0``) of frame ``f``, where ``ci[name]`` is ``(C, g, P, 1)`` and ``nj[name]`` is
    ``(C, g, 1, N)`` (channels first, like `_window.py`'s planar arrays) and ``d2`` is the
    ``(P, N)`` squared pixel distance ``dy^2 + dx^2``.
    """
    any_v = frames[0][value]
    h, w = any_v.shape[:2]
    dt = any_v.dtype
    r = int(radius)
    t = tile_size(r)
    nty, ntx = -(-h // t), -(-w // t)
    hc, wc = nty * t, ntx * t
    nh, nw = t + 2 * r, t + 2 * r
    p_n, n_n = t * t, nh * nw

    # Centre pixels, tiled: (ntiles, P, C) per name. Kept apart (not one stack) so that under
    # reverse-mode AD only the arrays that need a cotangent get one (LBF trains the lambdas alone).
    def tiles_of(a):
        a = jnp.pad(_as_hwc(a, (h, w), dt), ((0, hc - h), (0, wc - w), (0, 0)))
        c = a.shape[-1]
        return a.reshape(nty, t, ntx, t, c).transpose(0, 2, 1, 3, 4).reshape(nty * ntx, p_n, c)

    ctiles = {k: tiles_of(v) for k, v in centre.items()}

    # Neighbours of every frame, zero-padded by r (and the tile remainder) with the validity plane,
    # planar (channels first): a block's channel is then contiguous along its N pixels, the pair
    # pass's minor axis. With the channels last (before 0.9.6) XLA fused the block's transpose into
    # that pass and read every neighbour value with a stride of Cn floats: the filter ran 1.2-1.3x
    # slower, with bit-identical outputs (docs/methods/bilateral.md).
    fnames = list(frames[0])
    valid = jnp.ones((1, h, w), dt)
    nstack, fsizes = [], [frames[0][k].shape[-1] for k in fnames]
    for fr in frames:
        a = jnp.concatenate([*(jnp.moveaxis(fr[k].astype(dt), -1, 0) for k in fnames), valid], 0)
        nstack.append(jnp.pad(a, ((0, 0), (r, r + hc - h), (r, r + wc - w))))
    nstack = jnp.stack(nstack)  # (F, Cn, Hp, Wp)
    nf, cn = nstack.shape[0], nstack.shape[1]

    # Constant (P, N) geometry of a tile against its block.
    iy, ix = np.divmod(np.arange(p_n), t)
    jy, jx = np.divmod(np.arange(n_n), nw)
    dy = (jy[None, :] - r) - iy[:, None]
    dx = (jx[None, :] - r) - ix[:, None]
    d2 = jnp.asarray((dy * dy + dx * dx).astype(np.float64), dt)
    inwin = jnp.asarray(((np.abs(dy) <= r) & (np.abs(dx) <= r)).astype(np.float64), dt)

    ntile = nty * ntx
    # Tiles per group: GROUP_PAIRS pairs per frame (the frames are summed one after the other inside
    # a group), and at least 2: a group of one tile ran 5x slower on XLA's CPU backend (measured at
    # 96x240, r = 27, and for LBF's 7-frame filter at 128x128, 4.9 s against 0.88 s with 4 tiles).
    g = int(max(min(2, ntile), min(ntile, GROUP_PAIRS // (p_n * n_n))))
    ngroup = -(-ntile // g)
    ctiles = {k: jnp.pad(v, ((0, ngroup * g - ntile), (0, 0), (0, 0))).reshape(ngroup, g, p_n, v.shape[-1])
              for k, v in ctiles.items()}
    tids = jnp.arange(ngroup * g).reshape(ngroup, g)
    cv = fsizes[fnames.index(value)]

    def split(a, names, sizes):  # a stack with channels on axis 0 -> {name: its channels}
        out, o = {}, 0
        for k, n in zip(names, sizes):
            out[k] = a[o:o + n]
            o += n
        return out

    voff = sum(fsizes[:fnames.index(value)])

    def group(args):
        tid, cen = args
        ty = jnp.minimum(tid // ntx, nty - 1)  # padded tile ids (last group) read tile row nty - 1
        tx = tid % ntx
        ci = {k: jnp.moveaxis(v, -1, 0)[..., None] for k, v in cen.items()}  # (C, g, P, 1)
        num = jnp.zeros((g, p_n, cv), dt)
        den = jnp.zeros((g, p_n, 1), dt)
        for f in range(nf):
            blk = jax.vmap(lambda a, b: jax.lax.dynamic_slice(nstack[f], (0, a * t, b * t), (cn, nh, nw)))(ty, tx)
            blk = jnp.moveaxis(blk.reshape(g, cn, n_n), 1, 0)  # (Cn, g, N)
            nj = split(blk[:, :, None, :], fnames, fsizes)  # (C, g, 1, N)
            wgt = jnp.exp(log_weight(ci, nj, f, d2)) * inwin
            vj = blk[-1:]
            rhs = jnp.concatenate([blk[voff:voff + cv] * vj, vj], 0)  # (C_v + 1, g, N)
            s = jnp.einsum("gpn,cgn->gpc", wgt, rhs, precision=jax.lax.Precision.HIGHEST)
            num = num + s[..., :cv]
            den = den + s[..., cv:]
        return num, den

    num, den = jax.lax.map(jax.checkpoint(group), (tids, ctiles))

    def untile(a):
        c = a.shape[-1]
        a = a.reshape(ngroup * g, p_n, c)[:ntile].reshape(nty, ntx, t, t, c).transpose(0, 2, 1, 3, 4)
        return a.reshape(hc, wc, c)[:h, :w]

    return untile(num), untile(den)
