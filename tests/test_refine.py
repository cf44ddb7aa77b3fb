"""`jaxdenoise.filters.refine` (the feature-guided pass over a network's output) against a NumPy
evaluation of its weights, its invariances and errors, and its place in `demc.apply` and `rae.step`."""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise.buffers import Buffers
from jaxdenoise.errors import JaxdenoiseError
from jaxdenoise.filters import FilterError, check_refine_settings, exact_mask, refine
from jaxdenoise.methods import demc, rae

KW = {"sigma": 1.5, "range_sigma": 0.4, "albedo_sigma": 0.1, "normal_sigma": 0.3}


def _numpy_refine(y, a, n, sigma, range_sigma, albedo_sigma, normal_sigma, radius):
    """The module docstring's weights, pixel by pixel (float64)."""
    h, w, _ = y.shape
    m = np.abs(y).mean(-1)
    out = np.zeros_like(y, np.float64)
    for i in range(h):
        for j in range(w):
            num, den = np.zeros(y.shape[-1]), 0.0
            for di in range(-radius, radius + 1):
                for dj in range(-radius, radius + 1):
                    k, l = i + di, j + dj
                    if not (0 <= k < h and 0 <= l < w):
                        continue
                    e = (di * di + dj * dj) / (2 * sigma ** 2)
                    rng2 = 2 * range_sigma ** 2 * (m[i, j] ** 2 + m[k, l] ** 2)
                    e += np.sum((y[i, j] - y[k, l]) ** 2) / (rng2 + 1e-10)
                    e += np.sum((a[i, j] - a[k, l]) ** 2) / (2 * albedo_sigma ** 2)
                    e += np.sum((n[i, j] - n[k, l]) ** 2) / (2 * normal_sigma ** 2)
                    num, den = num + math.exp(-e) * y[k, l], den + math.exp(-e)
            out[i, j] = num / den
    return out


def _images(h=7, w=6, seed=0):
    r = np.random.default_rng(seed)
    return (r.uniform(0.2, 1.0, (h, w, 3)).astype(np.float32), r.uniform(0, 1, (h, w, 3)).astype(np.float32),
            r.uniform(-1, 1, (h, w, 3)).astype(np.float32))


def test_refine_matches_its_weights():
    y, a, n = _images()
    a[:, :3] = 0.5  # one flat albedo region, so some weights are far from 0
    n[:, :3] = [0.0, 0.0, 1.0]
    got = np.asarray(refine(y, a, n, **KW, radius=2))
    np.testing.assert_allclose(got, _numpy_refine(y, a, n, **KW, radius=2), rtol=2e-5)
    # radius defaults to ceil(2 sigma)
    np.testing.assert_array_equal(np.asarray(refine(y, a, n, **KW)), np.asarray(refine(y, a, n, **KW, radius=3)))


def test_refine_keeps_edges_and_scales_with_the_image():
    """Noise on two halves of different albedo is averaged within each half, not across; a shadow
    (the same albedo, 5x darker) moves by under 1 % at its edge; refine(k y) = k refine(y)."""
    r = np.random.default_rng(1)
    h, w = 16, 16
    a = np.where(np.arange(w)[None, :, None] < 8, 0.2, 0.8) * np.ones((h, w, 3), np.float32)
    n = np.broadcast_to(np.float32([0, 0, 1]), (h, w, 3))
    y = (a * r.uniform(0.8, 1.2, (h, w, 1))).astype(np.float32)
    out = np.asarray(refine(y, a, n, **KW))
    assert np.abs(out - a).std() < 0.5 * np.abs(y - a).std()  # noise reduced
    assert out[:, :8].max() < 0.25 and out[:, 8:].min() > 0.6  # no mixing across the albedo edge
    shadow = np.where(np.arange(w)[None, :, None] < 8, 0.1, 0.5) * np.ones((h, w, 3), np.float32)
    flat = np.full((h, w, 3), 0.5, np.float32)
    got = np.asarray(refine(shadow, flat, n, **KW))
    np.testing.assert_allclose(got, shadow, rtol=1e-2)
    for k in (np.float32(1 / 16), np.float32(16.0)):
        np.testing.assert_allclose(np.asarray(refine(k * y, a, n, **KW)), k * out, rtol=1e-5)


