"""Spike removal: after a filter, Kalantari, Bako & Sen 2015 Sec. 4.3; before a network, an outlier clamp.

``remove_spikes(image, *, n_std=2.0, block_radius=1) -> image``

``clamp_outliers(color, factor, floor, *, against="neighbours", radius=1, reference=None, unfloored=None) -> color``
(ours,
`rae`'s input: docs/methods/rae.md "Outliers"): each pixel's Rec. 709 luminance limited to ``factor`` times the larger
of ``floor`` and the largest luminance among its 8 neighbours (neighbours outside the image count as 0),
the hue kept. With ``radius`` r > 1 the neighbours are the 8 r pixels at Chebyshev distance exactly r (the
border of the (2r + 1)-pixel square around it; `rae`'s output clamp, docs/methods/rae.md "Output
clamp"): a blob narrower than 2r - 1 pixels is cut, while a line, an edge or a corner, which crosses the
square's border, passes. With ``against="median"`` the reference is instead the median luminance of the pixel's 3 x 3
block (border repeated), which also cuts a cluster of up to 4 outlier pixels (`match_to_input`'s
target). With ``reference`` (an image of the colour's shape) the neighbourhood is read from its luminance
instead: `input_gain`'s ``output_cut`` limits a noisy input to a multiple of what a denoiser drew around it.
With ``unfloored`` (a boolean ``(..., H, W)`` mask, broadcastable to the image's) the marked pixels are limited
by their neighbourhood alone, ``floor`` left out (`rae`'s ``outlier_rel_sd``: a pixel whose own variance says it
rests on about one sample is cut below the floor too; a marked pixel whose neighbours are all black is cut to
black).
``factor`` is a static number, or one per image: an array broadcastable to the leading
axes (`match_to_input`'s factor by sample count; a traced array is not checked). A noisy input's
isolated spike (a firefly) far above both is cut; a light, a highlight or an edge (a
bright neighbour) and anything below ``factor * floor`` pass unchanged (``factor`` 0: every lit pixel
is cut to black). Unlike the filters' ``(H, W, C)`` convention it takes any leading axes (training
batches of sequences), and ``C`` must be 3.

After filtering, a pixel is a spike when any of its colour channels lies more than ``n_std``
standard deviations from the mean of its ``3 x 3`` block (``block_radius=1``); a spike is replaced
by the per-channel median of the block, every other pixel is returned unchanged.

Choices the paper leaves open (docs/methods/bilateral.md): the block statistics include the centre
pixel (population standard deviation over the 9 values); at the border the block is completed by
edge replication, so every block has 9 values and a well-defined median.

Gradients: the spike test is a comparison, so no gradient flows through the mean and standard
deviation (which also keeps the ``sqrt`` at variance 0 out of the backward pass); the output is the
input or the block median, both differentiable almost everywhere with respect to the image. The
paper notes the step is not differentiable in its parameters: ``n_std`` is a threshold, so its
derivative is 0 almost everywhere and it is not a training parameter.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import compute_dtype, edge_blocks, is_concrete, median9
from ..color import luminance
from ._common import FilterError, as_image, check_radius


def remove_spikes(image, *, n_std: float = 2.0, block_radius: int = 1) -> jax.Array:
    """Replace block outliers by the block median (Sec. 4.3; module docstring)."""
    img = as_image(image, "image")
    block_radius = check_radius(block_radius, "block_radius")
    if not is_concrete(n_std) or not np.isfinite(n_std) or float(n_std) < 0:
        raise FilterError(f"argument 'n_std' is {n_std!r}; expected a static finite number >= 0")
    out_dtype = img.dtype if jnp.issubdtype(img.dtype, jnp.floating) else jnp.float32
    x = img.astype(compute_dtype(img))
    block = edge_blocks(x, block_radius)  # (H, W, C, (2r+1)^2)
    stats = jax.lax.stop_gradient(block)
    mean = jnp.mean(stats, axis=-1)
    std = jnp.sqrt(jnp.mean((stats - mean[..., None]) ** 2, axis=-1))
    spike = jnp.any(jnp.abs(jax.lax.stop_gradient(x) - mean) > float(n_std) * std, axis=-1, keepdims=True)
    # The median by a sorting network (equal to jnp.median, which sorts and runs ~10x slower on CPU).
    med = median9(jnp.moveaxis(block, -1, 0)) if block.shape[-1] == 9 else jnp.median(block, axis=-1)
    return jnp.where(spike, med, x).astype(out_dtype)


def clamp_outliers(color, factor: float, floor: float, *, against: str = "neighbours",
                   radius: int = 1, reference=None, unfloored=None) -> jax.Array:
    """``(..., H, W, 3)`` colour with isolated luminance spikes cut (module docstring); with ``reference`` (an
    image of ``color``'s shape) the neighbourhood's luminance is read from it instead of from ``color``."""
    shape = tuple(np.shape(color))
    if len(shape) < 3 or shape[-1] != 3:
        raise FilterError(f"argument 'color' has shape {shape}; expected (..., H, W, 3)")
    as_image(jnp.reshape(color, (-1,) + shape[-2:]), "color")  # sizes and (concrete) NaN/Inf checked by name
    if reference is not None:
        if tuple(np.shape(reference)) != shape:
            raise FilterError(f"argument 'reference' has shape {tuple(np.shape(reference))}; expected the colour's "
                              f"{shape}")
        as_image(jnp.reshape(reference, (-1,) + shape[-2:]), "reference")
    c = jnp.asarray(color)
    if not is_concrete(floor) or np.ndim(floor) or not np.isfinite(floor) or float(floor) < 1e-30:
        raise FilterError(f"argument 'floor' is {floor!r}; expected a static finite number > 0")
    if against not in ("neighbours", "median"):
        raise FilterError(f"argument 'against' is {against!r}; expected 'neighbours' or 'median'")
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 1:
        raise FilterError(f"argument 'radius' is {radius!r}; expected an int >= 1")
    if radius > 1 and against != "neighbours":
        raise FilterError(f"argument 'radius' is {radius!r} with against={against!r}; a radius above 1 goes "
                          "with against='neighbours'")
    lum = luminance(c)
    lead, (h, w) = lum.shape[:-2], lum.shape[-2:]
    factor = _factor(factor, lead)
    src = lum if reference is None else luminance(jnp.asarray(reference))
    if against == "median":  # the 3 x 3 block's median, border repeated: a cluster of <= 4 pixels is cut too
        near = median9(edge_blocks(src[..., None], 1, axis=0))[..., 0]
    else:
        near = _ring_max(src, int(radius))
    limit = jnp.maximum(near, float(floor))
    if unfloored is not None:
        mask = jnp.asarray(unfloored)
        try:
            np.broadcast_shapes(mask.shape, lum.shape)
        except ValueError:
            raise FilterError(f"argument 'unfloored' has shape {mask.shape}; expected a mask broadcastable to the "
                              f"image's (..., H, W) = {lum.shape}") from None
        if mask.dtype != bool:
            raise FilterError(f"argument 'unfloored' has dtype {mask.dtype}; expected bool")
        limit = jnp.where(mask, near, limit)
    limit = factor * limit
    cut = lum > limit  # then lum > 0: the inner where keeps the unused branch's gradient finite at lum = 0
    return c * jnp.where(cut, limit / jnp.where(cut, lum, 1.0), 1.0)[..., None]


def _ring_max(lum: jax.Array, r: int) -> jax.Array:
    """``(..., H, W)`` -> the largest value at Chebyshev distance exactly ``r`` from each pixel (0 outside
    the image): the square border's top and bottom rows (a running maximum of 2r + 1 along W) and its
    left and right columns without their corners (a running maximum of 2r - 1 along H)."""
    h, w = lum.shape[-2:]
    nd = lum.ndim
    pad = jnp.pad(lum, [(0, 0)] * (nd - 2) + [(r, r), (r, r)])
    rows = jax.lax.reduce_window(pad, -jnp.inf, jax.lax.max, (1,) * (nd - 1) + (2 * r + 1,), (1,) * nd, "VALID")
    cols = jax.lax.reduce_window(pad, -jnp.inf, jax.lax.max, (1,) * (nd - 2) + (2 * r - 1, 1), (1,) * nd, "VALID")
    return jnp.maximum(jnp.maximum(rows[..., :h, :], rows[..., 2 * r:2 * r + h, :]),
                       jnp.maximum(cols[..., 1:1 + h, :w], cols[..., 1:1 + h, 2 * r:2 * r + w]))


def _factor(factor, lead: tuple[int, ...]):
    """`clamp_outliers`' ``factor``: a static number >= 0 as a float, or one per image (an array
    broadcastable to the leading axes ``lead``) as ``(..., 1, 1)``; a traced array is not checked."""
    if np.ndim(factor) == 0 and is_concrete(factor):
        if not np.isfinite(factor) or float(factor) < 0:
            raise FilterError(f"argument 'factor' is {factor!r}; expected a finite number >= 0")
        return float(factor)
    shape = tuple(np.shape(factor))
    try:
        np.broadcast_shapes(shape, lead)
    except ValueError:
        raise FilterError(f"argument 'factor' has shape {shape}; expected a number or one per image, "
                          f"broadcastable to the leading axes {lead}") from None
    if len(shape) > len(lead):
        raise FilterError(f"argument 'factor' has shape {shape}; expected at most the leading axes {lead}")
    if is_concrete(factor):
        v = np.asarray(factor, np.float64)
        if not np.all(np.isfinite(v) & (v >= 0)):
            raise FilterError(f"argument 'factor' holds {v[~(np.isfinite(v) & (v >= 0))][:3].tolist()}; "
                              "expected finite numbers >= 0")
    return jnp.asarray(factor, jnp.float32)[..., None, None]
