"""LBF (Kalantari, Bako, Sen 2015): secondary features against NumPy, gradients of Eq. 8 through the
filter against finite differences, a few RPROP steps lower the loss, save/reload, needs, errors.

Small configs (no prefilter, radius 2-3) keep the compiles few and fast; the full default pipeline
runs in the stability suite (tests/stability) through the registry.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise import checkpoint
from jaxdenoise.buffers import Buffers, BuffersError
from jaxdenoise.methods import get, lbf
from jaxdenoise.methods.lbf_features import feature_names, num_features, secondary_features
from jaxdenoise.solvers import optim

from conftest import synthetic_frame

FEATS = lbf.PAPER_FEATURES
SMALL = lbf.Config(radius=2, prefilter=False, spike_removal=False)
# Two features keep the compiles of the gradient, training and sequence tests short.
SMALL2 = dataclasses.replace(SMALL, features=("normal", "albedo"))


# -- NumPy reference of Sec. 3.3 --------------------------------------------------------------------
def _np_block(a: np.ndarray, y: int, x: int, r: int) -> np.ndarray:
    """(2r+1)^2 x C block around (y, x) with edge replication."""
    h, w = a.shape[:2]
    ys = np.clip(np.arange(y - r, y + r + 1), 0, h - 1)
    xs = np.clip(np.arange(x - r, x + r + 1), 0, w - 1)
    return a[ys][:, xs].reshape(-1, a.shape[-1])


def _np_features(feats: dict, vars_: dict, spp: float) -> np.ndarray:
    names = list(FEATS)
    h, w = feats[names[0]].shape[:2]
    out = np.zeros((h, w, 7 * len(names) + 1))
    k = len(names)
    sx = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], float)
    sy = sx.T
    for y in range(h):
        for x in range(w):
            for i, n in enumerate(names):
                f = feats[n].astype(np.float64)
                out[y, x, i] = f[y, x].mean()
                out[y, x, k + i] = np.sqrt(vars_[n][y, x].mean() * spp)
                b7 = _np_block(f, y, x, 3)
                out[y, x, 2 * k + i] = b7.mean(0).mean()
                out[y, x, 3 * k + i] = b7.std(0).mean()
                b3 = _np_block(f, y, x, 1).reshape(3, 3, -1)
                gx = np.einsum("ab,abc->c", sx, b3)
                gy = np.einsum("ab,abc->c", sy, b3)
                out[y, x, 4 * k + i] = np.sqrt(gx ** 2 + gy ** 2).mean()
                b3f = b3.reshape(9, -1)
                out[y, x, 5 * k + i] = np.abs(b3f - b3f.mean(0)).mean(0).mean()
                out[y, x, 6 * k + i] = np.median(np.abs(b3f - np.median(b3f, 0)), 0).mean()
            out[y, x, -1] = 1.0 / spp
    return out


def test_secondary_features_match_numpy():
    b = synthetic_frame(6, 5, seed=1, spp=8)
    feats = {n: np.asarray(getattr(b, n)) for n in FEATS}
    vars_ = {n: np.asarray(getattr(b, f"{n}_var")) * 0.01 for n in FEATS}
    got = np.asarray(secondary_features(feats, vars_, 8.0, features=FEATS))
    want = _np_features(feats, vars_, 8.0)
    assert got.shape == (6, 5, 36) and len(feature_names(FEATS)) == 36 == num_features(FEATS)  # exact
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=2e-5)


def test_secondary_features_constant_frame():
    """A constant feature has zero block spread, gradient, deviation and MAD (1e-6 absolute)."""
    f = {n: np.full((4, 4, 3 if n != "visibility" else 1), 0.3, np.float32) for n in FEATS}
    v = {n: np.zeros((4, 4, 1), np.float32) for n in FEATS}
    x = np.asarray(secondary_features(f, v, 4.0, features=FEATS))
    k = len(FEATS)
    np.testing.assert_allclose(x[..., :k], 0.3, atol=1e-6)
    np.testing.assert_allclose(x[..., 2 * k:3 * k], 0.3, atol=1e-6)
    np.testing.assert_allclose(x[..., 3 * k:7 * k], 0.0, atol=1e-6)  # the 1e-20 sqrt floor is 1e-10
    np.testing.assert_allclose(x[..., -1], 0.25, atol=0)


# -- network and filter ------------------------------------------------------------------------------
_prepare_jit = jax.jit(lbf.prepare, static_argnums=1)


def _crops(n: int = 2, h: int = 7, w: int = 6, seed: int = 0, cfg: lbf.Config = SMALL2) -> dict:
    """A batch in the format of `lbf.batch`: smooth references, noisy colours, per-crop spp."""
    rng = np.random.default_rng(seed)
    fs = cfg.features
    xs, cols, cvars, refs, spps, guides, gvars = [], [], [], [], [], {f: [] for f in fs}, {f: [] for f in fs}
    for i in range(n):
        spp = float(4 * 2 ** i)
        b = synthetic_frame(h, w, seed=seed + i, spp=int(spp))
        yy, xx = np.mgrid[0:h, 0:w]
        ref = np.stack([0.2 + 0.05 * xx, 0.3 + 0.03 * yy, 0.4 + 0.0 * xx], -1).astype(np.float32)
        noise = rng.normal(size=ref.shape).astype(np.float32) * ref / np.sqrt(spp)
        b = b.replace(color=np.maximum(ref + noise, 0), color_var=(ref ** 2 / spp).astype(np.float32))
        prep = _prepare_jit(b, cfg)
        xs.append(prep["x"]), cols.append(prep["color"]), cvars.append(prep["color_var"])
        refs.append(ref), spps.append(np.float32(spp))
        for f in fs:
            guides[f].append(prep["guides"][f]), gvars[f].append(prep["guide_vars"][f])
    return {"x": np.stack(xs), "color": np.stack(cols), "color_var": np.stack(cvars), "reference": np.stack(refs),
            "spp": np.stack(spps), "guides": {f: np.stack(v) for f, v in guides.items()},
            "guide_vars": {f: np.stack(v) for f, v in gvars.items()}}


@pytest.mark.parametrize("filt", ["bilateral", "nlm"])
def test_loss_gradient_matches_finite_differences(filt):
    """d(Eq. 8)/d(weights) through the filter (float64): directional derivative vs central
    difference along a random direction, relative tolerance 1e-5."""
    cfg = dataclasses.replace(SMALL2, filter=filt, patch_radius=1)
    batch = _crops(2, 7, 6, cfg=cfg)
    with jax.enable_x64(True):
        params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), lbf.init(jax.random.PRNGKey(0), cfg))
        b64 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), batch)
        f = jax.jit(lambda p: lbf.loss(p, b64, cfg))
        g = jax.jit(jax.grad(lambda p: lbf.loss(p, b64, cfg)))(params)
        leaves, tdef = jax.tree_util.tree_flatten(params["net"])
        keys = jax.random.split(jax.random.PRNGKey(1), len(leaves))
        v = tdef.unflatten([jax.random.normal(k, l.shape, jnp.float64) for k, l in zip(keys, leaves)])
        eps = 1e-5
        shift = lambda s: {**params, "net": jax.tree_util.tree_map(lambda p, d: p + s * eps * d, params["net"], v)}
        fd = (float(f(shift(1.0))) - float(f(shift(-1.0)))) / (2 * eps)
        an = sum(float(jnp.vdot(a, d)) for a, d in zip(jax.tree_util.tree_leaves(g["net"]), jax.tree_util.tree_leaves(v)))
        assert abs(an) > 1e-8  # the check is not vacuous
        np.testing.assert_allclose(an, fd, rtol=1e-5)
        # the normalization statistics are not trained (Sec. 4.2): their gradient is exactly 0
        assert all(float(jnp.max(jnp.abs(a))) == 0.0 for a in jax.tree_util.tree_leaves(g["norm"]))


def test_rprop_steps_lower_the_loss():
    """Ten RPROP steps (Sec. 4.2) on one batch lower Eq. 8 by at least 5 % (the filter-MLP family's
    learning check in the default run: 6 s)."""
    cfg = SMALL2
    batch = _crops(3, 8, 8, seed=3)
    params = lbf.init(jax.random.PRNGKey(2), cfg)
    opt_init, opt_update = optim.rprop(0.02)
    state = opt_init(params)

    @jax.jit
    def step(p, s):
        val, g = jax.value_and_grad(lambda q: lbf.loss(q, batch, cfg))(p)
        p, s = opt_update(g, s, p)
        return p, s, val

    first = None
    for _ in range(10):
        params, state, val = step(params, state)
        first = float(val) if first is None else first
    last = float(lbf.loss(params, batch, cfg))
    assert np.isfinite(last) and last < 0.95 * first, (first, last)


def test_saved_and_reloaded_model_gives_the_same_image(tmp_path):
    cfg = dataclasses.replace(SMALL, spike_removal=True)
    params = lbf.init(jax.random.PRNGKey(4), cfg)
    params["norm"] = {"mean": jnp.linspace(0, 1, 36), "std": jnp.linspace(1, 2, 36)}
    checkpoint.save(tmp_path, params, cfg)
    loaded, meta = checkpoint.load(tmp_path)
    assert checkpoint.config_from_dict(lbf.Config, meta["config"]) == cfg  # exact
    b = synthetic_frame(7, 6, seed=5, spp=4)
    fn = jax.jit(lambda p, bb: lbf.apply(p, bb, cfg))
    a = np.asarray(fn(params, b))
    c = np.asarray(fn(jax.tree_util.tree_map(jnp.asarray, loaded), b))
    assert a.shape == (7, 6, 3) and np.all(np.isfinite(a))
    np.testing.assert_array_equal(a, c)  # bit-identical


def _static_noisy_frames(n: int = 3) -> list:
    frames = [synthetic_frame(5, 4, seed=0, spp=4) for _ in range(n)]
    rng = np.random.default_rng(0)
    return [f.replace(color=np.asarray(frames[0].color) + 0.1 * rng.normal(size=(5, 4, 3)).astype(np.float32))
            for f in frames]


def test_leading_axis_is_a_batch_of_independent_frames():
    """(B, H, W, C) input = B frames filtered on their own (tolerance 1e-6: the same arithmetic in a
    lax.map body), never blended as a video; a scalar spp applies to every frame."""
    cfg = dataclasses.replace(SMALL, radius=1, features=("normal",))
    params = lbf.init(jax.random.PRNGKey(6), cfg)
    frames = _static_noisy_frames()
    per_frame = np.stack([np.asarray(lbf.apply(params, f, cfg)) for f in frames])
    batch = Buffers(**{k: np.stack([np.asarray(getattr(f, k)) for f in frames]) for k in frames[0].to_dict()
                       if k != "spp"}, spp=np.float32(4))
    np.testing.assert_allclose(np.asarray(lbf.apply(params, batch, cfg)), per_frame, atol=1e-6)
    per_spp = batch.replace(spp=np.full((3,), 4, np.float32))
    np.testing.assert_allclose(np.asarray(lbf.apply(params, per_spp, cfg)), per_frame, atol=1e-6)


def test_sequence_driver_uses_the_spatiotemporal_window():
    """Through the sequence driver: with temporal_radius=0 the result equals per-frame apply (1e-6);
    with the window (Sec. 5) frame t equals `apply_window` over frames max(0, t-r)..min(T-1, t+r)
    computed by hand (1e-6), and the neighbours change the result."""
    from jaxdenoise.methods import Method
    from jaxdenoise.sequence import run_all

    cfg = dataclasses.replace(SMALL, radius=1, features=("normal",), temporal_radius=1)
    params = lbf.init(jax.random.PRNGKey(6), cfg)
    frames = _static_noisy_frames(4)
    m = Method("lbf", lbf, cfg)
    assert m.temporal == "windowed" and lbf.window(cfg) == (1, 1)
    per_frame = np.stack([np.asarray(lbf.apply(params, f, cfg)) for f in frames])
    m0 = Method("lbf", lbf, dataclasses.replace(cfg, temporal_radius=0))
    assert m0.temporal == "frame"
    np.testing.assert_allclose(run_all(m0, params, frames), per_frame, atol=1e-6)
    seq = run_all(m, params, frames)
    assert seq.shape == (4, 5, 4, 3) and np.all(np.isfinite(seq))  # exact shape
    preps = [lbf.prepare_frame(params, f, cfg) for f in frames]
    for t in range(4):
        lo, hi = max(0, t - 1), min(3, t + 1)
        want = np.asarray(lbf.apply_window(params, tuple(preps[lo:hi + 1]), t - lo, cfg))
        np.testing.assert_allclose(seq[t], want, atol=1e-6)
    assert not np.allclose(seq, per_frame, atol=1e-4)  # the neighbour frames take part


def test_needs_leaves_out_unused_features_and_registry():
    cfg = lbf.Config(features=("normal", "albedo"))
    assert lbf.needs(cfg) == {"color", "color_var", "normal", "normal_var", "albedo", "albedo_var", "spp"}  # exact
    assert "depth" not in lbf.needs(lbf.Config()) and "visibility" in lbf.needs(lbf.Config())
    assert get("lbf").config.filter == "bilateral" and get("lbf-nlm").config.filter == "nlm"
    p = lbf.init(jax.random.PRNGKey(0), cfg)
    assert p["net"]["0"]["w"].shape == (15, 10) and p["net"]["2"]["w"].shape == (10, 3)  # 7K+1 -> 10 -> K+1


def test_bad_inputs_raise_clear_errors():
    b = synthetic_frame(4, 4, fields=("color", "color_var", "normal", "normal_var"))
    with pytest.raises(BuffersError, match="position"):
        lbf.apply(lbf.init(jax.random.PRNGKey(0), SMALL), b, SMALL)
    with pytest.raises(ValueError, match="config.filter"):
        lbf.init(jax.random.PRNGKey(0), lbf.Config(filter="gauss"))
    with pytest.raises(ValueError, match="drop_categories"):
        lbf.init(jax.random.PRNGKey(0), lbf.Config(drop_categories=("colour",)))
