"""Stax-style layers over plain-pytree parameters (docs/architecture.md "Methods").

Every constructor returns a pair ``(init, apply)``:

- ``init(key, in_shape) -> (out_shape, params)``: ``in_shape`` is a tuple whose last entry is the
  channel count; leading entries (batch, height, width, ...) pass through and may be ``-1``.
- ``apply(params, x) -> y``: pure and jittable; ``x`` has any leading axes and channels last.

Params are plain pytrees (dicts of arrays, lists for `serial`), so they go straight through
`jaxdenoise.checkpoint.save` / ``load`` and any pure optimizer in `jaxdenoise.solvers`.

Layers here: `Dense` (Kalantari 2015 Eq. 7: ``a = f(W a_prev + w0)``), the activations `Sigmoid`,
`Softplus` (Kalantari 2015 Sec. 4.1), `Relu`, `LeakyRelu` (Chaitanya 2017: slope 0.1; Guo 2019:
0.01), `Identity`, and the combinator `serial`. One module per kind beside it, re-exported here:
`jaxdenoise.nn.conv` (`Conv`, `ConvTranspose`, their initializers, `pad_to_multiple` / `crop_to`)
`jaxdenoise.nn.pool` (`MaxPool`, `AvgPool`, `block_means`, `Upsample`) and `jaxdenoise.nn.combinators` (`fanout`,
`parallel`, `Concat`, `residual`, `UNet`, `RecurrentBlock`), `jaxdenoise.nn.norm` (`BatchNorm`) with
the stateful-layer convention of `jaxdenoise.nn.state` (explicit ``train`` mode, running statistics
returned as updates).
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp

__all__ = ["Dense", "Sigmoid", "Softplus", "Relu", "LeakyRelu", "Identity", "Elementwise", "serial", "Layer",
           "uniform_init", "glorot_uniform_init", "Conv", "ConvTranspose", "he_normal_init", "bilinear_init",
           "identity_init", "pad_to_multiple", "crop_to", "MaxPool", "AvgPool", "block_means", "Upsample", "fanout",
           "parallel", "Concat", "residual", "UNet", "RecurrentBlock", "BatchNorm", "merge_updates"]

Layer = tuple[Callable[..., Any], Callable[..., Any]]
Initializer = Callable[[jax.Array, tuple[int, ...]], jax.Array]


def uniform_init(scale: float = 0.5) -> Initializer:
    """Uniform in [-scale, scale]; Kalantari 2015 Sec. 3.1 draws weights in [-0.5, 0.5]."""
    if not scale > 0:
        raise ValueError(f"uniform_init: scale must be > 0, got {scale}")

    def init(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        return jax.random.uniform(key, shape, jnp.float32, -scale, scale)

    return init


def glorot_uniform_init(gain: float = 1.0) -> Initializer:
    """Glorot/Xavier uniform, U(-l, l) with l = sqrt(6 gain / (fan_in + fan_out)); the last two axes
    are (in, out) and any leading axes a receptive field (a conv kernel HWIO: fan_in = kh kw c_in).
    ``gain`` multiplies the variance (2 compensates a ReLU's halving, as He et al. 2015 do)."""
    if not gain > 0:
        raise ValueError(f"glorot_uniform_init: gain must be > 0, got {gain}")

    def init(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        rf = 1
        for n in shape[:-2]:
            rf *= int(n)
        fan_in, fan_out = rf * shape[-2], rf * shape[-1]
        limit = (6.0 * gain / (fan_in + fan_out)) ** 0.5
        return jax.random.uniform(key, shape, jnp.float32, -limit, limit)

    return init


def _check_shape(name: str, in_shape: Sequence[int]) -> tuple[int, ...]:
    in_shape = tuple(int(s) for s in in_shape)
    if len(in_shape) < 1 or in_shape[-1] <= 0:
        raise ValueError(f"{name}: in_shape must end with a positive channel count, got {in_shape}")
    return in_shape


def Dense(out_dim: int, *, w_init: Initializer | None = None, b_init: Initializer | None = None) -> Layer:
    """Fully connected layer on the last axis: ``y = x @ w + b`` (Kalantari 2015 Eq. 7 without f).

    Params ``{"w": (in, out), "b": (out,)}``. Defaults: Glorot-uniform weights, zero bias.
    """
    if int(out_dim) <= 0:
        raise ValueError(f"Dense: out_dim must be a positive integer, got {out_dim}")
    out_dim = int(out_dim)
    w_init = w_init or glorot_uniform_init()

    def init(key: jax.Array, in_shape: Sequence[int]):
        in_shape = _check_shape("Dense", in_shape)
        kw, kb = jax.random.split(key)
        w = w_init(kw, (in_shape[-1], out_dim))
        b = b_init(kb, (out_dim,)) if b_init is not None else jnp.zeros((out_dim,), jnp.float32)
        return in_shape[:-1] + (out_dim,), {"w": w, "b": b}

    def apply(params: dict, x: jax.Array) -> jax.Array:
        w = params["w"]
        if x.shape[-1] != w.shape[0]:
            raise ValueError(f"Dense: input has {x.shape[-1]} channels, the layer expects {w.shape[0]}")
        return jnp.matmul(x, w.astype(x.dtype)) + params["b"].astype(x.dtype)

    return init, apply


def Elementwise(fn: Callable[[jax.Array], jax.Array]) -> Layer:
    """A parameter-free layer applying ``fn`` to every element (params ``{}``)."""

    def init(key: jax.Array, in_shape: Sequence[int]):
        return tuple(in_shape), {}

    def apply(params: dict, x: jax.Array) -> jax.Array:
        return fn(x)

    return init, apply


# Activations are constructors returning layers (stax style: call them, e.g. ``Sigmoid()``).
def Sigmoid() -> Layer:
    """``1 / (1 + exp(-x))`` (Kalantari 2015 Sec. 4.1, hidden layer)."""
    return Elementwise(jax.nn.sigmoid)


def Softplus() -> Layer:
    """``log(1 + exp(x))``, always positive (Kalantari 2015 Sec. 4.1, output layer).

    `jax.nn.softplus` is the overflow-safe form ``logaddexp(x, 0)``: no ``exp`` of large x.
    """
    return Elementwise(jax.nn.softplus)


def Relu() -> Layer:
    return Elementwise(jax.nn.relu)


def LeakyRelu(slope: float = 0.01) -> Layer:
    """``x`` for x >= 0, ``slope * x`` below (Chaitanya 2017 Sec. 4.1: 0.1; Guo 2019 Sec. 4.4: 0.01)."""
    if not 0.0 <= float(slope) < 1.0:
        raise ValueError(f"LeakyRelu: slope must be in [0, 1), got {slope}")
    return Elementwise(lambda x: jax.nn.leaky_relu(x, float(slope)))


def Identity() -> Layer:
    return Elementwise(lambda x: x)


def serial(*layers: Layer) -> Layer:
    """Compose layers in order (stateful when a layer is: `jaxdenoise.nn.state`).

    Params are a dict keyed by the layer index as a string (``{"0": ..., "2": ...}``), holding only
    layers that have parameters: parameter-free layers (activations) are left out, so the pytree
    round-trips unchanged through `jaxdenoise.checkpoint` (which stores leaves only and would
    otherwise lose empty entries).
    """
    if not layers:
        raise ValueError("serial: needs at least one layer")
    inits, applies = zip(*layers)

    def init(key: jax.Array, in_shape: Sequence[int]):
        params = {}
        shape = tuple(in_shape)
        for i, layer_init in enumerate(inits):
            key, sub = jax.random.split(key)
            shape, p = layer_init(sub, shape)
            if jax.tree_util.tree_leaves(p):
                params[str(i)] = p
        return shape, params

    def apply(params: dict, x: jax.Array, train: bool = False):
        if not isinstance(params, dict):
            raise ValueError(f"serial: params must be a dict keyed by layer index, got {type(params).__name__}")
        extra = sorted(set(params) - {str(i) for i in range(len(applies))})
        if extra:
            raise ValueError(f"serial: params for unknown layer(s) {extra}; the model has {len(applies)} layers")
        updates: dict = {}
        for i, layer_apply in enumerate(applies):
            x = call(layer_apply, params.get(str(i), {}), x, train, updates, str(i))
        return (x, updates) if train and stateful else x

    stateful = any(is_stateful(a) for a in applies)
    return init, mark(apply, stateful)


# Sibling modules, one per kind of layer (imported last: they use nothing from this module).
from .state import call, is_stateful, mark, merge_updates  # noqa: E402
from .norm import BatchNorm  # noqa: E402
from .conv import Conv, ConvTranspose, bilinear_init, crop_to, he_normal_init, identity_init, pad_to_multiple  # noqa: E402
from .pool import AvgPool, MaxPool, Upsample, block_means  # noqa: E402
from .combinators import Concat, RecurrentBlock, UNet, fanout, parallel, residual  # noqa: E402
