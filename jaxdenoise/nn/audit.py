"""Structural checks of a training step's jaxpr: the two patterns that make training slow on CPU
with jax 0.10 (measured, docs/results/conv.md and the convolutional-networks issue):

- back-propagating through convolutions inside a **rolled** ``lax.scan`` (about 25x slower than the
  same loop unrolled: recurrent training must use ``unroll=True`` or a Python loop over frames);
- the gradient of max pooling through ``reduce_window`` / ``select_and_scatter`` (4.5x slower than
  `jaxdenoise.nn.MaxPool`'s reshape-and-max).

`slow_patterns(fn, *args)` traces ``fn`` (e.g. ``jax.grad(loss)``) and names every occurrence, so a
test keeps them out by structure rather than by timing.
"""
from __future__ import annotations

from typing import Any, Callable

import jax

__all__ = ["slow_patterns"]

_POOL_PRIMS = ("reduce_window", "reduce_window_max", "select_and_scatter", "select_and_scatter_add",
               "select_and_gather_add")


def _subjaxprs(eqn) -> list:
    out = []
    for v in eqn.params.values():
        for item in (v if isinstance(v, (list, tuple)) else [v]):
            j = getattr(item, "jaxpr", item)
            if hasattr(j, "eqns"):
                out.append(j)
    return out


def _has_conv(jaxpr) -> bool:
    for e in jaxpr.eqns:
        if e.primitive.name == "conv_general_dilated" or any(_has_conv(j) for j in _subjaxprs(e)):
            return True
    return False


def _walk(jaxpr, found: list[str], where: str) -> None:
    for e in jaxpr.eqns:
        name = e.primitive.name
        if name in _POOL_PRIMS:
            found.append(f"{where}{name} (max-pool gradient through reduce_window: use nn.MaxPool)")
        if name in ("scan", "while"):
            length, unroll = e.params.get("length"), e.params.get("unroll", 1)
            rolled = name == "while" or not (unroll is True or (length is not None and int(unroll) >= int(length)))
            if rolled and any(_has_conv(j) for j in _subjaxprs(e)):
                found.append(f"{where}{name} over convolutions, length {length}, unroll {unroll} "
                             "(rolled: unroll it, unroll=True)")
        for j in _subjaxprs(e):
            _walk(j, found, f"{where}{name}/")


def slow_patterns(fn: Callable, *args: Any) -> list[str]:
    """The slow patterns (module docstring) in the jaxpr of ``fn(*args)``; empty when there is none."""
    found: list[str] = []
    _walk(jax.make_jaxpr(fn)(*args).jaxpr, found, "")
    return found
