"""RAE (Chaitanya et al. 2017) and the view-space inputs it needs: shapes and the convolution count,
`step` over a sequence against the training-time pass, the recurrent state carrying information,
any input size, the loss terms against hand computations and HFEN's LoG against NumPy, the camera
metadata through EXR, and view-space vectors turning with the image under augmentation."""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise import color, pipeline, view
from jaxdenoise.buffers import Buffers, BuffersError
from jaxdenoise.methods import get, rae

# the paper's input (exposure as given, no rate channel) on a tiny network
TINY = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="none", rate_input=False)


def _camera(yaw=0.3, dist=4.0):
    """A column-vector world_to_camera: rotation about y, then a translation along the view axis."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4, dtype=np.float32)
    m[:3, :3] = [[c, 0, -s], [0, 1, 0], [s, 0, c]]
    m[2, 3] = dist
    return m


def _frame(h, w, seed=0, camera=None):
    r = np.random.default_rng(seed)
    n = r.normal(size=(h, w, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return Buffers(color=r.uniform(0, 2, (h, w, 3)).astype(np.float32), albedo=r.uniform(0.1, 1, (h, w, 3)).astype(np.float32),
                   normal=n, position=r.normal(size=(h, w, 3)).astype(np.float32),
                   roughness=r.uniform(size=(h, w, 1)).astype(np.float32), spp=1,
                   world_to_camera=_camera() if camera is None else camera)


def test_needs_and_the_paper_network():
    paper = get("rae-paper")
    assert paper.needs() == {"color", "albedo", "normal", "position", "roughness", "world_to_camera"}
    # the rate channel, exact pixels (issue 34), the camera TAA reprojects through (Sec. 5.4)
    assert get("rae").needs() == paper.needs() | {"spp", "color_var", "world_to_ndc"}
    assert get("rae").temporal == "causal" and paper.temporal == "causal"
    p = rae.init(jax.random.PRNGKey(0), paper.config)
    kernels = [x for x in jax.tree_util.tree_leaves(p) if x.ndim == 4]
    assert len(kernels) == 36  # 7 encoder + 10 decoder + 1 output + 6 x 3 recurrent (Sec. 4.1-4.2)
    assert rae.num_params(paper.config) == 2126281  # docs/methods/rae.md: the paper's 3.2 M and why
    assert rae.num_params(rae.Config()) == 2126281 + 9 * 32  # one more input channel
    assert p["enc"]["0"]["w"].shape == (3, 3, 7, 32) and p["rb"]["5"]["in"]["w"].shape[-1] == 101


def test_missing_camera_is_a_clear_error():
    from jaxdenoise.api import denoise

    b = _frame(8, 8).replace(world_to_camera=None)
    with pytest.raises(BuffersError, match="worldToCamera"):
        denoise(b, method="rae", params=rae.init(jax.random.PRNGKey(0), rae.Config()))


# 1x1 and 7x5 under `slow` (13 s and 26 s of compilation, 26th session): the stability suite runs
# rae at 1x1 in the default run, and 33x40 keeps an odd size there
@pytest.mark.parametrize("h,w", [pytest.param(1, 1, marks=pytest.mark.slow), pytest.param(7, 5, marks=pytest.mark.slow),
                                 (33, 40)])
def test_any_size(h, w):
    p = rae.init(jax.random.PRNGKey(0), TINY)
    b = _frame(h, w)
    y = rae.apply(p, b, TINY)
    assert y.shape == (h, w, 3) and bool(jnp.all(jnp.isfinite(y))) and float(jnp.min(y)) >= 0


def test_albedo_above_one_modulates_as_one():
    """data_gen's albedo (``eval_diffuse_reflectance``) exceeds 1 on glossy conductors; an export
    stores [0, 1]: the network sees, and multiplies back, the clipped value (exact)."""
    p = rae.init(jax.random.PRNGKey(0), TINY)
    b = _frame(9, 7, seed=3)
    a = np.asarray(b.albedo).copy()
    a[2:5, 1:4] = [1.0, 1.0, 1.0]
    over = a.copy()
    over[2:5, 1:4] = [1.7, 1.4, 1.2]
    np.testing.assert_array_equal(rae.apply(p, b.replace(albedo=over), TINY), rae.apply(p, b.replace(albedo=a), TINY))


def test_untextured_pixels_are_not_demodulated():
    """An albedo of 0 (a visible light, the background, a black material) (de)modulates as 1: the
    network's colour input there is ``(colour / (1 + eps))^0.2``, not ``(colour / eps)^0.2``; an
    albedo just above half an 8-bit step is still divided out."""
    b = _frame(6, 5, seed=4)
    a = np.asarray(b.albedo).copy()
    a[1:3, 2:4] = 0.0
    a[4, 0] = [0.0, 0.003, 0.0]
    x = np.asarray(rae.inputs(b.replace(albedo=a), TINY))
    c = np.asarray(b.color)
    eps = color.ALBEDO_EPS_DEFAULT
    np.testing.assert_allclose(x[1:3, 2:4, :3], (c[1:3, 2:4] / (1 + eps)) ** 0.2, rtol=1e-5)
    np.testing.assert_allclose(x[4, 0, :3], (c[4, 0] / (a[4, 0] + eps)) ** 0.2, rtol=1e-5)
    ones = a.copy()
    ones[1:3, 2:4] = 1.0
    y = jnp.asarray(x[..., :3])  # any network output: remodulation multiplies back what divided
    np.testing.assert_array_equal(rae._output(y, a, 1.0, TINY), rae._output(y, ones, 1.0, TINY))


def test_step_over_a_sequence_equals_the_training_pass():
    """Stepping frame by frame through the causal surface gives the training-time unrolled pass's
    predictions (clamped at 0 as `step` returns them) within 1e-5 relative."""
    p = rae.init(jax.random.PRNGKey(2), TINY)
    frames = [_frame(20, 24, seed=s) for s in range(3)]
    state = rae.init_state(frames[0], TINY)
    stepped = []
    for f in frames:
        state, y = rae.step(p, state, f, TINY)
        stepped.append(np.asarray(y))
    x = jnp.stack([rae.inputs(f, TINY) for f in frames])[None]
    alb = jnp.stack([f.albedo for f in frames])[None]
    trained = np.maximum(np.asarray(rae.run_sequence(p, x, alb, TINY))[0], 0)
    np.testing.assert_allclose(np.stack(stepped), trained, rtol=1e-5, atol=1e-6)


def test_the_state_carries_information():
    """The second frame differs from the same frame run from a zero state; with the recurrent half
    of every block's first hidden conv zeroed, it does not."""
    p = rae.init(jax.random.PRNGKey(3), TINY)
    f0, f1 = _frame(16, 16, seed=0), _frame(16, 16, seed=1)
    state, _ = rae.step(p, rae.init_state(f0, TINY), f0, TINY)
    second = np.asarray(rae.step(p, state, f1, TINY)[1])
    fresh = np.asarray(rae.apply(p, f1, TINY))
    assert not np.allclose(second, fresh, rtol=1e-4, atol=0)
    cut = jax.tree_util.tree_map(lambda a: a, p)
    for k, blk in cut["rb"].items():
        c = blk["h1"]["w"].shape[2] // 2
        blk["h1"]["w"] = blk["h1"]["w"].at[:, :, c:, :].set(0.0)
    state, _ = rae.step(cut, rae.init_state(f0, TINY), f0, TINY)
    np.testing.assert_allclose(np.asarray(rae.step(cut, state, f1, TINY)[1]), np.asarray(rae.apply(cut, f1, TINY)),
                               rtol=1e-6, atol=1e-7)


