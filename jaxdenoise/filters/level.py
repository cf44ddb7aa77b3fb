"""Level matching: an image given the large-scale level of another (ours, issue 33; docs/methods/demc.md
"Colour level at inference").

``match_level(image, target, sigma, eps, *, max_gain=inf) -> image``
``match_to_input(output, color, sigma, *, spike, floor, max_gain=inf, spp=None, output_cut=False) -> image``
``level_gain(image, target, sigma, eps, *, max_gain=inf)``, ``input_gain(output, color, sigma, ...)``: the
gains the two multiply by (a caller may average them over frames: `rae`'s ``match_frames``)
``check_match_settings(owner, sigma, spike, max_gain, by_rate)`` (a network config's settings for it)

Each channel of ``image`` times the gain ``(G(target) + eps) / (G(image) + eps)``, limited to
``[1 / max_gain, max_gain]``, where ``G`` is `gaussian` of ``sigma`` pixels (border renormalised) and
negative low-pass values count as 0. Where ``target``
is an unbiased estimate of what ``image`` should be (a Monte Carlo input: noisy, but right on
average), the product keeps the image's detail and puts its level, averaged over a few ``sigma``, at
the target's: a denoiser's large-scale darkening or tint is undone without the input's noise, which
the wide low-pass averages away. ``eps`` (> 0, in the image's units) keeps the gain finite and near 1
where both low-passes are dark; the gain is at most ``(max G(target) + eps) / eps``. Where the image
misses something concentrated that the target has (a small light drawn dark), the gain spreads it
over the low-pass's reach as a halo: ``max_gain`` bounds what that can add.

`match_to_input` is how a denoiser uses it (`demc`, `rae`): ``target`` is its noisy input ``color``
with outliers cut, each pixel's Rec. 709 luminance limited to ``spike`` times the larger of ``floor``
and the median luminance of its 3 x 3 block (border repeated), hue kept: a firefly the network
rightly removed would otherwise count as level it lacks (`clamp_outliers` with ``against="median"``).
The median, unlike the brightest neighbour (`clamp_outliers`'s default), also cuts a cluster of up to
4 outlier pixels, which a network may draw too bright itself: cut by the neighbour maximum, such a
cluster lifts the target's low-pass and the gain brightens the network's blob further
(docs/methods/rae.md "Colour level at inference"). ``eps`` is 1 % of ``floor`` (the level the caller's
exposure scaling brings a frame to).

With ``output_cut`` the target is cut once more, each pixel's luminance limited to the same factor times the
larger of ``floor`` and the output's brightest luminance among its 8 neighbours (`clamp_outliers` with
``reference=output``; ours, docs/methods/rae.md "Colour level at inference"): light the output has nowhere near
counts at most that much. A small light a network drew dark (its pixels not kept as exact: a wide pixel
filter mixes its edge samples) otherwise lifts the target's low-pass around it and the gain brightens its
whole neighbourhood, up to ``max_gain``.

With ``spp`` (the frame's samples per pixel: a number, or one per frame over the leading axes) the
cut scales with the noise: ``spike`` is then a single sample's factor and a pixel of ``n`` samples is
cut at ``1 + (spike - 1) / sqrt(n)`` times its median (ours, docs/methods/demc.md "Colour level at
inference"). A fixed factor tuned on denser frames cuts ordinary 1-spp noise, whose spread about the
median is ``sqrt(n)`` times wider, and leaves the target dark; scaled, the cut removes the same
share of a pixel's spread at every rate. ``spike`` must then be at least 1.

Homogeneous of degree 1 in ``(image, target, eps)`` together; ``sigma`` 0 gives ``image * (target +
eps) / (image + eps)``. Shapes: ``(..., H, W, C)`` with any leading axes (frames of a batch are
matched one by one), ``image`` and ``target`` alike. Computed in float32 at least (half precision
is cast back, an integer image comes back as float32). Unlike the filters' common conventions
(`jaxdenoise.filters`), ``sigma``, ``eps`` and ``max_gain`` are static scalars, not per-pixel maps,
and not differentiable.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import compute_dtype, is_concrete
from ._common import FilterError, as_image
from .gaussian import gaussian
from .spikes import clamp_outliers


def match_level(image, target, sigma: float, eps: float, *, max_gain: float = float("inf")) -> jax.Array:
    """``image`` times ``(G(target) + eps) / (G(image) + eps)`` per channel, within ``[1 / max_gain,
    max_gain]`` (module docstring)."""
    return _times(image, level_gain(image, target, sigma, eps, max_gain=max_gain))


def _times(image, gain: jax.Array) -> jax.Array:
    """``image`` times ``gain`` computed in the gain's precision, returned in the image's floating type
    (float32 for an integer image)."""
    image = jnp.asarray(image)
    out_dtype = image.dtype if jnp.issubdtype(image.dtype, jnp.floating) else jnp.float32
    return (image.astype(gain.dtype) * gain).astype(out_dtype)


def level_gain(image, target, sigma: float, eps: float, *, max_gain: float = float("inf")) -> jax.Array:
    """The per-channel gain `match_level` multiplies ``image`` by, ``(..., H, W, C)`` in float32 at least:
    a caller may average it over frames before applying it (`rae`'s ``match_frames``)."""
    shape = tuple(np.shape(image))
    if len(shape) < 3:
        raise FilterError(f"argument 'image' has shape {shape}; expected (..., H, W, C)")
    if tuple(np.shape(target)) != shape:
        raise FilterError(f"argument 'target' has shape {tuple(np.shape(target))}; expected the image's {shape}")
    for name, v, ok, want in (("sigma", sigma, lambda x: 0 <= x < np.inf, "a finite number >= 0"),
                              ("eps", eps, lambda x: 0 < x < np.inf, "a finite number > 0"),
                              ("max_gain", max_gain, lambda x: x >= 1, "a number >= 1 (inf: no limit)")):
        if not is_concrete(v) or np.ndim(v) or not ok(float(v)):
            raise FilterError(f"argument '{name}' is {v!r}; expected a static {want}")
    for name, a in (("image", image), ("target", target)):  # sizes, (concrete) NaN/Inf checked by name
        as_image(jnp.reshape(a, (-1,) + shape[-2:]), name)
    image, target = jnp.asarray(image), jnp.asarray(target)
    dt = compute_dtype(image, target)
    flat = (-1,) + shape[-3:]
    xs, ts = jnp.reshape(image, flat).astype(dt), jnp.reshape(target, flat).astype(dt)
    low = jax.vmap(lambda a: jnp.maximum(gaussian(a, float(sigma)), 0.0))
    gain = jnp.clip((low(ts) + float(eps)) / (low(xs) + float(eps)), 1.0 / float(max_gain), float(max_gain))
    return jnp.reshape(gain, shape)


def check_match_settings(owner: str, sigma: float, spike: float, max_gain: float, by_rate: bool) -> None:
    """Refuse, naming ``owner`` (e.g. ``"demc: config."``), a network's level-match settings that
    `match_to_input` cannot take: ``match_level`` (sigma) finite and >= 0, ``match_spike`` finite and
    > 0 (>= 1 with ``match_spike_by_rate``), ``match_max_gain`` finite and >= 1 or 0 (no limit)."""
    finite = all(np.isfinite(v) for v in (sigma, spike, max_gain))
    if not (finite and sigma >= 0 and (spike >= 1 if by_rate else spike > 0) and (max_gain >= 1 or max_gain == 0)):
        raise FilterError(f"{owner}match_level must be finite and >= 0, match_spike finite and > 0 (>= 1 with "
                          f"match_spike_by_rate), match_max_gain finite and >= 1 (0: no limit), got {sigma}, "
                          f"{spike}, {max_gain}")


def match_to_input(output, color, sigma: float, *, spike: float, floor: float,
                   max_gain: float = float("inf"), spp=None, output_cut: bool = False) -> jax.Array:
    """`match_level` of a denoiser's ``output`` against its noisy input ``color`` (``(..., H, W, 3)``)
    with outliers cut at ``spike`` times the larger of ``floor`` and their 3 x 3 median luminance
    (with ``spp``: ``1 + (spike - 1) / sqrt(spp)`` times), ``eps`` 1 % of ``floor`` (module docstring)."""
    return _times(output, input_gain(output, color, sigma, spike=spike, floor=floor, max_gain=max_gain, spp=spp,
                                     output_cut=output_cut))


def input_gain(output, color, sigma: float, *, spike: float, floor: float,
               max_gain: float = float("inf"), spp=None, output_cut: bool = False) -> jax.Array:
    """The gain `match_to_input` multiplies ``output`` by (`level_gain` against the outlier-cut input). With
    ``output_cut`` the target is cut a second time, at the same factor times the larger of ``floor`` and the
    output's largest luminance among the pixel's 8 neighbours (module docstring)."""
    for name, v in (("spike", spike), ("floor", floor)):
        if not is_concrete(v) or np.ndim(v) or not 0 < float(v) < np.inf:
            raise FilterError(f"argument '{name}' is {v!r}; expected a static finite number > 0")
    factor = float(spike)
    if spp is not None:
        if factor < 1:
            raise FilterError(f"argument 'spike' is {spike!r}; with 'spp' expected a single sample's factor >= 1")
        if is_concrete(spp) and not np.all(np.asarray(spp, np.float64) >= 1):
            raise FilterError(f"argument 'spp' is {spp!r}; expected samples per pixel >= 1")
        factor = 1.0 + (factor - 1.0) / jnp.sqrt(jnp.maximum(jnp.asarray(spp, jnp.float32), 1.0))
    target = clamp_outliers(color, factor, floor, against="median")
    if output_cut:
        target = clamp_outliers(target, factor, floor, reference=output)
    return level_gain(output, target, sigma, 0.01 * float(floor), max_gain=max_gain)
