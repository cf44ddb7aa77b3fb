"""Combinators for the shapes the papers' networks use (stax style; `serial` is in `jaxdenoise.nn`).

- `fanout(n)`: ``x -> (x, ..., x)``; `parallel(*layers)`: a tuple of inputs, one layer each (the two
  encoders of DEMC, Yang 2019 Fig. 3; the data and gradient branches of GradNet, Guo 2019 Fig. 4);
  `Concat()`: a tuple of NHWC tensors -> one, along channels.
- `residual(layer)`: ``x + layer(x)`` (GradNet's residual blocks, Guo 2019 Sec. 4.4).
- `UNet(down, pool, bottleneck, up, merge, decode)`: encoder stages whose outputs reach the decoder
  stage of the same level through skip connections (Chaitanya 2017 Fig. 2, Yang 2019 Fig. 3).
- `RecurrentBlock(channels)`: Chaitanya 2017 Sec. 4.1, Fig. 2: a 3x3 conv on the input,
  concatenation with the hidden state, two more 3x3 convs; the result is both the output and the
  new hidden state. The hidden state is an explicit argument and return value:
  ``apply(params, x, h) -> h_new`` and ``init_state(in_shape) -> zeros``.

Stateful children (BatchNorm) make a combinator stateful: its ``apply`` takes ``train`` and, in
training mode, returns ``(y, updates)`` (`jaxdenoise.nn.state`). Parameter pytrees are dicts keyed by position (``"0"``, ``"1"``, ...) or by role (``"down"``,
``"up"``...), leaving out parameter-free children, like `serial`'s.
"""
from __future__ import annotations

from typing import Any, Sequence

import jax
import jax.numpy as jnp

from .conv import Conv
from .state import call, is_stateful, mark

__all__ = ["fanout", "parallel", "Concat", "residual", "UNet", "RecurrentBlock"]


def _keep(params: dict, key: str, p: Any) -> None:
    if jax.tree_util.tree_leaves(p):
        params[key] = p


def fanout(n: int):
    """``x -> (x,) * n`` (no parameters)."""
    if int(n) < 1:
        raise ValueError(f"fanout: n must be >= 1, got {n}")

    def init(key, in_shape):
        return (tuple(in_shape),) * n, {}

    def apply(params, x):
        return (x,) * n

    return init, apply


def parallel(*layers):
    """A tuple of inputs, the i-th through the i-th layer; returns the tuple of outputs."""
    if not layers:
        raise ValueError("parallel: needs at least one layer")
    inits, applies = zip(*layers)

    def init(key, in_shapes):
        if len(in_shapes) != len(inits):
            raise ValueError(f"parallel: {len(in_shapes)} input shapes for {len(inits)} layers")
        params, shapes = {}, []
        for i, (f, s) in enumerate(zip(inits, in_shapes)):
            key, sub = jax.random.split(key)
            shape, p = f(sub, s)
            shapes.append(shape)
            _keep(params, str(i), p)
        return tuple(shapes), params

    def apply(params, xs, train: bool = False):
        if len(xs) != len(applies):
            raise ValueError(f"parallel: {len(xs)} inputs for {len(applies)} layers")
        updates: dict = {}
        ys = tuple(call(f, params.get(str(i), {}), x, train, updates, str(i))
                   for i, (f, x) in enumerate(zip(applies, xs)))
        return (ys, updates) if train and stateful else ys

    stateful = any(is_stateful(a) for a in applies)
    return init, mark(apply, stateful)


def Concat():
    """A tuple of ``(..., H, W, C_i)`` tensors -> ``(..., H, W, sum C_i)``."""

    def init(key, in_shapes):
        lead = {tuple(s[:-1]) for s in in_shapes}
        if len(lead) != 1:
            raise ValueError(f"Concat: inputs differ in more than channels: {list(in_shapes)}")
        return tuple(in_shapes[0][:-1]) + (sum(int(s[-1]) for s in in_shapes),), {}

    def apply(params, xs):
        return jnp.concatenate(xs, axis=-1)

    return init, apply


def residual(layer):
    """``x + layer(x)``; the layer must keep the shape."""
    f_init, f_apply = layer

    def init(key, in_shape):
        shape, params = f_init(key, in_shape)
        if tuple(shape) != tuple(in_shape):
            raise ValueError(f"residual: the layer maps {tuple(in_shape)} to {tuple(shape)}; it must keep the shape")
        return shape, params

    def apply(params, x, train: bool = False):
        if train and is_stateful(f_apply):
            y, updates = f_apply(params, x, train=True)
            return x + y, updates
        return x + (f_apply(params, x, train=False) if is_stateful(f_apply) else f_apply(params, x))

    return init, mark(apply, is_stateful(f_apply))