def test_log_kernel_against_numpy_and_hfen_on_a_tiny_image():
    k = rae.log_kernel(1.5)
    assert k.shape == (11, 11) and abs(float(k.sum())) < 1e-6
    r = np.arange(-5, 6)
    yy, xx = np.meshgrid(r, r, indexing="ij")
    q = (xx ** 2 + yy ** 2) / (2 * 1.5 ** 2)
    raw = -(1 / (np.pi * 1.5 ** 4)) * (1 - q) * np.exp(-q)
    np.testing.assert_allclose(k, raw - raw.mean(), atol=1e-7)
    img = np.random.default_rng(0).uniform(size=(1, 1, 6, 7, 3)).astype(np.float32)
    got = np.asarray(rae._hfen(jnp.asarray(img), 1.5))[0, 0]
    pad = np.pad(img[0, 0], ((5, 5), (5, 5), (0, 0)))
    want = np.zeros_like(img[0, 0])
    for i in range(6):
        for j in range(7):
            want[i, j] = np.einsum("hw,hwc->c", k, pad[i:i + 11, j:j + 11])
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_loss_terms_by_hand():
    """2 frames of 1x2 pixels: L_s, L_t by hand on the 0.2-power images; L_g of a constant-offset
    pair is the LoG of the offset's border only, checked against the same kernel."""
    cfg = rae.Config()
    pred = np.array([[[[[1.0, 1, 1], [32.0, 32, 32]]], [[[1.0, 1, 1], [1.0, 1, 1]]]]], np.float32)  # (1, 2, 1, 2, 3)
    targ = np.ones_like(pred)
    t = rae.loss_terms(jnp.asarray(pred), jnp.asarray(targ), cfg)
    # 32^0.2 = 2: frame 0 differs by 1 at one of two pixels -> L_s = 0.5; frame 1 equal -> 0
    np.testing.assert_allclose(np.asarray(t["spatial"]), [0.5, 0.0], atol=1e-6)
    # temporal: frame 1 - frame 0 of pred is -1 at that pixel, of the target 0 -> mean 0.5
    np.testing.assert_allclose(np.asarray(t["temporal"]), [0.0, 0.5], atol=1e-6)
    assert float(t["hfen"][1]) == 0.0 and float(t["hfen"][0]) > 0
    v, _ = rae.loss(rae.init(jax.random.PRNGKey(0), TINY), {"x": np.zeros((1, 2, 8, 8, 7), np.float32),
                                                            "albedo": np.ones((1, 2, 8, 8, 3), np.float32),
                                                            "reference": np.ones((1, 2, 8, 8, 3), np.float32)}, TINY)
    assert np.isfinite(float(v))


def test_level_term_pulls_the_l1_median_toward_the_block_mean():
    """The level term (`Config.level_weight`): the RelMSE of 8x8 block means by hand; ``loss`` adds it
    frame-weighted; and it moves the uniform output that minimises the frame loss from the L1's
    median (the dark reference) toward the block's mean."""
    # each 8x8 block: 3/4 of the pixels 0.2, 1/4 1.0 (mean 0.4); one frame
    ref = np.where((np.arange(8)[:, None] % 4 == 0) & np.ones((8, 8), bool), 1.0, 0.2)
    refs = jnp.asarray(np.broadcast_to(np.tile(ref, (2, 2))[None, None, ..., None], (1, 1, 16, 16, 3)), jnp.float32)
    cfg = dataclasses.replace(rae.Config(), level_weight=4.0)
    t = rae.loss_terms(jnp.full_like(refs, 0.5), refs, cfg)
    np.testing.assert_allclose(np.asarray(t["level"]), [0.1 ** 2 / (0.4 ** 2 + 1e-3)], rtol=1e-5)
    assert "level" not in rae.loss_terms(refs, refs, rae.Config())

    def best(c):
        def frame_loss(v):
            t = rae.loss_terms(jnp.full_like(refs, v), refs, c)
            return sum(w * t[k][0] for w, k in zip(c.loss_weights, ("spatial", "hfen", "temporal"))) + (
                c.level_weight * t["level"][0] if c.level_weight else 0.0)

        vs = np.linspace(0.2, 1.0, 401)
        return vs[int(np.argmin(np.asarray(jax.vmap(frame_loss)(jnp.asarray(vs, jnp.float32)))))]

    assert best(rae.Config()) == pytest.approx(0.2, abs=3e-3)
    assert best(cfg) == pytest.approx(0.4, abs=0.03)
    # `loss` adds the term, weighted like the others over the frames
    tiny = dataclasses.replace(TINY, level_weight=4.0)
    params = rae.init(jax.random.PRNGKey(0), tiny)
    x = np.asarray(jax.random.uniform(jax.random.PRNGKey(1), (1, 2, 8, 8, 7)), np.float32)
    batch = {"x": x, "albedo": np.ones((1, 2, 8, 8, 3), np.float32), "reference": np.full((1, 2, 8, 8, 3), 0.3, np.float32)}
    with_level, aux = rae.loss(params, batch, tiny)
    plain, _ = rae.loss(params, batch, TINY)
    fw = np.asarray(rae.frame_weights(tiny, 2))
    pred = rae.run_sequence(params, jnp.asarray(x), jnp.asarray(batch["albedo"]), tiny)
    level = np.asarray(rae.loss_terms(pred, jnp.asarray(batch["reference"]), tiny)["level"])
    np.testing.assert_allclose(float(with_level) - float(plain), 4.0 * np.sum(fw * level) / np.sum(fw), rtol=1e-4)
    assert float(aux["terms"]["level"]) > 0
    with pytest.raises(ValueError, match="level_weight"):
        rae.num_params(rae.Config(level_weight=-1.0))


