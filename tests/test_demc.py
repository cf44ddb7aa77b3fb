"""DEMC (Yang et al. 2019): shapes and parameter counts, the Eq. 3 and bilinear initialisations,
BatchNorm train vs eval, any input size, gradients reaching every branch and the Eq. 5 loss (the
shipped weights: tests/test_golden.py)."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise import color, nn
from jaxdenoise.buffers import Buffers
from jaxdenoise.errors import JaxdenoiseError
from jaxdenoise.methods import demc, get
from jaxdenoise.pipeline import augment

SMALL = demc.Config(widths=(4, 6, 8, 8, 8), fusion_width=4)


def _frame(h, w, seed=0):
    r = np.random.default_rng(seed)
    f = lambda *s: r.uniform(0, 1, (h, w) + s).astype(np.float32)
    return Buffers(color=f(3) * 2, normal=f(3) * 2 - 1, position=f(3) * 5, albedo=f(3), albedo2=f(3), spp=4)


def _batch(n, size, seed=0):
    r = np.random.default_rng(seed)
    f = lambda *s: r.uniform(0, 1, (n, size, size) + s).astype(np.float32)
    b = {"color": f(3) * 2, "normal": f(3) * 2 - 1, "position": f(3) * 5, "albedo": f(3), "albedo2": f(3)}
    b["reference"] = (b["albedo"] * 0.8).astype(np.float32)
    return b


def test_needs_exactly_colour_and_the_four_features():
    """The paper's inputs; `demc` (``keep_exact``) may read the colour variance too, never requires it."""
    four = {"color", "normal", "position", "albedo", "albedo2"}
    assert get("demc-paper").needs() == four and get("demc").required() == four
    assert get("demc").needs() == four | {"color_var"} and get("demc").config.keep_exact
    assert not get("demc-paper").config.keep_exact


def test_keep_exact_pixels_keeps_the_input_where_the_samples_agreed():
    """`demc.keep_exact_pixels`: at >= 2 spp a pixel with zero variance in every channel and a lit
    colour keeps its input; a pixel with variance in one channel, a black one, a 1-spp frame, a frame
    without variance keep the network's output; a batch takes each frame's own rate."""
    c = np.full((4, 5, 3), 0.5, np.float32)
    v = np.full((4, 5, 3), 0.01, np.float32)
    v[1, 2] = 0.0  # exact, lit: kept
    v[2, 3] = [0.0, 0.0, 0.01]  # one channel varies: denoised
    v[3, 4], c[3, 4] = 0.0, 0.0  # exact but black (no sample hit anything lit): denoised
    out = np.full((4, 5, 3), 9.0, np.float32)
    got = np.asarray(demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=c, color_var=v, spp=4)))
    want = out.copy()
    want[1, 2] = c[1, 2]
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(demc.keep_exact_pixels(out, Buffers(color=c, color_var=v, spp=1)), out)
    np.testing.assert_array_equal(demc.keep_exact_pixels(out, Buffers(color=c, spp=4)), out)
    # a 1-spp frame cannot have a variance: not reported as a missing optional buffer there
    from jaxdenoise.inference import missing_optional
    assert missing_optional(get("demc"), Buffers(color=c, spp=1)) == []
    assert missing_optional(get("demc"), Buffers(color=c, spp=4)) == ["color_var"]
    batch = {"color": np.stack([c, c]), "color_var": np.stack([v, v]), "spp": np.asarray([1.0, 16.0])}
    got = np.asarray(demc.keep_exact_pixels(jnp.asarray(np.stack([out, out])), batch))
    np.testing.assert_array_equal(got[0], out)
    np.testing.assert_array_equal(got[1], want)


