"""Transfer functions: closed forms, round trips, gradients, bad input (jaxdenoise.color)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise import color

VALUES = np.array([-1e4, -3.0, -1.0, -1e-5, 0.0, 1e-7, 1e-3, 0.3, 1.0, 7.5, 1e4], np.float32)
PAIRS = [color.GAMMA, color.LOG, color.MU_LAW, color.SRGB, color.IDENTITY]


@pytest.mark.parametrize("pair", PAIRS, ids=lambda p: p.name)
def test_round_trip(pair):
    y = pair.forward(VALUES)
    back = np.asarray(pair.inverse(y))
    # float32 round trip: relative 1e-5 plus absolute 1e-6 near zero
    np.testing.assert_allclose(back, VALUES, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pair.forward(pair.inverse(y))), np.asarray(y), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("pair", PAIRS, ids=lambda p: p.name)
def test_odd_and_monotone(pair):
    y = np.asarray(pair.forward(VALUES))
    np.testing.assert_allclose(np.asarray(pair.forward(-VALUES)), -y, rtol=0, atol=0)  # exact symmetry
    assert np.all(np.diff(y) > 0), "forward transfer must be strictly increasing"


def test_closed_forms():
    x = np.array([0.0, 0.25, 1.0, 4.0], np.float64)
    np.testing.assert_allclose(np.asarray(color.gamma(x.astype(np.float32))), x ** (1 / 2.2), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(color.log_transform(x.astype(np.float32))), np.log1p(x), rtol=1e-6)
    # Guo et al. 2019 Eq. 6 with mu = 16: log(1 + 16 x) / log(17)
    np.testing.assert_allclose(np.asarray(color.mu_law(x.astype(np.float32))), np.log1p(16 * x) / math.log(17),
                               rtol=1e-6)
    np.testing.assert_allclose(np.asarray(color.mu_law(x.astype(np.float32), mu=1.0)),
                               np.log1p(x) / math.log(2), rtol=1e-6)  # mu = 1: log up to a constant
    # sRGB (IEC 61966-2-1): linear toe below 0.0031308, 1.055 x^(1/2.4) - 0.055 above; continuous
    s = np.array([0.0, 0.001, 0.0031308, 0.2, 1.0], np.float64)
    want = np.where(s <= 0.0031308, 12.92 * s, 1.055 * s ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(np.asarray(color.srgb(s.astype(np.float32))), want, rtol=1e-5, atol=1e-7)
    assert float(color.srgb(1.0)) == pytest.approx(1.0, abs=1e-6)
    t = np.array([-1.0, 0.0, 0.5, 1.0, 3.0], np.float32)
    np.testing.assert_allclose(np.asarray(color.tonemap(t)), np.clip(t, 0, 1) ** (1 / 2.2), rtol=1e-6)


def test_mu_law_maps_unit_interval_to_itself():
    np.testing.assert_allclose(np.asarray(color.mu_law(np.array([0.0, 1.0], np.float32), mu=16.0)), [0.0, 1.0],
                               atol=1e-7)


@pytest.mark.parametrize("fn", [color.gamma, color.inv_gamma, color.log_transform, color.inv_log_transform,
                                color.mu_law, color.inv_mu_law, color.tonemap, color.srgb, color.inv_srgb],
                         ids=lambda f: f.__name__)
def test_gradients_finite_at_zero_and_extremes(fn):
    # +-20 stays inside every inverse's float32 range (inv_mu_law(20) = (17^20 - 1) / 16 ~ 2.6e23)
    g = jax.vmap(jax.grad(lambda v: fn(v)))(jnp.array([0.0, -0.0, 1e-30, -1e-30, 1.0, 20.0, -20.0], jnp.float32))
    assert np.all(np.isfinite(np.asarray(g))), f"{fn.__name__}: non-finite gradient {g}"


def test_gradient_matches_derivative():
    x = jnp.array([0.1, 0.5, 2.0], jnp.float32)
    g = jax.vmap(jax.grad(lambda v: color.mu_law(v)))(x)
    want = 16.0 / ((1 + 16.0 * np.asarray(x)) * math.log(17.0))
    np.testing.assert_allclose(np.asarray(g), want, rtol=1e-5)
    g = jax.vmap(jax.grad(lambda v: color.gamma(v)))(x)
    np.testing.assert_allclose(np.asarray(g), (1 / 2.2) * np.asarray(x) ** (1 / 2.2 - 1), rtol=1e-5)


def test_jit_matches_eager():
    f = jax.jit(lambda v: color.inv_mu_law(color.mu_law(v)) + color.tonemap(v))
    np.testing.assert_allclose(np.asarray(f(VALUES)), np.asarray(color.inv_mu_law(color.mu_law(VALUES))
                                                                 + color.tonemap(VALUES)), rtol=1e-6, atol=1e-6)


def test_demodulate_round_trip_and_zero_albedo():
    rng = np.random.default_rng(0)
    c = rng.uniform(0, 5, (4, 5, 3)).astype(np.float32)
    a = rng.uniform(0, 1, (4, 5, 3)).astype(np.float32)
    a[0, 0] = 0.0  # black texture: the eps guard must keep it finite
    d = color.demodulate(c, a)
    assert np.all(np.isfinite(np.asarray(d)))
    np.testing.assert_allclose(np.asarray(d), c / (a + color.ALBEDO_EPS_DEFAULT), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(color.remodulate(d, a)), c, rtol=1e-5)
    # zero colour over zero albedo is 0, not NaN
    assert float(color.demodulate(np.zeros(3, np.float32), np.zeros(3, np.float32)).sum()) == 0.0


def test_demodulate_float16_promotes():
    c = np.full((2, 2, 3), 1000.0, np.float16)
    a = np.zeros((2, 2, 3), np.float16)
    d = color.demodulate(c, a)
    assert d.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(d)))  # 1000 / 0.00316 = 3.2e5 would overflow float16
    np.testing.assert_allclose(np.asarray(color.remodulate(d, a)), 1000.0, rtol=1e-5)


def test_demodulate_gradient_finite_at_zero_albedo():
    g = jax.grad(lambda a: color.demodulate(jnp.ones(3), a).sum())(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))


def test_bad_input():
    with pytest.raises(ValueError, match="'eps' must be > 0"):
        color.demodulate(np.ones(3), np.ones(3), eps=0.0)
    with pytest.raises(ValueError, match="'mu' must be > 0"):
        color.mu_law(np.ones(3), mu=-1.0)
    with pytest.raises(ValueError, match="unknown transfer 'xyz'"):
        color.transfer("xyz")
    assert color.transfer("mu-law") is color.MU_LAW