def test_camera_metadata_round_trips_through_exr(tmp_path):
    from jaxdenoise.io import read_buffers, write_buffers

    b = _frame(4, 5)
    ndc = np.arange(16, dtype=np.float32).reshape(4, 4)
    write_buffers(tmp_path / "f.exr", b.replace(world_to_ndc=ndc))
    r, attrs = read_buffers(tmp_path / "f.exr")
    np.testing.assert_array_equal(r.world_to_camera, b.world_to_camera)
    np.testing.assert_array_equal(r.world_to_ndc, ndc)
    # OpenEXR's row-vector convention in the file: the transpose
    np.testing.assert_allclose(np.asarray(attrs["worldToCamera"]).reshape(4, 4), b.world_to_camera.T)


def test_view_space_quantities():
    m = _camera(yaw=0.0, dist=3.0)
    n = np.array([[[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]], np.float32)  # facing the camera; pointing right
    p = np.array([[[0.0, 0.0, 2.0], [1.0, 1.0, 0.0]]], np.float32)
    np.testing.assert_allclose(np.asarray(view.view_normals(n, m)), n, atol=1e-6)
    np.testing.assert_allclose(np.asarray(view.linear_depth(p, n, m))[..., 0], [[5.0, 3.0]], atol=1e-6)
    none = np.zeros_like(n)
    assert np.all(np.asarray(view.view_normals(none, m)) == 0) and np.all(np.asarray(view.linear_depth(p, none, m)) == 0)
    turned = _camera(yaw=0.5, dist=3.0)
    vn = np.asarray(view.view_normals(n, turned))
    np.testing.assert_allclose(np.linalg.norm(vn, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(vn[0, 0], turned[:3, :3] @ n[0, 0], atol=1e-6)


def test_view_space_vectors_turn_with_the_image():
    """A quarter turn of the image (content counter-clockwise) turns (x, y) to (-y, x); a mirror
    negates x; world-space normals are left as they are."""
    v = np.zeros((3, 4, 3), np.float32)
    v[..., 0] = 1.0  # every view normal points right
    out = pipeline.rotate90({"normal_view": v, "normal": v.copy()}, 1)
    np.testing.assert_allclose(out["normal_view"][..., :2], np.broadcast_to([0.0, 1.0], (4, 3, 2)))
    np.testing.assert_array_equal(out["normal"], np.rot90(v, 1, axes=(-3, -2)))
    np.testing.assert_allclose(pipeline.flip_lr({"normal_view": v})["normal_view"][..., 0], -1.0)


def test_frame_weights_for_any_sequence_length():
    """Sec. 4.4's seven weights: the last t of them for a shorter sequence, 1 for every frame past
    the seventh of a longer one (documented in docs/methods/rae.md; exact)."""
    cfg = rae.Config()
    assert rae.frame_weights(cfg, 7) == (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1.0)
    assert rae.frame_weights(cfg, 2) == (0.882, 1.0)
    assert rae.frame_weights(cfg, 9) == (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1.0, 1.0, 1.0)


def test_exposure_frame_scales_the_output_with_the_input():
    """``exposure = "frame"``: f(k x) = k f(x) for k in 1/16..16 (issue 34 item 3), in `step` and in
    the training pass with the carried whole-frame statistic; the paper's input ("none") does not."""
    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame")
    p = rae.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(16, 12, seed=3)
    base = np.asarray(rae.apply(p, fr, cfg))
    assert base.max() > 0
    for k in (1 / 16, 0.25, 4.0, 16.0):
        out = np.asarray(rae.apply(p, fr.replace(color=fr.color * k), cfg))
        np.testing.assert_allclose(out, k * base, rtol=2e-4, atol=1e-6 * k)
    paper = TINY
    pp = rae.init(jax.random.PRNGKey(1), paper)
    a, b = np.asarray(rae.apply(pp, fr, paper)), np.asarray(rae.apply(pp, fr.replace(color=fr.color * 16), paper))
    assert np.max(np.abs(b - 16 * a)) > 1e-3 * np.max(np.abs(16 * a))
    # a crop normalised by its whole frame's carried colour mean: the same scale as the whole frame
    crop = {**fr.to_dict(), "color": fr.color[:8, :8], "stat.color_mean": np.asarray(color.color_mean(fr.color))}
    np.testing.assert_allclose(np.asarray(rae.exposure_scale(crop, cfg)).ravel(),
                               np.asarray(rae.exposure_scale(fr, cfg)).ravel(), rtol=1e-6)
    assert set(rae.frame_stats(cfg)) == {"depth_mean", "color_mean"}


def test_outlier_clamp_in_the_input():
    """``outlier_clamp`` (`jaxdenoise.filters.clamp_outliers` on the exposure-scaled colour, floor
    `color.EXPOSURE_LEVEL`): a firefly changes the output, `apply` still scales with the exposure
    (f(k x) = k f(x)); it needs exposure "frame"; `rae` has it on, `rae-paper` off."""
    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame", outlier_clamp=4.0)
    p = rae.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(16, 12, seed=3)
    fr = fr.replace(color=np.asarray(fr.color).copy())
    fr.color[5, 5] = 1e4  # cut, at every exposure
    base = np.asarray(rae.apply(p, fr, cfg))
    assert not np.allclose(base, np.asarray(rae.apply(p, fr, dataclasses.replace(cfg, outlier_clamp=0.0))))
    for k in (1 / 16, 16.0):
        np.testing.assert_allclose(np.asarray(rae.apply(p, fr.replace(color=fr.color * k), cfg)), k * base,
                                   rtol=2e-4, atol=1e-6 * k)
    with pytest.raises(ValueError, match="outlier_clamp"):
        rae.num_params(dataclasses.replace(TINY, outlier_clamp=4.0))  # TINY has exposure "none"
    assert get("rae").config.outlier_clamp == 8.0 and get("rae-paper").config.outlier_clamp == 0.0


def test_single_sample_setting():
    """``outlier_rel_sd``: `single_sample` marks the pixels of a >= 2-spp frame whose relative standard error
    (the channel mean of sqrt(``color_var``) over the colour's channel mean) reaches it; those lose the outlier
    clamp's frame-level floor (a dark spike carried by one sample, below 8x the level, is cut to 8x its
    brightest neighbour), nothing else changes; inert at 1 spp, without a variance, or at 0; it needs the
    clamp."""
    from jaxdenoise.filters import clamp_outliers

    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame", outlier_clamp=8.0)
    on = dataclasses.replace(cfg, outlier_rel_sd=0.8)
    p = rae.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(16, 12, seed=3)
    c = np.full((16, 12, 3), 0.01, np.float32)
    c[:, 6:] = 1.0  # a lit half sets the frame's level; the dark half holds the spike
    c[5, 2] = 0.5  # 50x its neighbours, below 8x the frame's level
    var = (0.2 * c) ** 2  # relative standard error 0.2 ...
    var[5, 2] = c[5, 2] ** 2  # ... and 1 at the spike: one non-zero sample among n
    fr = fr.replace(color=c, color_var=var, spp=4)
    mask = np.asarray(rae.single_sample(fr, 0.8))
    assert mask.shape == (16, 12) and mask.sum() == 1 and mask[5, 2]
    assert not np.asarray(rae.single_sample(fr.replace(spp=1), 0.8)).any()
    assert rae.single_sample(fr.replace(color_var=None), 0.8) is None
    scale = rae.exposure_scale(fr, cfg)
    x_off, x_on = np.asarray(rae.inputs(fr, cfg)), np.asarray(rae.inputs(fr, on))
    diff = np.any(x_off != x_on, axis=-1)
    assert diff.sum() == 1 and diff[5, 2]
    want = clamp_outliers(np.asarray(c * scale), 8.0, color.EXPOSURE_LEVEL, unfloored=mask)
    np.testing.assert_allclose(np.asarray(rae._cut_outliers(c * scale, on, fr)), np.asarray(want), rtol=1e-6)
    lum = lambda v: 0.2126 * v[..., 0] + 0.7152 * v[..., 1] + 0.0722 * v[..., 2]
    np.testing.assert_allclose(lum(np.asarray(want)[5, 2]), 8 * 0.01 * float(np.ravel(scale)[0]), rtol=1e-5)
    assert not np.allclose(np.asarray(rae.apply(p, fr, cfg)), np.asarray(rae.apply(p, fr, on)))
    np.testing.assert_array_equal(np.asarray(rae.apply(p, fr.replace(spp=1), cfg)),
                                  np.asarray(rae.apply(p, fr.replace(spp=1), on)))
    np.testing.assert_array_equal(np.asarray(rae.inputs(fr, dataclasses.replace(on, outlier_rel_sd=0.0))), x_off)
    for bad in (dataclasses.replace(on, outlier_clamp=0.0), dataclasses.replace(on, outlier_rel_sd=-1.0),
                dataclasses.replace(on, outlier_rel_sd=float("nan"))):
        with pytest.raises(ValueError, match="outlier_rel_sd"):
            rae.num_params(bad)


def _step_off_on(cfg, on):
    """One first step of a 16x12 frame with ``cfg`` and with ``on`` (inference settings only): the
    params, the frame and both outputs; the two states must be the network's, bit for bit."""
    p = rae.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(16, 12, seed=3)
    s0 = rae.init_state(fr, cfg)
    state_off, off = rae.step(p, s0, fr, cfg)
    state_on, out = rae.step(p, s0, fr, on)
    for a, b in zip(state_off, state_on):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    return p, fr, off, out


def test_output_clamp_after_the_network():
    """``output_clamp``: the network's frame (exact pixels kept) through `clamp_outliers` with
    ``radius`` in the exposure-scaled units (floor 0.1 % of `color.EXPOSURE_LEVEL`), exact pixels
    restored after (the composition by hand); the state is the network's; f(k x) = k f(x) holds; it
    needs exposure "frame" and an int radius >= 1."""
    from jaxdenoise.filters import clamp_outliers, exact_mask

    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame", keep_exact=True, exact_window=3)
    on = dataclasses.replace(cfg, output_clamp=1.0, output_clamp_radius=2)
    p, fr, off, out = _step_off_on(cfg, on)
    scale = rae.exposure_scale(fr, cfg)
    want = clamp_outliers(off * scale, 1.0, 1e-3 * color.EXPOSURE_LEVEL, radius=2) / scale
    exact = exact_mask(fr.color, None, fr.spp, window=3)
    np.testing.assert_allclose(np.asarray(out), np.asarray(jnp.where(exact, color.radiance(fr.color), want)),
                               rtol=1e-5, atol=1e-7)
    assert not np.allclose(np.asarray(out), np.asarray(off))  # an untrained network's frame has local peaks
    for k in (1 / 16, 16.0):
        np.testing.assert_allclose(np.asarray(rae.apply(p, fr.replace(color=fr.color * np.float32(k)), on)),
                                   k * np.asarray(out), rtol=2e-4, atol=1e-6 * k)
    with pytest.raises(ValueError, match="output_clamp"):
        rae.num_params(dataclasses.replace(TINY, output_clamp=2.0))  # TINY has exposure "none"
    with pytest.raises(ValueError, match="output_clamp_radius"):
        rae.num_params(dataclasses.replace(on, output_clamp_radius=0))


def test_spike_term_charges_only_light_above_the_targets_neighbourhood():
    """``spike_weight``: the term is max(0, p - k M)^2 / ((k M)^2 + eps) averaged over pixels per frame
    (p the prediction's channel mean, M the target's 9x9 maximum of it; a NumPy evaluation); an output
    below k M everywhere, however wrong, costs nothing; bad settings are refused by name."""
    from scipy.ndimage import maximum_filter

    cfg = rae.Config(spike_weight=2.0, spike_factor=4.0, spike_window=9)
    r = np.random.default_rng(5)
    t = r.uniform(0.05, 1.0, (2, 3, 20, 18, 3)).astype(np.float32)
    p = t * r.uniform(0.0, 3.0, t.shape).astype(np.float32)  # wrong, but nowhere above 4x the neighbourhood
    assert np.all(np.asarray(rae.loss_terms(jnp.asarray(p), jnp.asarray(t), cfg)["spike"]) == 0)
    p[1, 2, 10, 9] = 60.0
    p[0, 0, 0, 0] = 40.0  # at the border: the window is cut by the frame
    m = 4.0 * maximum_filter(t.mean(-1), size=(1, 1, 9, 9), mode="constant", cval=-np.inf)
    want = np.mean(np.maximum(p.mean(-1) - m, 0) ** 2 / (m ** 2 + cfg.level_eps), axis=(0, 2, 3))
    got = np.asarray(rae.loss_terms(jnp.asarray(p), jnp.asarray(t), cfg)["spike"])
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert got[0] > 0 and got[2] > 0 and got[1] == 0
    for bad in ({"spike_weight": -1.0}, {"spike_factor": 0.0}, {"spike_window": 8}):
        with pytest.raises(ValueError, match="spike_"):
            rae.num_params(dataclasses.replace(TINY, **bad))


def test_level_match_setting():
    """``match_level``: the output's low-pass level is moved toward the input's within the gain limit
    (`jaxdenoise.filters.match_to_input`, with ``match_output_cut`` its ``output_cut``), the state is the
    network's, f(k x) = k f(x) holds; it needs exposure "frame"; on for `rae`, off for `rae-paper`."""
    from jaxdenoise.filters import match_to_input

    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame")
    on = dataclasses.replace(cfg, match_level=4.0, match_max_gain=1.2)
    p, fr, off, out = _step_off_on(cfg, on)
    s0 = rae.init_state(fr, cfg)
    gain = np.asarray(out) / np.maximum(np.asarray(off), 1e-12)
    lit = np.asarray(off) > 1e-6
    assert np.all(gain[lit] <= 1.2 + 1e-5) and np.all(gain[lit] >= 1 / 1.2 - 1e-5) and not np.allclose(out, off)
    for k in (1 / 16, 3.0):
        np.testing.assert_allclose(np.asarray(rae.apply(p, fr.replace(color=fr.color * np.float32(k)), on)),
                                   k * np.asarray(out), rtol=2e-4, atol=1e-6 * k)
    four = fr.replace(spp=4)  # by rate: one sample's factor 7 cuts a 4-spp frame as a fixed 4 does
    np.testing.assert_array_equal(
        np.asarray(rae.step(p, s0, four, dataclasses.replace(on, match_spike=7.0, match_spike_by_rate=True))[1]),
        np.asarray(rae.step(p, s0, four, dataclasses.replace(on, match_spike=4.0))[1]))
    cut = dataclasses.replace(on, match_output_cut=True)  # the target cut against the output too
    scale = rae.exposure_scale(fr, cut)
    want = match_to_input(np.asarray(off) * scale, color.radiance(fr.color) * scale, 4.0, spike=cut.match_spike,
                          floor=color.EXPOSURE_LEVEL, max_gain=1.2, output_cut=True) / scale
    np.testing.assert_allclose(np.asarray(rae.apply(p, fr, cut)), np.asarray(want), rtol=2e-5, atol=1e-6)
    with pytest.raises(ValueError, match="match_level"):
        rae.num_params(dataclasses.replace(TINY, match_level=8.0))  # TINY has exposure "none"
    with pytest.raises(ValueError, match="match_spike_by_rate"):
        rae.num_params(dataclasses.replace(on, match_spike=0.5, match_spike_by_rate=True))
    assert get("rae").config.match_level == 8.0 and get("rae-paper").config.match_level == 0.0


def test_keep_exact_pixels():
    """``keep_exact`` (`jaxdenoise.filters.exact_mask`): at >= 2 spp a lit pixel whose colour variance is
    0 keeps its input, before and after the level match; at 1 spp the window rule keeps a uniform 3x3
    block's centre; every other pixel and the state are as without it; `needs` reads color_var,
    `required` does not."""
    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame", match_level=4.0, match_max_gain=1.2)
    on = dataclasses.replace(cfg, keep_exact=True, exact_window=3)
    assert "color_var" in rae.needs(on) and "color_var" not in rae.required(on) | rae.needs(cfg)
    p = rae.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(16, 12, seed=3)
    color = np.asarray(fr.color).copy()
    color[4:7, 5:8] = [5.0, 4.0, 3.0]  # a uniform light: its centre (5, 6) agrees with its 3x3 square
    var = np.full_like(color, 0.1)
    var[10, 2] = 0.0  # samples that all agreed
    s0 = rae.init_state(fr, cfg)
    for spp, kept in ((4, (10, 2)), (1, (5, 6))):
        b = fr.replace(color=color, color_var=var, spp=spp)
        state_off, off = rae.step(p, s0, b, cfg)
        state_on, out = rae.step(p, s0, b, on)
        out, off = np.asarray(out), np.asarray(off)
        np.testing.assert_array_equal(out[kept], color[kept])
        assert not np.allclose(off[kept], color[kept])
        for a, c in zip(state_off, state_on):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
        plain = dataclasses.replace(cfg, match_level=0.0)  # without the match: only the kept pixel changes
        a = np.array(rae.step(p, s0, b, plain)[1])
        z = np.asarray(rae.step(p, s0, b, dataclasses.replace(plain, keep_exact=True, exact_window=3))[1])
        a[kept] = color[kept]
        np.testing.assert_array_equal(z, a)
    with pytest.raises(ValueError, match="exact_window"):
        rae.num_params(dataclasses.replace(on, exact_window=4))
    assert get("rae").config.keep_exact and not get("rae-paper").config.keep_exact


def test_keep_background_pixels():
    """``keep_background``: a pixel with a zero normal (no surface: the environment seen directly) keeps its
    input, before and after the level match, alone or with exact pixels; every other pixel and the state
    are as without it; `needs` reads the normal; the shipped `rae` keeps them, `rae-paper` does not."""
    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, exposure="frame", match_level=4.0, match_max_gain=1.2,
                     aux=())
    on = dataclasses.replace(cfg, keep_background=True)
    assert "normal" in rae.needs(on) and "normal" not in rae.needs(cfg)
    p = rae.init(jax.random.PRNGKey(1), cfg)
    fr = _frame(16, 12, seed=4)
    normal = np.asarray(fr.normal).copy()
    normal[:3] = 0.0  # the top three rows see the sky
    b = fr.replace(normal=normal, spp=4)
    s0 = rae.init_state(b, cfg)
    state_off, off = rae.step(p, s0, b, cfg)
    state_on, out = rae.step(p, s0, b, on)
    color = np.asarray(b.color)
    np.testing.assert_array_equal(np.asarray(out)[:3], color[:3])
    assert not np.allclose(np.asarray(off)[:3], color[:3])
    for a, c in zip(state_off, state_on):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    plain = dataclasses.replace(cfg, match_level=0.0)  # without the match: only the kept pixels change
    a = np.array(rae.step(p, s0, b, plain)[1])
    a[:3] = color[:3]
    kept = rae.step(p, s0, b, dataclasses.replace(plain, keep_background=True))[1]
    np.testing.assert_array_equal(np.asarray(kept), a)
    var = np.full_like(color, 0.1)
    var[10, 2] = 0.0  # and an exact pixel besides
    both = rae.step(p, s0, b.replace(color_var=var), dataclasses.replace(plain, keep_background=True, keep_exact=True))
    a[10, 2] = color[10, 2]
    np.testing.assert_array_equal(np.asarray(both[1]), a)
    assert get("rae").config.keep_background and not get("rae-paper").config.keep_background


def test_rate_channel_and_linear_input():
    """``rate_input``: one more channel, log2(spp) / RATE_SCALE, per pixel from a sample-count map;
    a frame without ``spp`` is refused. ``input_transform = "linear"``: the demodulated colour itself."""
    cfg = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, rate_input=True)
    assert "spp" in rae.needs(cfg) and rae.in_channels(cfg) == 8
    fr = _frame(6, 5, seed=2).replace(spp=16)
    x = np.asarray(rae.inputs(fr, cfg))
    assert x.shape == (6, 5, 8)
    np.testing.assert_allclose(x[..., -1], 4 / rae.RATE_SCALE)
    counts = np.full((6, 5, 1), 4.0, np.float32)
    counts[0, 0] = 64
    xm = np.asarray(rae.inputs(fr.replace(spp_map=counts), cfg))
    np.testing.assert_allclose(xm[..., -1], np.log2(counts[..., 0]) / rae.RATE_SCALE)
    with pytest.raises(Exception, match="spp"):
        rae.inputs(fr.replace(spp=None), cfg)
    batch = {**fr.to_dict(), "color": np.stack([fr.color] * 2), "spp": np.asarray([1.0, 64.0])}
    batch = {k: (np.stack([v] * 2) if k in ("albedo", "normal", "position", "roughness") else v) for k, v in batch.items()}
    xb = np.asarray(rae.inputs(batch, cfg))
    np.testing.assert_allclose(xb[:, 0, 0, -1], [0.0, 6 / rae.RATE_SCALE])
    p = rae.init(jax.random.PRNGKey(0), cfg)
    assert p["enc"]["0"]["w"].shape[2] == 8 and np.isfinite(np.asarray(rae.apply(p, fr, cfg))).all()
    lin = rae.Config(widths=(4, 4, 6, 6, 8), bottleneck=8, input_transform="linear", exposure="none",
                     rate_input=False)
    demod = np.asarray(color.demodulate(fr.color, np.clip(fr.albedo, 0, 1)))
    np.testing.assert_allclose(np.asarray(rae.inputs(fr, lin))[..., :3], demod, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(rae.inputs(fr, TINY))[..., :3], demod ** 0.2, rtol=1e-5)
    with pytest.raises(Exception, match="input_transform"):
        rae.needs(rae.Config(input_transform="log"))


def _pinhole_frames(n: int) -> list:
    """``n`` 16x12 frames of `_frame` in front of a pinhole camera (w = z) that moves a little per frame."""
    cam = np.eye(4, dtype=np.float32)
    cam[2, 2], cam[3, 2], cam[3, 3] = 0.0, 1.0, 0.0
    frames = []
    for s in range(n):
        f = _frame(16, 12, seed=s)
        pos = np.asarray(f.position).copy()
        pos[..., 2] = np.abs(pos[..., 2]) + 2.0  # in front of the camera
        frames.append(f.replace(position=pos, world_to_ndc=cam + np.float32(0.01 * s)))
    return frames


def test_accumulate_setting():
    """``accumulate_samples`` (`jaxdenoise.filters.accumulate_step`): the state carries the input's history
    after the recurrent one; each frame's network sees the accumulated colour (at most samples / spp
    frames) and, with the rate channel, its samples times the frames averaged per pixel, as a frame
    carrying them would; `apply` is unchanged; `needs` adds what reprojection reads; bad settings are
    refused by their config names."""
    from jaxdenoise.filters import accumulate_step, taa_init

    cfg = dataclasses.replace(TINY, rate_input=True)
    on = dataclasses.replace(cfg, accumulate_samples=2.0, accumulate_tolerance=0.05, accumulate_clamp=4.0)
    assert {"position", "normal", "world_to_ndc"} <= rae.needs(on) and "world_to_ndc" not in rae.required(on)
    p = rae.init(jax.random.PRNGKey(5), cfg)
    frames = _pinhole_frames(3)
    s_off, s_on, acc = rae.init_state(frames[0], cfg), rae.init_state(frames[0], on), taa_init((16, 12, 3))
    assert len(s_on) == len(s_off) + 1
    lengths = []
    for f in frames:
        acc, mean, n = accumulate_step(acc, f.color, f.position, f.normal, f.world_to_ndc, frames=2.0,
                                       tolerance=0.05, clamp=4.0)
        s_off, want = rae.step(p, s_off, f.replace(color=mean, spp_map=np.asarray(n)), cfg)
        s_on, out = rae.step(p, s_on, f, on)
        np.testing.assert_allclose(np.asarray(out), np.asarray(want), rtol=1e-5, atol=1e-6)
        for a, b in zip(s_off, s_on[:-1]):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
        lengths.append(float(np.max(n)))
    assert lengths == [1.0, 2.0, 2.0]  # history read somewhere; capped at 2 frames (2 samples at 1 spp)
    np.testing.assert_array_equal(np.asarray(rae.apply(p, frames[2], on)), np.asarray(rae.apply(p, frames[2], cfg)))
    at2 = [f.replace(spp=2) for f in frames]  # a frame of `accumulate_samples` spp keeps no history
    s_off, s_on = rae.init_state(at2[0], cfg), rae.init_state(at2[0], on)
    for f in at2:
        s_off, want = rae.step(p, s_off, f, cfg)
        s_on, out = rae.step(p, s_on, f, on)
        np.testing.assert_allclose(np.asarray(out), np.asarray(want), rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="config.accumulate_samples"):
        rae.num_params(dataclasses.replace(on, accumulate_samples=-1.0))


def _plane_video(t: int, h: int, w: int, *, shift: float, seed: int = 0, spread: tuple = (0.05, 0.95)) -> dict:
    """A ``t``-frame video ``(t, h, w, .)`` of the plane z = 5 seen by a pinhole camera (NDC = f (x, y) / z,
    w = z) that moves ``shift`` pixels to the right per frame, one sample per pixel offset by ``spread``
    pixels from its corner (a pixel filter wider than the pixel reaches beyond it): colour,
    albedo, positions, normals, roughness and every frame's ``world_to_ndc``."""
    r = np.random.default_rng(seed)
    f, z = 1.5, 5.0
    out = {k: [] for k in ("color", "albedo", "position", "normal", "world_to_ndc")}
    for k in range(t):
        rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        jx, jy = r.uniform(*spread, (2, h, w))
        ndc_x, ndc_y = (cols + jx) * 2 / w - 1, 1 - (rows + jy) * 2 / h
        cx = k * shift * 2 / w * z / f  # the camera's x in the world
        pos = np.stack([ndc_x * z / f + cx, ndc_y * z / f, np.full((h, w), z)], -1).astype(np.float32)
        m = np.zeros((4, 4), np.float32)
        m[0, 0], m[0, 3], m[1, 1], m[3, 2] = f, -f * cx, f, 1.0
        out["position"].append(pos)
        out["world_to_ndc"].append(m)
        out["color"].append(r.exponential(0.3, (h, w, 3)).astype(np.float32))
        out["albedo"].append(np.full((h, w, 3), 0.5, np.float32))
        out["normal"].append(np.broadcast_to(np.float32([0, 0, -1]), (h, w, 3)).copy())
    out["roughness"] = [np.full((h, w, 1), 0.5, np.float32)] * t
    return {k: np.stack(v) for k, v in out.items()}


def test_crop_projection_recovers_the_crops_window():
    """`rae.crop_projection`: fitted from a crop's own positions, ``A @ world_to_ndc`` puts every pixel's
    sample inside that pixel of the crop, for the frame and for a later frame of the same crop window."""
    v = _plane_video(2, 24, 32, shift=3.0)
    y0, x0, c = 5, 9, 12
    crop = {k: v[k][:, y0:y0 + c, x0:x0 + c] for k in ("position", "normal")}
    a = rae.crop_projection(crop["position"][0], crop["normal"][0], v["world_to_ndc"][0].astype(np.float64))
    for t in range(2):
        m = a @ v["world_to_ndc"][t]
        p = crop["position"][t].astype(np.float64)
        q = p @ m[:3, :3].T + m[:3, 3]
        wq = p @ m[3, :3] + m[3, 3]
        col = (q[..., 0] / wq + 1) / 2 * c - 0.5
        row = (1 - q[..., 1] / wq) / 2 * c - 0.5
        rows, cols = np.meshgrid(np.arange(c), np.arange(c), indexing="ij")
        assert np.all(np.abs(col - cols) < 0.5) and np.all(np.abs(row - rows) < 0.5)
    assert rae.crop_projection(crop["position"][0], np.zeros_like(crop["normal"][0]), v["world_to_ndc"][0]) is None
    wide = _plane_video(1, 72, 96, shift=0.0, spread=(-1.5, 2.5))  # samples up to 2 px outside their pixel
    c = 48
    a = rae.crop_projection(wide["position"][0, y0:y0 + c, x0:x0 + c], wide["normal"][0, y0:y0 + c, x0:x0 + c],
                            wide["world_to_ndc"][0].astype(np.float64))
    exact = np.eye(4)  # the frame's NDC to the crop's: x' = (W x + W - 2 x0) / c - 1, y' = (H y - H + 2 y0) / c + 1
    exact[0, 0], exact[0, 3], exact[1, 1], exact[1, 3] = 96 / c, (96 - 2 * x0) / c - 1, 72 / c, 1 - 72 / c + 2 * y0 / c
    np.testing.assert_allclose(a, exact, atol=0.01)


class _Videos:
    """A stand-in training set: `sequences` returns whole (un-augmented) crops of one video at ``spp``."""

    def __init__(self, video: dict, spp: float, config):
        self.video, self.spp, self.config = video, spp, config

    def sequences(self, n, size, rng, *, frames, stop_probability, augment):
        v = {k: np.repeat(x[None, :frames, :size, :size] if x.ndim == 4 else x[None, :frames], n, 0)
             for k, x in self.video.items()}
        v["reference"], v["spp"] = v["color"], np.full((n, frames), self.spp, np.float32)
        v["world_to_camera"] = np.broadcast_to(np.eye(4, dtype=np.float32), (n, frames, 4, 4)).copy()
        for name, fn in rae.frame_stats(self.config).items():
            v[pipeline.STAT + name] = np.stack([[np.asarray(fn({k: x[i, t] for k, x in v.items()}))
                                                 for t in range(frames)] for i in range(n)])
        return v


def test_training_on_accumulated_inputs():
    """``train_accumulate``: a 1-spp training crop is given `step`'s accumulated colour and, in the rate
    channel, each pixel's samples (1, 2, 3, then 4 frames: ``accumulate_samples`` 4); a crop at 4 spp
    (``accumulate_samples``) and a run without it keep the colour as rendered; bad settings are refused."""
    cfg = dataclasses.replace(TINY, exposure="frame", rate_input=True, accumulate_samples=4.0, train_accumulate=1.0,
                              train_batch=2, train_crop=16, stop_probability=0.0)
    v = _plane_video(7, 16, 16, shift=0.0)
    rate = lambda b: b["x"][:, :, 6:10, 6:10, -1] * rae.RATE_SCALE  # noqa: E731  (interior pixels)
    got = rate(rae.batch(_Videos(v, 1.0, cfg), 0, cfg, np.random.default_rng(0)))
    want = np.log2(np.minimum(np.arange(1, 8), 4.0))
    np.testing.assert_allclose(got, np.broadcast_to(want[None, :, None, None], got.shape), atol=1e-6)
    plain = dataclasses.replace(cfg, train_accumulate=0.0)
    np.testing.assert_array_equal(rate(rae.batch(_Videos(v, 1.0, plain), 0, plain, np.random.default_rng(0))), 0.0)
    np.testing.assert_allclose(rate(rae.batch(_Videos(v, 4.0, cfg), 0, cfg, np.random.default_rng(0))), 2.0)
    with pytest.raises(ValueError, match="config.train_accumulate"):
        rae.num_params(dataclasses.replace(cfg, accumulate_samples=0.0))


def test_match_frames_setting():
    """``match_frames``: the level match's gain averaged over the previous frames' gains reprojected
    (`jaxdenoise.filters.accumulate_step`, no clamp), over match_frames / (the frames the input accumulation
    averaged) frames; the state carries it after TAA's; the first frame, `apply` and a frame without
    world_to_ndc (its own gain, the history kept) as without it; bad settings refused by name."""
    from jaxdenoise.filters import accumulate_step, input_gain, taa_init

    cfg = dataclasses.replace(TINY, exposure="frame", match_level=4.0, taa_alpha=0.25)  # gain unlimited
    on = dataclasses.replace(cfg, match_frames=4.0, match_tolerance=0.0)  # the frames' positions are random
    assert {"position", "normal", "world_to_ndc"} <= rae.needs(dataclasses.replace(on, taa_alpha=0.0))
    p = rae.init(jax.random.PRNGKey(4), cfg)  # a random network about 7x too bright: gains of about 0.14
    frames = _pinhole_frames(4)
    s_off, s_on, gains = rae.init_state(frames[0], cfg), rae.init_state(frames[0], on), taa_init((16, 12, 3))
    assert len(s_on) == len(s_off) + 1
    network = dataclasses.replace(cfg, match_level=0.0)  # the same frames before the match
    for k, f in enumerate(frames):
        s_off, own = rae.step(p, s_off, f, cfg)
        pre = rae.step(p, s_on[:-1], f, network)[1]
        s_on, out = rae.step(p, s_on, f, on)
        scale = rae.exposure_scale(f, cfg)
        gain = input_gain(pre * scale, color.radiance(f.color) * scale, 4.0, spike=cfg.match_spike,
                          floor=color.EXPOSURE_LEVEL)
        gains, gain, _ = accumulate_step(gains, gain, f.position, f.normal, f.world_to_ndc, frames=4.0,
                                         tolerance=0.0, clamp=0.0)
        np.testing.assert_allclose(np.asarray(out), np.asarray(pre * gain), rtol=2e-5, atol=1e-6)
        for a, b in zip(jax.tree_util.tree_leaves(s_off), jax.tree_util.tree_leaves(s_on[:-1])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        if k == 0:
            np.testing.assert_array_equal(np.asarray(out), np.asarray(own))
    assert not np.allclose(np.asarray(out), np.asarray(own), rtol=1e-4)  # earlier gains were averaged in
    np.testing.assert_array_equal(np.asarray(rae.apply(p, frames[1], on)), np.asarray(rae.apply(p, frames[1], cfg)))
    bare = frames[1].replace(world_to_ndc=None)
    s2, out2 = rae.step(p, s_on, bare, on)
    np.testing.assert_array_equal(np.asarray(out2), np.asarray(rae.step(p, s_on[:-1], bare, cfg)[1]))
    for a, b in zip(jax.tree_util.tree_leaves(s2[-1]), jax.tree_util.tree_leaves(s_on[-1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # with the input accumulation a pixel keeps match_frames / (the frames its input averaged) gains
    acc = dataclasses.replace(on, accumulate_samples=2.0, accumulate_tolerance=0.0, match_frames=2.0)
    s = rae.init_state(frames[0], acc)
    for f in frames:
        s, out = rae.step(p, s, f, acc)
    s_own = rae.init_state(frames[0], dataclasses.replace(acc, match_frames=0.0))
    for f in frames:
        s_own, own = rae.step(p, s_own, f, dataclasses.replace(acc, match_frames=0.0))
    np.testing.assert_allclose(np.asarray(out), np.asarray(own), rtol=1e-6)  # 2 / 2 frames: no gain history
    for bad in ({"match_frames": -1.0}, {"match_tolerance": np.inf}):
        with pytest.raises(ValueError, match="config.match_frames"):
            rae.num_params(dataclasses.replace(on, **bad))
    unmatched = dataclasses.replace(on, match_level=0.0, taa_alpha=0.0)  # without the match it does nothing
    assert len(rae.init_state(frames[0], unmatched)) == len(rae.init_state(frames[0], TINY))
    assert "world_to_ndc" not in rae.needs(unmatched)


def test_taa_setting():
    """``taa_alpha`` (`jaxdenoise.filters.taa_step`): the state carries the TAA history beside the
    recurrent one; each frame is the network's output without TAA passed through `taa_step` with the
    same settings, the first frame (and `apply`) unchanged; `needs` adds what reprojection reads; bad
    settings are refused by their config names."""
    from jaxdenoise.filters import match_to_input, taa_init, taa_step

    on = dataclasses.replace(TINY, taa_alpha=0.25, taa_window=3, taa_tolerance=0.05)
    assert {"position", "normal", "world_to_ndc"} <= rae.needs(on) and "world_to_ndc" not in rae.required(on)
    assert "world_to_ndc" not in rae.needs(TINY)
    p = rae.init(jax.random.PRNGKey(4), TINY)
    frames = _pinhole_frames(3)
    s_off, s_on, taa = rae.init_state(frames[0], TINY), rae.init_state(frames[0], on), taa_init((16, 12, 3))
    assert len(s_on) == len(s_off) + 1
    for k, f in enumerate(frames):
        s_off, plain = rae.step(p, s_off, f, TINY)
        s_on, out = rae.step(p, s_on, f, on)
        taa, want = taa_step(taa, plain, f.position, f.normal, f.world_to_ndc, alpha=0.25, window=3, tolerance=0.05)
        np.testing.assert_allclose(np.asarray(out), np.asarray(want), rtol=1e-6, atol=1e-7)
        if k == 0:
            np.testing.assert_array_equal(np.asarray(out), np.asarray(plain))
        for a, b in zip(s_off, s_on[:-1]):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(out), np.asarray(plain), rtol=1e-3)  # history was blended in
    np.testing.assert_array_equal(np.asarray(rae.apply(p, frames[2], on)), np.asarray(rae.apply(p, frames[2], TINY)))
    with pytest.raises(ValueError, match="config.taa_window"):
        rae.num_params(dataclasses.replace(on, taa_window=4))
    # the shipped order: exact pixels, TAA, the level match, exact pixels again; a frame without
    # world_to_ndc (not required) gets no TAA and leaves the history as it was
    shipped = dataclasses.replace(on, exposure="frame", match_level=4.0, match_max_gain=1.2, keep_exact=True,
                                  exact_window=3)
    assert "world_to_ndc" in rae.needs(shipped) and "world_to_ndc" not in rae.required(shipped)
    network = dataclasses.replace(shipped, taa_alpha=0.0, match_level=0.0)  # the network and exact pixels
    color_ = np.asarray(frames[0].color).copy()
    color_[4:7, 5:8] = [5.0, 4.0, 3.0]  # a uniform light: kept exactly at 1 spp by the 3x3 window rule
    seq = [f.replace(color=color_) for f in frames]
    s_on, taa = rae.init_state(seq[0], shipped), taa_init((16, 12, 3))
    for f in seq:
        pre = rae.step(p, s_on[:-1], f, network)[1]
        s_on, out = rae.step(p, s_on, f, shipped)
        taa, want = taa_step(taa, pre, f.position, f.normal, f.world_to_ndc, alpha=0.25, window=3, tolerance=0.05)
        scale = rae.exposure_scale(f, shipped)
        c = np.asarray(color.radiance(f.color))
        want = np.array(match_to_input(want * scale, c * scale, 4.0, spike=shipped.match_spike,
                                       floor=color.EXPOSURE_LEVEL, max_gain=1.2) / scale)
        want[5, 6] = c[5, 6]
        np.testing.assert_allclose(np.asarray(out), want, rtol=2e-5, atol=1e-6)
        np.testing.assert_array_equal(np.asarray(out)[5, 6], c[5, 6])
    bare = seq[0].replace(world_to_ndc=None)
    s2, out2 = rae.step(p, s_on, bare, shipped)
    for a, b in zip(jax.tree_util.tree_leaves(s2[-1]), jax.tree_util.tree_leaves(s_on[-1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
