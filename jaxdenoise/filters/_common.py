"""Shared argument checks for the filters (private).

Every filter takes HWC float images and parameters that are either scalars or per-pixel ``(H, W)``
maps. Checks run on shapes (always static under ``jit``) and, when the values are concrete (not
traced), on finiteness: a NaN/Inf input raises a `FilterError` naming the argument instead of
spreading silently through the window sums.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..arrays import is_concrete
from ..errors import JaxdenoiseError


class FilterError(JaxdenoiseError):
    """A filter was called with an argument of the wrong shape, dtype or value."""


def as_image(x: Any, name: str, *, hw: tuple[int, int] | None = None, channels: int | None = None) -> jax.Array:
    """Validate an ``(H, W, C)`` image (``hw``/``channels`` pin its size) and return it as an array."""
    if x is None:
        raise FilterError(f"argument '{name}' is None; expected an (H, W, C) array")
    shape = tuple(np.shape(x))
    if len(shape) != 3:
        raise FilterError(f"argument '{name}' has shape {shape}; expected (H, W, C)")
    if 0 in shape:
        raise FilterError(f"argument '{name}' has shape {shape}; every dimension must be >= 1")
    if hw is not None and shape[:2] != tuple(hw):
        raise FilterError(f"argument '{name}' has pixel grid {shape[:2]}; expected {tuple(hw)} like the image")
    if channels is not None and shape[2] != channels:
        raise FilterError(f"argument '{name}' has {shape[2]} channel(s); expected {channels}")
    require_finite(x, name)
    return jnp.asarray(x)


def as_param(x: Any, name: str, hw: tuple[int, int], *, nonneg: bool = True) -> jax.Array:
    """Validate a filter parameter: a scalar or a per-pixel ``(H, W)`` map (``(H, W, 1)`` is accepted).

    Returns an array broadcastable against ``(H, W, 1)``: shape ``()`` or ``(H, W, 1)``.
    """
    if x is None:
        raise FilterError(f"argument '{name}' is None; expected a scalar or an {hw} array")
    shape = tuple(np.shape(x))
    if shape not in ((), tuple(hw), tuple(hw) + (1,)):
        raise FilterError(f"argument '{name}' has shape {shape}; expected a scalar, {tuple(hw)} or {tuple(hw) + (1,)}")
    require_finite(x, name)
    if nonneg and is_concrete(x) and np.any(np.asarray(x) < 0):
        raise FilterError(f"argument '{name}' has negative values (min {float(np.min(np.asarray(x)))}); "
                          "bandwidth parameters must be >= 0")
    x = jnp.asarray(x)
    return x if x.ndim == 0 else x.reshape(hw + (1,))


def check_radius(radius: Any, name: str = "radius") -> int:
    if isinstance(radius, (bool, np.bool_)) or not isinstance(radius, (int, np.integer)):
        raise FilterError(f"argument '{name}' is {radius!r}; expected a non-negative Python int (static under jit)")
    if radius < 0:
        raise FilterError(f"argument '{name}' is {radius}; expected >= 0")
    return int(radius)


def require_finite(x: Any, name: str) -> None:
    """Raise a `FilterError` naming ``name`` if ``x`` is concrete and holds a NaN/Inf (traced: nothing)."""
    if not is_concrete(x):
        return
    a = np.asarray(x)
    if a.dtype.kind not in "fc":
        if a.dtype.kind not in "iub":
            raise FilterError(f"argument '{name}' has dtype {a.dtype}; expected a float array")
        return
    bad = int(a.size - np.count_nonzero(np.isfinite(a)))
    if bad:
        raise FilterError(f"argument '{name}' has {bad} NaN/Inf value(s); filters need finite input "
                          "(read EXRs with repair=... to fix them)")