def UNet(down: Sequence, pool, bottleneck, up, decode: Sequence):
    """A U-Net: for level i = 0..L-1, ``x = down[i](x)`` is kept as skip i and ``x = pool(x)``; then
    ``x = bottleneck(x)``; then for i = L-1..0, ``x = decode[i](concat(up(x), skip_i))``. ``pool`` and
    ``up`` are shared parameter-free layers (e.g. `MaxPool`, `Upsample`); inputs must be a multiple of
    the total stride (`pad_to_multiple`). Params: ``{"down": {i: ...}, "bottleneck": ..., "decode":
    {i: ...}}``."""
    if len(down) != len(decode) or not down:
        raise ValueError(f"UNet: needs as many decoder as encoder stages (>= 1), got {len(down)} and {len(decode)}")
    p_init, p_apply = pool
    u_init, u_apply = up
    b_init, b_apply = bottleneck

    def init(key, in_shape):
        params: dict = {"down": {}, "decode": {}}
        shape, skips = tuple(in_shape), []
        for i, (f, _) in enumerate(down):
            key, sub = jax.random.split(key)
            shape, p = f(sub, shape)
            _keep(params["down"], str(i), p)
            skips.append(shape)
            shape, _ = p_init(None, shape)
        key, sub = jax.random.split(key)
        shape, p = b_init(sub, shape)
        _keep(params, "bottleneck", p)
        for i in reversed(range(len(decode))):
            shape, _ = u_init(None, shape)
            shape = tuple(shape[:-1]) + (int(shape[-1]) + int(skips[i][-1]),)
            key, sub = jax.random.split(key)
            shape, p = decode[i][0](sub, shape)
            _keep(params["decode"], str(i), p)
        params = {k: v for k, v in params.items() if jax.tree_util.tree_leaves(v)}
        return shape, params

    def apply(params, x, train: bool = False):
        skips = []
        updates: dict = {"down": {}, "decode": {}}
        for i, (_, f) in enumerate(down):
            x = call(f, params.get("down", {}).get(str(i), {}), x, train, updates["down"], str(i))
            skips.append(x)
            x = p_apply({}, x)
        x = call(b_apply, params.get("bottleneck", {}), x, train, updates, "bottleneck")
        for i in reversed(range(len(decode))):
            x = u_apply({}, x)
            x = call(decode[i][1], params.get("decode", {}).get(str(i), {}), jnp.concatenate([x, skips[i]], axis=-1),
                     train, updates["decode"], str(i))
        return (x, {k: v for k, v in updates.items() if v}) if train and stateful else x

    stateful = any(is_stateful(a) for a in [f for _, f in down] + [b_apply] + [f for _, f in decode])
    return init, mark(apply, stateful)


def RecurrentBlock(channels: int, *, kernel: int = 3, slope: float = 0.1, w_init=None):
    """Chaitanya 2017's recurrent block (module docstring), leaky ReLU ``slope`` after each conv
    (their Sec. 4.1: 0.1). Returns ``(init, apply, init_state)``:
    ``init(key, in_shape) -> (out_shape, params)``, ``apply(params, x, h) -> h_new`` (``h_new`` is
    also the block's output), ``init_state(in_shape) -> zeros`` of the output shape."""
    channels = int(channels)
    c_in_init, c_in = Conv(channels, kernel, w_init=w_init)
    c1_init, c1 = Conv(channels, kernel, w_init=w_init)
    c2_init, c2 = Conv(channels, kernel, w_init=w_init)
    act = lambda v: jax.nn.leaky_relu(v, slope)

    def init(key, in_shape):
        k0, k1, k2 = jax.random.split(key, 3)
        shape, p0 = c_in_init(k0, in_shape)
        cat = tuple(shape[:-1]) + (2 * channels,)
        shape, p1 = c1_init(k1, cat)
        shape, p2 = c2_init(k2, shape)
        return shape, {"in": p0, "h1": p1, "h2": p2}

    def apply(params, x, h):
        a = act(c_in(params["in"], x))
        if h.shape != a.shape:
            raise ValueError(f"RecurrentBlock: hidden state has shape {tuple(h.shape)}; expected {tuple(a.shape)}")
        z = act(c1(params["h1"], jnp.concatenate([a, h], axis=-1)))
        return act(c2(params["h2"], z))

    def init_state(in_shape, dtype=jnp.float32):
        return jnp.zeros(tuple(in_shape[:-1]) + (channels,), dtype)

    return init, apply, init_state
