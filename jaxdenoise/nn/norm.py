"""Batch normalization (Ioffe & Szegedy 2015) as a pure stateful layer (`jaxdenoise.nn.state`):
DEMC's fusion sub-network uses it in its two middle blocks (Yang 2019 Sec. 3.2)."""
from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp

from .state import mark

__all__ = ["BatchNorm"]


def BatchNorm(momentum: float = 0.9, eps: float = 1e-5):
    """Per-channel normalization over every other axis (batch, time, height, width).

    Params ``{"scale", "bias", "mean", "var"}`` (C each; the last two are the running statistics).
    Training mode normalizes with the batch mean and (biased) variance and returns the running
    statistics ``momentum * old + (1 - momentum) * batch`` (the unbiased variance, n / (n - 1), as
    the usual convention for inference); inference mode uses the running statistics. ``eps`` keeps
    the division finite for a constant channel."""
    if not 0.0 <= float(momentum) < 1.0:
        raise ValueError(f"BatchNorm: momentum must be in [0, 1), got {momentum}")
    if not float(eps) > 0:
        raise ValueError(f"BatchNorm: eps must be > 0, got {eps}")
    m, eps = float(momentum), float(eps)

    def init(key, in_shape: Sequence[int]):
        c = int(in_shape[-1])
        return tuple(in_shape), {"scale": jnp.ones((c,), jnp.float32), "bias": jnp.zeros((c,), jnp.float32),
                                 "mean": jnp.zeros((c,), jnp.float32), "var": jnp.ones((c,), jnp.float32)}

    def apply(params, x, train: bool = False):
        axes = tuple(range(x.ndim - 1))
        if train:
            mu = jnp.mean(x, axis=axes)
            var = jnp.mean(jnp.square(x - mu), axis=axes)
        else:
            mu, var = params["mean"].astype(x.dtype), params["var"].astype(x.dtype)
        y = (x - mu) * jax.lax.rsqrt(var + eps) * params["scale"].astype(x.dtype) + params["bias"].astype(x.dtype)
        if not train:
            return y
        n = max(1, x.size // x.shape[-1])
        unbiased = var * (n / max(n - 1, 1))
        sg = jax.lax.stop_gradient
        return y, {"mean": m * params["mean"] + (1 - m) * sg(mu).astype(params["mean"].dtype),
                   "var": m * params["var"] + (1 - m) * sg(unbiased).astype(params["var"].dtype)}

    return init, mark(apply, True)