def test_keep_exact_pixels_window_rule_where_no_variance_tells():
    """``window``: in a frame without a variance to read (1 spp, or none written) a lit pixel whose
    window x window square holds its colour bit for bit keeps its input (the inner pixels of a uniform
    light); a frame of >= 2 spp with ``color_var`` keeps the variance rule alone; odd windows only."""
    rng = np.random.default_rng(0)
    c = rng.exponential(0.3, (9, 10, 3)).astype(np.float32)
    c[2:7, 3:8] = 12.0  # a 5x5 light: every sample on it returns its radiance
    out = np.full((9, 10, 3), 9.0, np.float32)
    light = np.zeros((9, 10), bool)
    light[2:7, 3:8] = True
    for window, inner in ((3, (slice(3, 6), slice(4, 7))), (5, (4, 5))):
        got = np.asarray(demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=c, spp=1), window))
        want = out.copy()
        want[inner] = 12.0
        np.testing.assert_array_equal(got, want)
    no_var = np.asarray(demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=c, spp=4), 3))
    assert np.sum(no_var[..., 0] == 12.0) == 9
    v = np.full_like(c, 0.01)
    with_var = np.asarray(demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=c, color_var=v, spp=4), 3))
    np.testing.assert_array_equal(with_var, out)  # the variance says every pixel is noisy
    np.testing.assert_array_equal(demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=c, spp=1)), out)
    for bad in (1, 4, -3):  # 1 keeps every lit pixel, an even square is off-centre
        with pytest.raises(JaxdenoiseError, match="exact_window"):
            demc.widths_of(demc.Config(exact_window=bad))
        with pytest.raises(JaxdenoiseError, match="window"):
            demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=c, spp=1), bad)
    inf = c.copy()
    inf[:3, :3] = np.inf  # a block of infinite pixels agrees with itself but is not kept
    got = np.asarray(demc.keep_exact_pixels(jnp.asarray(out), Buffers(color=inf, spp=1), 3))
    assert np.all(got[:3, :3] == 9.0)


def test_match_input_level_puts_the_output_at_the_input_level():
    """``match_level``: an output 10 % dark in red comes back within 2 % of the noisy input's level
    (the reference's on average), limited by ``match_max_gain``; f(k x) = k f(x); bad settings named."""
    rng = np.random.default_rng(1)
    truth = np.full((64, 64, 3), 0.3, np.float32)
    fr = Buffers(color=(truth * rng.gamma(4.0, 0.25, truth.shape)).astype(np.float32), spp=1)
    dark = truth * np.float32([0.9, 1.0, 1.0])
    cfg = demc.Config(match_level=16.0)
    got = np.asarray(demc.match_input_level(jnp.asarray(dark), fr, cfg))
    np.testing.assert_allclose(got[16:-16, 16:-16].mean((0, 1)) / 0.3, 1.0, atol=0.02)
    capped = np.asarray(demc.match_input_level(jnp.asarray(dark), fr, dataclasses.replace(cfg, match_max_gain=1.05)))
    assert float(np.max(capped[..., 0] / dark[..., 0])) <= 1.05 + 1e-6
    for k in (np.float32(8.0), np.float32(3.0), np.float32(1 / 16)):
        scaled = demc.match_input_level(jnp.asarray(k * dark), dataclasses.replace(fr, color=k * fr.color), cfg)
        np.testing.assert_allclose(np.asarray(scaled), k * got, rtol=1e-5)
    four = dataclasses.replace(fr, spp=4)  # by rate: one sample's factor 7 cuts a 4-spp frame at 4
    np.testing.assert_array_equal(
        np.asarray(demc.match_input_level(jnp.asarray(dark), four, dataclasses.replace(cfg, match_spike=7.0,
                                                                                          match_spike_by_rate=True))),
        np.asarray(demc.match_input_level(jnp.asarray(dark), four, dataclasses.replace(cfg, match_spike=4.0))))
    for bad in ({"match_level": -1.0}, {"match_spike": 0.0}, {"match_max_gain": 0.5}, {"match_level": np.inf},
                {"match_spike": 0.5, "match_spike_by_rate": True}):
        with pytest.raises(JaxdenoiseError, match="match_"):
            demc.widths_of(demc.Config(**bad))


# 1x1 and 7x5 under `slow` (19 s and 29 s of compilation, 26th session): the stability suite runs
# demc at 1x1 in the default run, and 33x64 keeps an odd size there
@pytest.mark.parametrize("h,w", [pytest.param(1, 1, marks=pytest.mark.slow), pytest.param(7, 5, marks=pytest.mark.slow),
                                 (33, 64), (32, 32)])
def test_any_size_gives_the_input_shape(h, w):
    p = demc.init(jax.random.PRNGKey(0), SMALL)
    y = demc.apply(p, _frame(h, w), SMALL)
    assert y.shape == (h, w, 3) and bool(jnp.all(jnp.isfinite(y)))


