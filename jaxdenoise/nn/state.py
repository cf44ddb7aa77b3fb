"""Layers with running statistics (BatchNorm), kept pure: the statistics are ordinary leaves of the
params pytree, and the mode is an explicit argument.

A *stateful* layer's ``apply`` takes ``train`` as a keyword and is marked ``apply.stateful = True``:

- ``apply(params, x, train=False) -> y`` uses the stored statistics (inference);
- ``apply(params, x, train=True) -> (y, updates)`` normalizes with the batch's statistics and returns
  the new running statistics as ``updates``, a pytree with the same keys as the part of ``params``
  they replace.

Combinators (`serial`, `parallel`, `residual`, `UNet`) are stateful when a child is, pass ``train``
down, and gather their children's updates under the children's params keys. A method's ``loss``
returns ``(value, {"updates": ...})``; the trainer merges the updates into the params after the
optimizer step (`merge_updates`), so the statistics are never moved by the gradient (which is zero
for them in training mode: they are not used there).
"""
from __future__ import annotations

from typing import Any, Callable

__all__ = ["is_stateful", "mark", "call", "merge_updates"]


def is_stateful(apply: Callable) -> bool:
    return bool(getattr(apply, "stateful", False))


def mark(apply: Callable, stateful: bool) -> Callable:
    """Mark ``apply`` as stateful (or not) and return it."""
    apply.stateful = bool(stateful)
    return apply


def call(apply: Callable, params: Any, x: Any, train: bool, updates: dict, key: str) -> Any:
    """Run one child layer; in training mode a stateful child's updates go into ``updates[key]``."""
    if not is_stateful(apply):
        return apply(params, x)
    if not train:
        return apply(params, x, train=False)
    y, u = apply(params, x, train=True)
    if u:
        updates[key] = u
    return y


def merge_updates(params: Any, updates: Any, path: str = "params") -> Any:
    """``params`` with the leaves named in the nested dict ``updates`` replaced (same shapes)."""
    if not isinstance(updates, dict):
        if getattr(params, "shape", None) != getattr(updates, "shape", None):
            raise ValueError(f"{path}: update has shape {getattr(updates, 'shape', None)}; the param has "
                             f"{getattr(params, 'shape', None)}")
        return updates
    if not isinstance(params, dict):
        raise ValueError(f"{path}: updates are a dict but the params are a {type(params).__name__}")
    unknown = sorted(set(updates) - set(params))
    if unknown:
        raise ValueError(f"{path}: updates for unknown entries {unknown}")
    return {k: (merge_updates(v, updates[k], f"{path}/{k}") if k in updates else v) for k, v in params.items()}
