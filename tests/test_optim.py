"""Pure optimizers (jaxdenoise.solvers.optim): Adam and RPROP against closed-form steps."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise.solvers import adam, rprop


def tree(a, b):
    return {"w": jnp.asarray(a, jnp.float32), "layer": [jnp.asarray(b, jnp.float32)]}


# -- Adam ---------------------------------------------------------------------------------------------

def test_adam_constant_gradient_closed_form():
    """With a constant gradient g, m_hat = g and v_hat = g^2 at every step (bias correction), so each
    step moves by exactly lr * g / (|g| + eps)."""
    lr, eps = 0.01, 1e-8
    g = tree([0.5, -2.0, 0.0], [[3e-4]])
    p0 = tree([1.0, 1.0, 1.0], [[0.0]])
    init, update = adam(lr, eps=eps)
    p, s = p0, init(p0)
    for _ in range(7):
        p, s = update(g, s, p)
    for leaf_p, leaf_p0, leaf_g in zip(jax.tree_util.tree_leaves(p), jax.tree_util.tree_leaves(p0),
                                       jax.tree_util.tree_leaves(g)):
        expect = np.asarray(leaf_p0) - 7 * lr * np.asarray(leaf_g) / (np.abs(np.asarray(leaf_g)) + eps)
        np.testing.assert_allclose(leaf_p, expect, rtol=1e-5, atol=1e-7)  # tol: 1e-5 rel, 1e-7 abs
    assert int(s.count) == 7


def test_adam_two_steps_by_hand():
    """Algorithm 1 of Kingma & Ba written out for two steps with different gradients."""
    lr, b1, b2, eps = 0.1, 0.9, 0.999, 1e-8
    g1, g2 = 2.0, -1.0
    m1, v1 = (1 - b1) * g1, (1 - b2) * g1 ** 2
    p1 = 0.5 - lr * (m1 / (1 - b1)) / (np.sqrt(v1 / (1 - b2)) + eps)
    m2, v2 = b1 * m1 + (1 - b1) * g2, b2 * v1 + (1 - b2) * g2 ** 2
    p2 = p1 - lr * (m2 / (1 - b1 ** 2)) / (np.sqrt(v2 / (1 - b2 ** 2)) + eps)
    init, update = adam(lr, b1, b2, eps)
    update = jax.jit(update)
    p = jnp.float32(0.5)
    s = init(p)
    p, s = update(jnp.float32(g1), s, p)
    assert abs(float(p) - p1) <= 1e-6                                    # tol: 1e-6 abs
    p, s = update(jnp.float32(g2), s, p)
    assert abs(float(p) - p2) <= 1e-6                                    # tol: 1e-6 abs


def test_adam_schedule_and_minimizes_quadratic():
    init, update = adam(lambda count: 0.1 / (1.0 + 0.01 * count))
    target = tree([1.0, -2.0, 3.0], [[0.5]])
    loss = lambda p: sum(jnp.sum((a - b) ** 2) for a, b in zip(jax.tree_util.tree_leaves(p),
                                                                jax.tree_util.tree_leaves(target)))
    p = tree([0.0, 0.0, 0.0], [[0.0]])
    s = init(p)

    @jax.jit
    def step(p, s):
        return update(jax.grad(loss)(p), s, p)
    for _ in range(600):
        p, s = step(p, s)
    assert float(loss(p)) <= 1e-4                                        # tol: loss <= 1e-4


def test_adam_bad_arguments():
    with pytest.raises(ValueError, match="'lr'"):
        adam(-1.0)
    with pytest.raises(ValueError, match="'b2'"):
        adam(0.1, b2=1.0)


# -- RPROP --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["irprop-", "rprop+"])
def test_rprop_constant_sign_grows_geometrically_to_step_max(variant):
    """Same sign every step: Delta_t = min(Delta_0 * eta+^(t-1), Delta_max), and the weight moves by
    -sign(g) * Delta_t (the first step uses Delta_0: there is no previous gradient)."""
    d0, eta, dmax = 0.1, 1.2, 0.3
    init, update = rprop(d0, eta_plus=eta, step_max=dmax, variant=variant)
    p = jnp.asarray([0.0, 0.0])
    g = jnp.asarray([3.0, -0.001])
    s = init(p)
    for _ in range(10):
        p, s = update(g, s, p)
    total = sum(min(d0 * eta ** t, dmax) for t in range(10))
    np.testing.assert_allclose(p, [-total, total], rtol=1e-5)           # tol: 1e-5 relative


def test_irprop_minus_sign_flip_skips_step_and_halves():
    init, update = rprop(0.1, variant="irprop-")
    p = jnp.float32(0.0)
    s = init(p)
    p, s = update(jnp.float32(1.0), s, p)       # moves -0.1
    p, s = update(jnp.float32(-1.0), s, p)      # flip: Delta -> 0.05, no move, gradient forgotten
    assert abs(float(p) + 0.1) <= 1e-7                                   # tol: 1e-7 abs
    p, s = update(jnp.float32(-1.0), s, p)      # previous gradient 0: Delta stays 0.05, moves +0.05
    assert abs(float(p) + 0.05) <= 1e-7                                  # tol: 1e-7 abs
    p, s = update(jnp.float32(-1.0), s, p)      # same sign: Delta 0.06, moves +0.06
    assert abs(float(p) - 0.01) <= 1e-7                                  # tol: 1e-7 abs


def test_rprop_plus_backtracks_on_flip():
    init, update = rprop(0.1, variant="rprop+")
    p = jnp.float32(0.0)
    s = init(p)
    p, s = update(jnp.float32(1.0), s, p)       # -0.1
    p, s = update(jnp.float32(1.0), s, p)       # -0.12
    p, s = update(jnp.float32(-1.0), s, p)      # flip: undo the last change (+0.12), Delta -> 0.06
    assert abs(float(p) + 0.1) <= 1e-7                                   # tol: 1e-7 abs
    p, s = update(jnp.float32(-1.0), s, p)      # previous gradient 0: moves +0.06
    assert abs(float(p) + 0.04) <= 1e-7                                  # tol: 1e-7 abs


def test_rprop_step_min_clamp_and_minimizes():
    init, update = rprop(0.5, step_min=0.01, variant="irprop-")
    target = tree([1.0, -2.0, 3.0], [[0.5]])
    loss = lambda p: sum(jnp.sum((a - b) ** 2) for a, b in zip(jax.tree_util.tree_leaves(p),
                                                                jax.tree_util.tree_leaves(target)))
    p = tree([0.0, 0.0, 0.0], [[0.0]])
    s = init(p)
    step = jax.jit(lambda p, s: update(jax.grad(loss)(p), s, p))
    for _ in range(200):
        p, s = step(p, s)
    assert float(loss(p)) <= 4 * 0.01 ** 2 * 4                           # tol: within step_min per weight
    assert all(float(jnp.min(d)) >= 0.01 - 1e-9 for d in jax.tree_util.tree_leaves(s.step))


def test_rprop_bad_arguments():
    with pytest.raises(ValueError, match="'variant'"):
        rprop(variant="rprop")
    with pytest.raises(ValueError, match="'eta_minus'"):
        rprop(eta_minus=-0.5)
    with pytest.raises(ValueError, match="step_min <= step_init"):
        rprop(100.0)