@pytest.mark.slow  # 15 s (SEMC's width search builds many networks)
def test_parameter_counts_and_semc_matches_demc():
    """The count `num_params` states equals the leaves of `init` (without the 24 norm values); the
    SEMC ablation is widened to DEMC's count within 1 % (Sec. 4.4, Fig. 4)."""
    for variant in demc.VARIANTS:
        cfg = dataclasses.replace(demc.Config(), variant=variant)
        p = demc.init(jax.random.PRNGKey(0), cfg)
        n = sum(int(np.prod(x.shape)) for k, v in p.items() if k != "norm" for x in jax.tree_util.tree_leaves(v))
        assert n == demc.num_params(cfg)
    full = demc.num_params(demc.Config())
    assert abs(demc.num_params(demc.Config(variant="semc")) - full) / full < 0.01
    assert demc.widths_of(demc.Config(variant="semc"))[0] > demc.Config().widths[0]
    assert 1.2e6 < full < 1.6e6  # the documented 1.39 M (docs/methods/demc.md)


def test_fresh_skip_fusion_passes_the_decoder_tensor_through():
    """Eq. 3: W = [I, 0, 0], b = 0, so ReLU(W [d; f; c] + b) = d for the (non-negative) decoder tensor."""
    p = demc.init(jax.random.PRNGKey(1), demc.Config())
    layers = demc._layers(demc.Config(), demc.widths_of(demc.Config()))
    r = np.random.default_rng(0)
    for i, c in enumerate(demc.Config().widths):
        d, f, e = (r.uniform(0, 1, (5, 6, c)).astype(np.float32) for _ in range(3))
        out = layers["fuse"][i][1](p["fuse"][str(i)], np.concatenate([d, f, e], -1))
        np.testing.assert_array_equal(np.asarray(out), d)


def test_decoder_deconvolution_starts_as_bilinear_upsampling():
    """The latent-to-level-4 deconvolution (equal widths) up-samples a ramp exactly away from the border."""
    cfg = demc.Config()
    p = demc.init(jax.random.PRNGKey(2), cfg)
    up = nn.ConvTranspose(cfg.widths[-1], 4, stride=2)[1]
    yy, xx = np.meshgrid(np.arange(6), np.arange(7), indexing="ij")
    ramp = np.repeat((2.0 * yy + 3.0 * xx + 1.0)[..., None], cfg.widths[-1], -1).astype(np.float32)
    out = np.asarray(up(p["up"]["4"]["0"], ramp))
    oy, ox = np.meshgrid((np.arange(12) + 0.5) / 2 - 0.5, (np.arange(14) + 0.5) / 2 - 0.5, indexing="ij")
    np.testing.assert_allclose(out[1:-1, 1:-1, 0], (2.0 * oy + 3.0 * ox + 1.0)[1:-1, 1:-1], atol=1e-4)


def test_batchnorm_train_and_eval_modes():
    """The loss (training mode) returns new running statistics for both BatchNorm layers; `apply`
    (inference) uses the stored ones, so updating them changes the output."""
    p = demc.init(jax.random.PRNGKey(0), SMALL)
    b = _batch(2, 32)
    _, aux = demc.loss(p, b, SMALL)
    ups = aux["updates"]["fusion"]
    assert sorted(ups) == ["3", "6"] and all(set(u) == {"mean", "var"} for u in ups.values())
    assert not np.allclose(np.asarray(ups["3"]["mean"]), 0.0)
    # inference mode uses the stored statistics (the fresh Eq. 3 fusion hides the detail map from the
    # output at the start, so the sub-network is checked directly)
    fusion = demc._layers(SMALL, demc.widths_of(SMALL))["fusion"][1]
    _, x_feat = demc.inputs(p, _frame(32, 32), SMALL)
    before = np.asarray(fusion(p["fusion"], x_feat, train=False))
    after = np.asarray(fusion(nn.merge_updates(p, aux["updates"])["fusion"], x_feat, train=False))
    assert not np.allclose(before, after, rtol=1e-3, atol=0)
    trained, _ = fusion(p["fusion"], x_feat, train=True)
    assert not np.allclose(before, np.asarray(trained), rtol=1e-3, atol=0)


