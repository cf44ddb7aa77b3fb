"""Pure first-order optimizers over pytrees (no optax): Adam and RPROP.

Each constructor returns an ``(init, update)`` pair:

- ``init(params) -> state``
- ``update(grads, state, params) -> (new_params, new_state)``

Both functions are pure and jittable; ``state`` is a plain pytree (tuples / dicts of arrays), so it
can be checkpointed with `jaxdenoise.checkpoint` next to the parameters.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple, Union

import jax
import jax.numpy as jnp
import numpy as np
from ..errors import JaxdenoiseError

__all__ = ["adam", "rprop", "AdamState", "RpropState", "schedule", "SCHEDULES", "clip_by_global_norm"]

Schedule = Union[float, Callable[[Any], Any]]


def _check_positive(fn: str, **values):
    for name, v in values.items():
        if callable(v):
            continue
        if not (np.ndim(v) == 0 and np.isfinite(float(v)) and float(v) > 0):
            raise JaxdenoiseError(f"{fn}: argument '{name}' is {v!r}; expected a finite scalar > 0")


class AdamState(NamedTuple):
    count: Any   # int32 scalar, number of updates done
    mu: Any      # first-moment estimate, same pytree as params
    nu: Any      # second-moment estimate


def adam(lr: Schedule, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8):
    """Adam (Kingma & Ba, ICLR 2015, Algorithm 1), with bias correction.

    ``lr`` is a scalar or a schedule ``lr(count) -> scalar`` (``count`` = updates done before this
    one). ``eps`` is added to ``sqrt(v_hat)`` (as in Algorithm 1): it bounds the step where the
    second moment vanishes (a parameter with zero gradient so far), which would otherwise be 0/0.
    """
    _check_positive("adam", lr=lr, eps=eps)
    for name, b in (("b1", b1), ("b2", b2)):
        if not 0 <= b < 1:
            raise JaxdenoiseError(f"adam: argument '{name}' is {b}; expected 0 <= {name} < 1")

    def init(params):
        zeros = jax.tree_util.tree_map(jnp.zeros_like, params)
        return AdamState(jnp.zeros((), jnp.int32), zeros, jax.tree_util.tree_map(jnp.zeros_like, params))

    def update(grads, state, params):
        count = state.count + 1
        mu = jax.tree_util.tree_map(lambda m, g: b1 * m + (1 - b1) * g, state.mu, grads)
        nu = jax.tree_util.tree_map(lambda v, g: b2 * v + (1 - b2) * g * g, state.nu, grads)
        t = count.astype(jnp.float32)
        c1 = 1 - b1 ** t
        c2 = 1 - b2 ** t
        step = lr(state.count) if callable(lr) else lr

        def move(p, m, v):
            m_hat = m / c1.astype(m.dtype)
            v_hat = v / c2.astype(v.dtype)
            return (p - step * m_hat / (jnp.sqrt(v_hat) + eps)).astype(p.dtype)

        new_params = jax.tree_util.tree_map(move, params, mu, nu)
        return new_params, AdamState(count, mu, nu)

    return init, update


class RpropState(NamedTuple):
    step: Any        # per-weight step size Delta, same pytree as params
    prev_grad: Any   # gradient of the previous iteration (zeroed after a sign change)
    prev_delta: Any  # previous weight change (used by 'rprop+' backtracking)


_VARIANTS = ("irprop-", "rprop+")


def rprop(step_init: float = 0.1, *, eta_plus: float = 1.2, eta_minus: float = 0.5,
          step_min: float = 1e-6, step_max: float = 50.0, variant: str = "irprop-"):
    """Resilient backpropagation (Riedmiller & Braun 1993), as Kalantari et al. 2015 Sec. 4.2 train
    the LBF network: each weight moves by its own step size ``Delta`` against the sign of its
    gradient; ``Delta`` grows by ``eta_plus`` while the gradient sign is stable and shrinks by
    ``eta_minus`` when it flips, clipped to ``[step_min, step_max]``. Defaults are the paper's
    (Delta_0 = 0.1, eta+ = 1.2, eta- = 0.5, Delta_max = 50, Delta_min = 1e-6).

    ``variant``:

    - ``'irprop-'`` (default; Igel & Huesken 2000): after a sign flip the gradient is set to zero, so
      that weight does not move this iteration and the step is not shrunk twice. No backtracking,
      which makes it robust on mini-batch gradients (Kalantari averages mini-batch gradients, Sec. 4.2).
    - ``'rprop+'``: the original 1993 rule with weight backtracking (a flip undoes the previous change).
    """
    _check_positive("rprop", step_init=step_init, eta_plus=eta_plus, eta_minus=eta_minus,
                    step_min=step_min, step_max=step_max)
    if variant not in _VARIANTS:
        raise JaxdenoiseError(f"rprop: argument 'variant' is {variant!r}; expected one of {_VARIANTS}")
    if not eta_minus < 1 < eta_plus:
        raise JaxdenoiseError(f"rprop: expected eta_minus < 1 < eta_plus, got {eta_minus}, {eta_plus}")
    if not step_min <= step_init <= step_max:
        raise JaxdenoiseError(f"rprop: expected step_min <= step_init <= step_max, got {step_min}, {step_init}, {step_max}")

    def init(params):
        return RpropState(
            jax.tree_util.tree_map(lambda p: jnp.full_like(p, step_init), params),
            jax.tree_util.tree_map(jnp.zeros_like, params),
            jax.tree_util.tree_map(jnp.zeros_like, params))

    def one(g, p, delta, g_prev, dw_prev):
        s = g * g_prev
        delta = jnp.where(s > 0, jnp.minimum(delta * eta_plus, step_max),
                          jnp.where(s < 0, jnp.maximum(delta * eta_minus, step_min), delta))
        if variant == "irprop-":
            g = jnp.where(s < 0, 0, g)
            dw = -jnp.sign(g) * delta
        else:  # rprop+: on a flip, take back the previous change and forget the gradient
            dw = jnp.where(s < 0, -dw_prev, -jnp.sign(g) * delta)
            g = jnp.where(s < 0, 0, g)
        return (p + dw).astype(p.dtype), delta, g, dw

    def update(grads, state, params):
        out = jax.tree_util.tree_map(one, grads, params, state.step, state.prev_grad, state.prev_delta)
        leaves_def = jax.tree_util.tree_structure(params)
        flat = leaves_def.flatten_up_to(out)
        new_params, delta, g, dw = (leaves_def.unflatten([f[i] for f in flat]) for i in range(4))
        return new_params, RpropState(delta, g, dw)

    return init, update


# -- learning-rate schedules (in steps) ------------------------------------------------------------
SCHEDULES = ("constant", "rampup_rsqrt", "step", "exponential")


def schedule(name: str, lr: float, *, every: int = 1, factor: float = 1.0) -> Callable[[Any], Any]:
    """A learning rate as a pure function of the update count ``t`` (0 for the first update):

    - ``"constant"``: ``lr``;
    - ``"rampup_rsqrt"``: Chaitanya et al. 2017 Sec. 5.3: a geometric ramp-up by ``factor`` (their
      tenfold) over the first ``every`` steps, ``lr * factor ** (t / every - 1)``, then a decay as
      ``lr * sqrt(every / t)`` (their 1/sqrt(t) in epochs, restated in steps);
    - ``"step"``: ``lr * factor ** floor(t / every)`` (Guo et al. 2019 Sec. 5.1: 0.95 every other
      epoch);
    - ``"exponential"``: ``lr * factor ** (t / every)``.
    """
    if name not in SCHEDULES:
        raise JaxdenoiseError(f"schedule: unknown name {name!r}; expected one of {SCHEDULES}")
    _check_positive("schedule", lr=lr, factor=factor)
    if not (isinstance(every, (int, np.integer)) and every >= 1):
        raise JaxdenoiseError(f"schedule: argument 'every' is {every!r}; expected an int >= 1")
    lr, factor, every = float(lr), float(factor), int(every)

    def fn(t):
        t = jnp.asarray(t, jnp.float32)
        if name == "constant":
            return jnp.full_like(t, lr)
        if name == "step":
            return lr * factor ** jnp.floor(t / every)
        if name == "exponential":
            return lr * factor ** (t / every)
        ramp = lr * factor ** (t / every - 1.0)
        return jnp.where(t < every, ramp, lr * jnp.sqrt(every / jnp.maximum(t, 1.0)))

    return fn


def clip_by_global_norm(grads: Any, max_norm: float) -> tuple[Any, Any]:
    """Scale ``grads`` so that their global L2 norm is at most ``max_norm``; returns ``(grads, norm
    before clipping)``. A zero gradient stays zero (the scale is guarded where the norm is 0)."""
    leaves = jax.tree_util.tree_leaves(grads)
    norm = jnp.sqrt(sum(jnp.sum(jnp.square(g.astype(jnp.float32))) for g in leaves)) if leaves else jnp.zeros(())
    scale = jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-30))
    return jax.tree_util.tree_map(lambda g: (g * scale).astype(g.dtype), grads), norm

