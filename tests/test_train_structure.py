"""The training steps avoid the two slow patterns of this CPU (`jaxdenoise.nn.audit`): checked on
the jaxpr, not by timing, for every registered trainable method and on planted offenders."""
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


def _tiny_batches() -> dict:
    """name -> (tiny config, one training batch) for every registered trainable method."""
    from jaxdenoise.methods import gradnet, lbf, rae

    r = np.random.default_rng(0)
    u = lambda *s: r.uniform(0.1, 1.0, s).astype(np.float32)  # noqa: E731
    lbf_cfg = dict(radius=1, prefilter=False, features=("normal",), train_spps=(4,), train_crop=6)
    lbf_batch = {"x": u(2, 6, 6, 8), "color": u(2, 6, 6, 3), "color_var": u(2, 6, 6, 3), "reference": u(2, 6, 6, 3),
                 "spp": np.full(2, 4, np.float32), "guides": {"normal": u(2, 6, 6, 3)},
                 "guide_vars": {"normal": u(2, 6, 6, 1)}}
    rae_cfg = rae.Config(widths=(4, 4, 4, 4, 4), bottleneck=4)
    rae_paper = rae.Config(widths=(4, 4, 4, 4, 4), bottleneck=4, recipe="paper", exposure="none", rate_input=False,
                           train_spps=(1,))
    gn_cfg = gradnet.Config(widths=(4, 4, 4), res_blocks=1, g_width=4)
    gn = {f: u(2, 16, 16, 3) for f in ("color", "dx", "dy", "albedo", "normal")}
    return {
        "lbf": (lbf.Config(filter="bilateral", **lbf_cfg), lbf_batch),
        "lbf-nlm": (lbf.Config(filter="nlm", **lbf_cfg), lbf_batch),
        "demc": (demc.Config(widths=(4, 4, 4, 4, 4), fusion_width=4),
                 {f: u(2, 32, 32, 3) for f in ("color", *demc.FEATURES, "reference")}),
        "demc-paper": (demc.Config(widths=(4, 4, 4, 4, 4), fusion_width=4, recipe="paper", exposure="none",
                                   train_spps=(4,)),
                       {f: u(2, 32, 32, 3) for f in ("color", *demc.FEATURES, "reference")}),
        "rae": (rae_cfg, {"x": u(1, 7, 32, 32, rae.in_channels(rae_cfg)), "albedo": u(1, 7, 32, 32, 3),
                          "reference": u(1, 7, 32, 32, 3), "scale": u(1, 7, 1, 1, 1)}),
        "rae-paper": (rae_paper, {"x": u(1, 7, 32, 32, rae.in_channels(rae_paper)), "albedo": u(1, 7, 32, 32, 3),
                                  "reference": u(1, 7, 32, 32, 3)}),
        "gradnet": (gn_cfg, {**gn, "depth": u(2, 16, 16, 1), "lambda": np.float32(1.0)}),
    }


def test_every_registered_network_training_step_has_no_slow_pattern():
    """Every registered trainable method (the first assertion names a new one without a case): the
    gradient of its loss, as the trainer takes it, has no rolled scan over convolutions and no
    reduce_window pooling gradient (RAE's seven-frame loop is where a rolled scan would hurt)."""
    from jaxdenoise.methods import get, names

    cases = _tiny_batches()
    assert set(cases) == {n for n in names() if get(n).trainable}, "add a tiny batch for the new method"
    for name, (cfg, batch) in cases.items():
        m = get(name, cfg)
        p = jax.eval_shape(m.init, jax.random.PRNGKey(0))  # shapes suffice for a jaxpr (an eager init: 15 s)
        groups = m.module.param_groups(cfg) if hasattr(m.module, "param_groups") else {None: None}

        def loss(q, group):
            out = m.module.loss(q, batch, cfg) if group is None else m.module.loss(q, batch, cfg, group=group)
            return out[0] if isinstance(out, tuple) else out

        for group in groups:
            assert slow_patterns(jax.grad(lambda q: loss(q, group)), p) == [], (name, group)