@pytest.mark.slow  # 23 s (a full training step's gradient)
def test_every_branch_receives_gradient():
    """No dead branch: after one gradient step (the fresh Eq. 3 fusion has zero encoder blocks, so at
    the very start only its weights see the encoders), the fusion sub-network and both encoders get a
    non-zero gradient."""
    p = demc.init(jax.random.PRNGKey(0), SMALL)
    b = _batch(2, 32)
    g = jax.grad(lambda q: demc.loss(q, b, SMALL)[0])(p)
    p = jax.tree_util.tree_map(lambda a, da: a - 1e-2 * jnp.sign(da), p, g)
    g = jax.grad(lambda q: demc.loss(q, b, SMALL)[0])(p)
    for branch in ("fusion", "enc_c", "enc_f", "latent", "up", "fuse", "out"):
        total = sum(float(jnp.sum(jnp.abs(x))) for x in jax.tree_util.tree_leaves(g[branch]))
        assert total > 0, branch
    assert all(float(jnp.sum(jnp.abs(x))) == 0 for x in jax.tree_util.tree_leaves(g["norm"]))


def test_loss_is_eq5_relmse_in_hdr():
    """Without BatchNorm (DEMC-noSN) training and inference outputs agree, so with ``level_weight=0``
    the loss must equal mean((y - r)^2 / (r^2 + 1e-3)) of `apply`'s HDR output, computed here in
    NumPy; the default adds 4 times the same term on 8x8 block means."""
    cfg = dataclasses.replace(SMALL, variant="nosn", level_weight=0.0)
    p = demc.init(jax.random.PRNGKey(3), cfg)
    b = _batch(2, 32)
    y = np.stack([np.asarray(demc.apply(p, Buffers(**{k: b[k][i] for k in b if k != "reference"}), cfg))
                  for i in range(2)]).astype(np.float64)
    r = b["reference"].astype(np.float64)
    rel = lambda a, c: np.mean((a - c) ** 2 / (c ** 2 + 1e-3))  # noqa: E731
    np.testing.assert_allclose(float(demc.loss(p, b, cfg)[0]), rel(y, r), rtol=1e-4)
    pool = lambda a: a.reshape(2, 4, 8, 4, 8, 3).mean((2, 4))  # noqa: E731
    default = dataclasses.replace(cfg, level_weight=demc.Config().level_weight)
    np.testing.assert_allclose(float(demc.loss(p, b, default)[0]), rel(y, r) + 4.0 * rel(pool(y), pool(r)), rtol=1e-4)


def test_inputs_eq4_and_feature_normalisation():
    cfg = demc.Config(exposure="none")
    p = demc.init(jax.random.PRNGKey(0), cfg)
    p["norm"] = {"mean": jnp.arange(12, dtype=jnp.float32), "std": jnp.full((12,), 2.0)}
    fr = _frame(8, 8)
    xc, xf = demc.inputs(p, fr, cfg)
    np.testing.assert_allclose(np.asarray(xc), fr.color ** (1 / 2.2), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(xf[..., :3]), (fr.normal - np.arange(3)) / 2, rtol=1e-5)
    pos = fr.position
    np.testing.assert_allclose(np.asarray(xf[..., 3:6]), (pos - pos.mean((0, 1))) / pos.std((0, 1)), rtol=1e-3,
                               atol=1e-4)
    g = dataclasses.replace(cfg, position_norm="global")
    np.testing.assert_allclose(np.asarray(demc.inputs(p, fr, g)[1][..., 3:6]), (pos - np.arange(3, 6)) / 2, rtol=1e-5)
    # negative and non-finite radiance never reach the power: clamped to 0
    bad = dataclasses.replace(fr, color=np.full((8, 8, 3), -1.0, np.float32))
    assert float(jnp.max(demc.inputs(p, bad, cfg)[0])) == 0.0


