"""jaxdenoise.nn: stax-style layers (shapes, values against NumPy, checkpoint round trip, errors)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise import checkpoint, nn


def _mlp():
    return nn.serial(nn.Dense(10, w_init=nn.uniform_init(0.5), b_init=nn.uniform_init(0.5)), nn.Sigmoid(),
                     nn.Dense(6), nn.Softplus())


def test_init_predicts_apply_shape():
    init, apply = _mlp()
    out_shape, params = init(jax.random.PRNGKey(0), (-1, 4, 5, 36))
    y = apply(params, jnp.ones((2, 4, 5, 36)))
    assert out_shape == (-1, 4, 5, 6)
    assert y.shape == (2, 4, 5, 6)  # exact


def test_mlp_matches_numpy():
    init, apply = _mlp()
    _, params = init(jax.random.PRNGKey(1), (-1, 36))
    x = np.random.default_rng(0).normal(size=(7, 36)).astype(np.float32)
    w0, b0 = np.asarray(params["0"]["w"]), np.asarray(params["0"]["b"])
    w2, b2 = np.asarray(params["2"]["w"]), np.asarray(params["2"]["b"])
    h = 1.0 / (1.0 + np.exp(-(x @ w0 + b0)))
    want = np.log1p(np.exp(h @ w2 + b2))
    np.testing.assert_allclose(np.asarray(apply(params, x)), want, rtol=1e-5, atol=1e-6)


def test_uniform_init_range():
    init, _ = nn.Dense(10, w_init=nn.uniform_init(0.5), b_init=nn.uniform_init(0.5))
    _, p = init(jax.random.PRNGKey(2), (36,))
    assert float(jnp.max(jnp.abs(p["w"]))) <= 0.5 and float(jnp.max(jnp.abs(p["b"]))) <= 0.5  # exact bound
    assert float(jnp.std(p["w"])) > 0.2  # uniform on [-0.5, 0.5] has std 0.289; 360 draws


def test_softplus_is_positive_and_finite_for_large_inputs():
    _, apply = nn.Softplus()
    y = apply({}, jnp.array([-1e4, 0.0, 1e4]))
    assert bool(jnp.all(jnp.isfinite(y)))
    assert float(y[0]) >= 0.0 and abs(float(y[2]) - 1e4) < 1e-2  # softplus(x) ~ x for large x (tol 1e-2)


def test_params_roundtrip_through_checkpoint(tmp_path):
    init, apply = _mlp()
    _, params = init(jax.random.PRNGKey(3), (36,))
    checkpoint.save(tmp_path, params)
    loaded, _ = checkpoint.load(tmp_path)
    x = jnp.linspace(-1, 1, 36)
    np.testing.assert_array_equal(np.asarray(apply(loaded, x)), np.asarray(apply(params, x)))  # exact
    assert jax.tree_util.tree_structure(jax.tree_util.tree_map(np.asarray, loaded)) == \
        jax.tree_util.tree_structure(jax.tree_util.tree_map(np.asarray, params))


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="out_dim"):
        nn.Dense(0)
    init, apply = nn.Dense(3)
    _, p = init(jax.random.PRNGKey(0), (4,))
    with pytest.raises(ValueError, match="expects 4"):
        apply(p, jnp.ones((2, 5)))
    with pytest.raises(ValueError, match="channel count"):
        init(jax.random.PRNGKey(0), ())
    with pytest.raises(ValueError, match="at least one layer"):
        nn.serial()
