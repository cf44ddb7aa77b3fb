"""Exact pixels: where a Monte Carlo frame's estimate has no noise to remove (ours, issue 33; shared by
`demc` and `rae` since issue 34; docs/methods/demc.md "Exact pixels").

``exact_mask(color, color_var=None, spp=None, *, window=0) -> mask (..., H, W, 1)``
``check_exact_window(owner, window)`` (a network config's ``exact_window``)

On a pixel that sees an area light or a constant background directly, every sample returns the same
radiance: the input there is the reference, and a denoiser that keeps it cannot add bias. Two rules
say where:

- **The variance rule**: in a frame of ``spp`` >= 2 with ``color_var`` (the variance of the pixel's
  samples, the Buffers contract), a pixel whose variance is 0 in every channel: its samples all agreed.
- **The window rule** (``window`` > 0, an odd number >= 3): where the variance rule cannot apply (a
  frame of 1 spp, or one without ``color_var`` or ``spp``), a pixel whose ``window`` x ``window``
  square (the frame's border repeated outward) holds bit-for-bit its colour in every pixel:
  independent samples of a noisy estimate never agree so, a directly seen uniform emitter's interior
  or a constant background does. It can be wrong where a light's edge crosses a pixel and that pixel's
  one sample and all its neighbours' landed on the light.

Either way a kept pixel is lit (some channel above 0) and finite. ``spp`` is a number or one per frame
over the leading axes. A renderer that writes 0 for a variance it did not compute would have every lit
pixel kept: such a frame breaks the contract the cross filters rely on too. Not differentiable (a
mask); ``window`` is static.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._common import FilterError


def check_exact_window(owner: str, window: Any) -> None:
    """Refuse, naming ``owner`` (e.g. ``"demc: config.exact_window"``), a window that `exact_mask`
    cannot take: 0 (off) or an odd integer >= 3."""
    if not (isinstance(window, (int, np.integer)) and not isinstance(window, bool)
            and (window == 0 or window >= 3 and window % 2)):
        raise FilterError(f"{owner} must be 0 (off) or an odd number of pixels >= 3, got {window!r}")


def exact_mask(color, color_var=None, spp=None, *, window: int = 0) -> jax.Array:
    """The boolean mask ``(..., H, W, 1)`` of the pixels of ``color`` ``(..., H, W, C)`` whose estimate
    is exact by the variance rule (``color_var`` and ``spp`` >= 2) or, where that rule cannot apply, by
    the window rule (module docstring)."""
    check_exact_window("argument 'window'", window)
    c = jnp.asarray(color)
    if c.ndim < 3:
        raise FilterError(f"argument 'color' has shape {tuple(c.shape)}; expected (..., H, W, C)")
    lit = (jnp.max(c, axis=-1, keepdims=True) > 0) & jnp.all(jnp.isfinite(c), axis=-1, keepdims=True)
    many = exact = jnp.asarray(False)  # `many`: the variance rule applies
    if color_var is not None and spp is not None:
        var = jnp.asarray(color_var)
        if var.shape != c.shape:
            raise FilterError(f"argument 'color_var' has shape {tuple(var.shape)}; expected the colour's "
                              f"{tuple(c.shape)}")
        n = jnp.asarray(spp, jnp.float32)
        many = jnp.reshape(n, n.shape + (1,) * (c.ndim - n.ndim)) >= 2 if n.ndim else n >= 2
        exact = many & (jnp.max(var, axis=-1, keepdims=True) == 0)
    if window:
        h, w, r = c.shape[-3], c.shape[-2], window // 2
        p = jnp.pad(c, [(0, 0)] * (c.ndim - 3) + [(r, r), (r, r), (0, 0)], mode="edge")
        agree = jnp.ones(lit.shape, bool)
        for dy in range(window):
            for dx in range(window):
                agree = agree & jnp.all(p[..., dy:dy + h, dx:dx + w, :] == c, axis=-1, keepdims=True)
        exact = exact | (~many & agree)
    return exact & lit