@pytest.mark.parametrize("variant", ["demc", "nosn"])
def test_exposure_frame_scales_the_output_with_the_input(variant):
    """``exposure = "frame"``: f(k x) = k f(x) for k in 1/16..16 (the colour is scaled to a fixed level
    by a statistic of degree 1, and the output scaled back); stated tolerance 1e-4 relative to the
    output's largest value (float32 rounding). A batch without carried statistics gets one level per
    item, the same as each frame alone."""
    cfg = dataclasses.replace(SMALL, variant=variant, exposure="frame")
    p = demc.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(40, 24, seed=5)
    base = np.asarray(demc.apply(p, fr, cfg))
    for k in (1 / 16, 1 / 4, 1.0, 3.0, 16.0):
        out = np.asarray(demc.apply(p, dataclasses.replace(fr, color=fr.color * np.float32(k)), cfg))
        assert np.max(np.abs(out - k * base)) <= 1e-4 * k * np.max(np.abs(base))
    # the level: per frame, degree 1, clipped at the 99.9 % luminance quantile (one firefly does not set it)
    levels = np.asarray(color.exposure_level(np.stack([fr.color, 4 * fr.color])))[:, 0]
    assert np.shape(color.exposure_level(fr.color)) == (1,)  # a per-frame statistic is a small vector
    np.testing.assert_allclose(levels[1], 4 * levels[0], rtol=1e-6)
    hot = fr.color.copy()
    hot[0, 0] = 1e6
    np.testing.assert_allclose(float(color.exposure_level(hot)[0]), levels[0], rtol=0.01)
    assert float(color.exposure_level(np.zeros((8, 8, 3), np.float32))[0]) == 0.0
    assert float(np.max(np.asarray(demc.apply(p, dataclasses.replace(fr, color=np.zeros_like(fr.color)), cfg)))) < 1e3
    b = _batch(2, 32)
    both = np.asarray(demc.apply(p, Buffers(**{k: b[k] for k in b if k != "reference"}), cfg))
    one = np.asarray(demc.apply(p, Buffers(**{k: b[k][1] for k in b if k != "reference"}), cfg))
    np.testing.assert_allclose(both[1], one, rtol=1e-4, atol=1e-5)
    # "none" keeps the paper's inputs (the shipped demc-paper weights were trained that way)
    none = dataclasses.replace(cfg, exposure="none")
    np.testing.assert_allclose(np.asarray(demc.inputs(p, fr, none)[0]), fr.color ** (1 / 2.2), rtol=1e-5)


def test_color_mean_is_the_clipped_level_per_channel_and_follows_the_modulation():
    """`color_mean`'s luminance is the clipped mean luminance (`exposure_level`: pixels above the
    99.9 % luminance quantile scaled down to it, hue kept); a crop drawn with colour modulation m
    carries m times its frame's value, which is the modulated frame's own wherever no pixel is
    clipped (rtol 1e-5), and the exposure scale uses it."""
    fr = _frame(40, 24, seed=7)
    c = fr.color.copy()
    c[3, 4] = (50.0, 5.0, 1.0)
    lum = 0.2126 * c[..., 0] + 0.7152 * c[..., 1] + 0.0722 * c[..., 2]
    clip = np.sort(lum.ravel())[int(np.floor(0.999 * (lum.size - 1)))]
    np.testing.assert_allclose(float(color.exposure_level(c)[0]), np.minimum(lum, clip).mean(), rtol=1e-5)
    cm = np.asarray(color.color_mean(c))
    assert cm.shape == (3,) and cm[0] < c[..., 0].mean()  # the hot pixel clipped, its hue kept
    frame = {"color": fr.color, "reference": fr.color}
    item = {**frame, "stat.color_mean": np.asarray(color.color_mean(fr.color))}
    out = augment(item, np.random.default_rng(3), rotate=False, flip=False)
    m = out["color"][0, 0] / fr.color[0, 0]
    np.testing.assert_allclose(out["stat.color_mean"], np.asarray(color.color_mean(fr.color * m)), rtol=1e-5)
    cfg = dataclasses.replace(SMALL, exposure="frame")
    np.testing.assert_allclose(np.asarray(demc.exposure_scale(out, cfg)).ravel(),
                               np.asarray(demc.exposure_scale({"color": fr.color * m}, cfg)).ravel(), rtol=1e-5)