def test_refine_leading_axes_and_errors():
    y, a, n = _images()
    y2, a2, n2 = _images(seed=3)
    batch = np.asarray(refine(np.stack([y, y2]), np.stack([a, a2]), np.stack([n, n2]), **KW))
    np.testing.assert_allclose(batch[1], np.asarray(refine(y2, a2, n2, **KW)), rtol=1e-6)
    for key in KW:
        for bad in (0.0, -1.0, np.inf, np.nan, True):
            with pytest.raises(FilterError, match=key):
                refine(y, a, n, **{**KW, key: bad})
    with pytest.raises(FilterError, match="albedo"):
        refine(y, a[:-1], n, **KW)
    with pytest.raises(FilterError, match="normal"):
        refine(y, a, None, **KW)
    with pytest.raises(FilterError, match="demc: config.refine_range"):
        check_refine_settings("demc: config.", 2.0, 0.0, 0.1, 0.3)
    with pytest.raises(JaxdenoiseError, match="refine_sigma"):
        demc.widths_of(demc.Config(refine_sigma=-1.0))
    with pytest.raises(JaxdenoiseError, match="refine_albedo"):
        rae.needs(rae.Config(refine_sigma=2.0, refine_albedo=0.0))


def test_demc_refines_between_the_exact_pixels_and_the_level_match():
    """``refine_sigma``: network, exact pixels, `refine_output`, the level match, exact pixels again
    (the composition by hand), in the exposure-scaled units; f(k x) = k f(x) holds."""
    cfg = demc.Config(widths=(4, 6, 8, 8, 8), fusion_width=4, keep_exact=True, exact_window=3, match_level=4.0,
                      match_max_gain=1.1, refine_sigma=1.5)
    r = np.random.default_rng(2)
    f = lambda *s: r.uniform(0, 1, (24, 20) + s).astype(np.float32)  # noqa: E731
    c = f(3) * 2
    c[:4, :4] = 5.0  # an exact (emitter-like) block
    b = Buffers(color=c, normal=f(3) * 2 - 1, position=f(3) * 5, albedo=f(3), albedo2=f(3), spp=1)
    p = demc.init(jax.random.PRNGKey(0), cfg)
    apply = jax.jit(demc.apply, static_argnums=2)  # one compile per config instead of op-by-op dispatch
    got = np.asarray(apply(p, b, cfg))
    net = apply(p, b, dataclasses.replace(cfg, keep_exact=False, match_level=0.0, refine_sigma=0.0))
    exact = exact_mask(c, None, 1, window=3)
    x = jnp.where(exact, c, net)
    scale = demc.exposure_scale(b, cfg)
    x = refine(x * scale, b.albedo, b.normal, sigma=1.5, range_sigma=cfg.refine_range, albedo_sigma=cfg.refine_albedo,
               normal_sigma=cfg.refine_normal) / scale
    x = demc.match_input_level(x, b, cfg)
    np.testing.assert_allclose(got, np.asarray(jnp.where(exact, c, x)), rtol=1e-5, atol=1e-6)
    assert np.all(got[1:3, 1:3] == 5.0)
    k = np.float32(8.0)
    np.testing.assert_allclose(np.asarray(apply(p, b.replace(color=k * c), cfg)), k * got, rtol=2e-4, atol=1e-6)


def test_rae_refines_each_frame_before_taa():
    """``refine_sigma`` in `rae.step`: the network's frame, exact pixels, `refine`, then the rest as
    before (no TAA, no match here: the refined frame is the output); the state is the network's."""
    cfg = rae.Config(widths=(4, 4, 4, 4, 4), bottleneck=4, keep_exact=True, exact_window=3, refine_sigma=1.5)
    r = np.random.default_rng(4)
    f = lambda *s: r.uniform(0, 1, (16, 12) + s).astype(np.float32)  # noqa: E731
    cam = np.eye(4, dtype=np.float32)
    b = Buffers(color=f(3) * 2, albedo=f(3), normal=f(3) * 2 - 1, position=f(3) * 5, roughness=f(1), spp=1,
                world_to_camera=cam)
    p = rae.init(jax.random.PRNGKey(0), cfg)
    step = jax.jit(rae.step, static_argnums=3)  # one compile per config instead of op-by-op dispatch
    s_on, y_on = step(p, rae.init_state(b, cfg), b, cfg)
    off = dataclasses.replace(cfg, refine_sigma=0.0)
    s_off, y_off = step(p, rae.init_state(b, off), b, off)
    scale = rae.exposure_scale(b, cfg)
    want = refine(y_off * scale, b.albedo, b.normal, sigma=1.5, range_sigma=cfg.refine_range,
                  albedo_sigma=cfg.refine_albedo, normal_sigma=cfg.refine_normal) / scale
    exact = exact_mask(b.color, None, 1, window=3)
    np.testing.assert_allclose(np.asarray(y_on), np.asarray(jnp.where(exact, b.color, want)), rtol=1e-5, atol=1e-6)
    for a, z in zip(jax.tree_util.tree_leaves(s_on), jax.tree_util.tree_leaves(s_off)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(z))
