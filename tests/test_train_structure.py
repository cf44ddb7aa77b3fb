"""The training steps avoid the two slow patterns of this CPU (`jaxdenoise.nn.audit`): checked on
the jaxpr, not by timing, for every registered convolutional network and on planted offenders."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdenoise import nn
from jaxdenoise.methods import demc
from jaxdenoise.nn.audit import slow_patterns


def _conv(w, x):
    return jax.lax.conv_general_dilated(x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))


def _recurrent_loss(unroll):
    def loss(w, xs):
        def body(h, x):
            h = jnp.tanh(_conv(w, x + h))
            return h, jnp.sum(h)
        return jnp.sum(jax.lax.scan(body, jnp.zeros_like(xs[0]), xs, unroll=unroll)[1])
    return loss


def test_planted_rolled_scan_over_convolutions_is_found():
    w, xs = jnp.ones((3, 3, 2, 2)) * 0.1, jnp.ones((7, 1, 6, 6, 2))
    found = slow_patterns(jax.grad(_recurrent_loss(1)), w, xs)
    assert found and "rolled" in found[0]
    assert slow_patterns(jax.grad(_recurrent_loss(True)), w, xs) == []


def test_planted_reduce_window_max_pool_is_found():
    pool = lambda x: jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
    found = slow_patterns(jax.grad(lambda x: jnp.sum(pool(x) ** 2)), jnp.ones((1, 4, 4, 2)))
    assert any("reduce_window" in f or "select_and" in f for f in found)
    assert slow_patterns(jax.grad(lambda x: jnp.sum(nn.MaxPool(2)[1]({}, x) ** 2)), jnp.ones((1, 4, 4, 2))) == []


def test_demc_training_step_has_no_slow_pattern():
    cfg = demc.Config(widths=(4, 4, 4, 4, 4), fusion_width=4)
    p = demc.init(jax.random.PRNGKey(0), cfg)
    r = np.random.default_rng(0)
    b = {f: r.uniform(0, 1, (2, 32, 32, 3)).astype(np.float32) for f in ("color", *demc.FEATURES, "reference")}
    assert slow_patterns(jax.grad(lambda q: demc.loss(q, b, cfg)[0]), p) == []