def test_skip_init_readings_of_eq3():
    """Eq. 3's readings: "decoder" passes the upsampled decoder block through ([I, 0, 0]), "all" sums
    the decoder and both encoder blocks ([I, I, I]); zero bias either way; only the init differs."""
    for reading, blocks in (("decoder", (1, 0, 0)), ("all", (1, 1, 1))):
        cfg = dataclasses.replace(SMALL, skip_init=reading)
        p = demc.init(jax.random.PRNGKey(0), cfg)
        for lvl, fuse in p["fuse"].items():
            w, b = np.asarray(fuse["0"]["w"])[0, 0], np.asarray(fuse["0"]["b"])
            c = w.shape[1]
            for k, v in enumerate(blocks):
                np.testing.assert_array_equal(w[k * c:(k + 1) * c], v * np.eye(c))
            assert not b.any()
    assert demc.num_params(dataclasses.replace(SMALL, skip_init="all")) == demc.num_params(SMALL)


def test_loss_scale_and_level_term_move_the_optimum_toward_the_mean_reference():
    """Two references for one output (an input that admits both): Eq. 5's gradient vanishes below
    their mean (dark references weigh more); with ``loss_scale = "output"`` it vanishes at the mean;
    the level term (block means) pulls Eq. 5's optimum toward the block's mean (hand-computed)."""
    refs = jnp.asarray([0.2, 1.0])

    def grad(y, scale):
        cfg = dataclasses.replace(SMALL, loss_scale=scale, level_weight=0.0)
        return float(jax.grad(lambda v: demc.relative_loss(jnp.full(2, v), refs, cfg))(y))

    assert abs(grad(0.6, "output")) < 1e-6
    assert grad(0.6, "reference") > 0.1  # the minimiser is darker than the mean
    # the level term: references alternating 0.2 / 1.0 in 8x8 blocks (each block's mean is 0.6); the
    # uniform output that minimises the loss moves from Eq. 5's 0.23 to 0.47 with level_weight 8
    refs8 = jnp.asarray(np.where((np.add.outer(np.arange(8), np.arange(8)) % 2)[..., None], 1.0, 0.2)
                        * np.ones((1, 8, 8, 3)), jnp.float32)
    vs = np.linspace(0.2, 1.0, 801)

    def best(cfg):
        return vs[int(np.argmin([float(demc.relative_loss(jnp.full_like(refs8, v), refs8, cfg)) for v in vs]))]

    plain, level = best(dataclasses.replace(SMALL, level_weight=0.0)), best(dataclasses.replace(SMALL, level_weight=8.0))
    assert plain == pytest.approx(0.2315, abs=2e-3) and level == pytest.approx(0.4658, abs=2e-3)
    # an input that admits two whole crops (0.2 everywhere or 1.0 everywhere): the block means are as
    # uncertain as the pixels, the reference-scaled level term keeps Eq. 5's 0.2315, the output-scaled
    # one (level_weight 8) moves the gradient's zero to 0.4962 (hand-solved: 2 (v - 0.2) / 0.041 +
    # 2 (v - 1) / 1.001 + 8 (4 v - 2.4) / (v^2 + 0.001) = 0 over the two crops)
    crops = jnp.stack([jnp.full((8, 8, 3), 0.2), jnp.full((8, 8, 3), 1.0)])

    def zero(scale):
        cfg = dataclasses.replace(SMALL, level_weight=8.0, level_scale=scale)
        g = jax.grad(lambda v: demc.relative_loss(jnp.full_like(crops, v), crops, cfg))
        lo, hi = 0.2, 1.0
        for _ in range(40):
            lo, hi = ((lo + hi) / 2, hi) if float(g((lo + hi) / 2)) < 0 else (lo, (lo + hi) / 2)
        return lo

    assert zero("reference") == pytest.approx(0.2315, abs=1e-3) and zero("output") == pytest.approx(0.4962, abs=1e-3)
    with pytest.raises(ValueError, match="level_scale"):
        demc.num_params(demc.Config(level_scale="block"))
    with pytest.raises(ValueError, match="level_weight"):
        demc.num_params(demc.Config(level_weight=-1.0))
    with pytest.raises(ValueError, match="loss_scale"):
        demc.num_params(demc.Config(loss_scale="ref"))
    with pytest.raises(ValueError, match="skip_init"):
        demc.num_params(demc.Config(skip_init="III"))


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="variant"):
        demc.num_params(demc.Config(variant="triple"))
    with pytest.raises(ValueError, match="exposure"):
        demc.num_params(demc.Config(exposure="auto"))
    with pytest.raises(ValueError, match="five positive"):
        demc.num_params(demc.Config(widths=(4, 4)))
