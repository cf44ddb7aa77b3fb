"""jaxdenoise.arrays: the median of nine by a sorting network against NumPy's median; the lower quantile by
bisection against jnp.quantile."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise.arrays import edge_blocks, edge_views, median9, quantile_lower


@pytest.mark.parametrize("ties", [False, True])
def test_median9_equals_numpy_median(ties):
    rng = np.random.default_rng(3)
    v = rng.integers(0, 4, (9, 31)) if ties else rng.standard_normal((9, 31))
    v = v.astype(np.float32)
    np.testing.assert_array_equal(np.asarray(median9(jnp.asarray(v))), np.median(v, axis=0))  # exact: a selection


def test_median_of_the_edge_views_matches_numpy_on_odd_sizes():
    x = np.random.default_rng(8).random((7, 9, 2)).astype(np.float32)
    p = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    ref = np.median(np.stack([p[i:i + 7, j:j + 9] for i in range(3) for j in range(3)]), axis=0)
    np.testing.assert_array_equal(np.asarray(median9(edge_views(jnp.asarray(x), 1))), ref)     # exact (a selection)
    np.testing.assert_array_equal(np.asarray(median9(edge_views(jnp.asarray(x[:1, :1]), 1))), x[:1, :1])  # 1x1: itself


def test_median9_gradient_selects_the_median():
    v = jnp.asarray(np.random.default_rng(1).permutation(9).astype(np.float32))
    g = jax.grad(lambda a: median9(a))(v)
    assert float(g[int(np.argsort(np.asarray(v))[4])]) == 1.0 and float(jnp.sum(g)) == 1.0  # tol: exact


def test_median9_refuses_other_counts():
    with pytest.raises(ValueError, match="9 arrays"):
        median9([jnp.zeros(2)] * 8)


def test_edge_blocks_stack_the_edge_views():
    x = jnp.asarray(np.random.default_rng(2).random((2, 5, 6, 3)).astype(np.float32))
    np.testing.assert_array_equal(np.asarray(edge_blocks(x, 1, axis=0)), np.stack(edge_views(x, 1)))


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 4099])
def test_quantile_lower_is_jnp_quantile_bit_for_bit(n):
    """`quantile_lower` (bisection on order keys) gives ``jnp.quantile(..., method="lower")``'s value:
    negative values, zeros of both signs, ties, leading axes, every q from 0 to 1; the gradient goes
    to the selected element."""
    r = np.random.default_rng(n)
    a = (r.standard_normal((3, 2, n)) * 5).astype(np.float32)
    a[0, 0, : n // 2] = 0.0
    a[0, 1, : n // 3] = -0.0
    a[0, 1, n // 3: 2 * n // 3] = 0.0  # both zeros in one row
    a[1] = np.round(a[1])  # ties
    a[2, 0] = np.abs(a[2, 0]) ** 3  # a heavy tail
    for q in (0.0, 0.1, 0.5, 0.999, 1.0):
        np.testing.assert_array_equal(np.asarray(quantile_lower(a, q)),
                                      np.asarray(jnp.quantile(a, q, axis=-1, method="lower")))
    v = jnp.asarray([5.0, 1.0, 8.0, 3.0, 0.0, 7.0, 2.0, 6.0, 4.0])  # the median, 4.0, is the last
    np.testing.assert_array_equal(np.asarray(jax.grad(lambda u: quantile_lower(u, 0.5))(v)), np.eye(9)[8])
    with pytest.raises(ValueError, match="q must be"):
        quantile_lower(a, 1.5)
