"""Array helpers shared by filters and solvers: concreteness test for eager validation, the floating
compute dtype (private to jaxdenoise; `filters` and `solvers` are peers, so neither owns these)."""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


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
