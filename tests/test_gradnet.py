"""GradNet (Guo et al. 2019): network shapes, the unsupervised losses against hand computations, the
post-process, the lambda schedule, and that training never reads a reference."""
from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdenoise.buffers import Buffers
from jaxdenoise.methods import gradnet as G

CFG = G.Config(widths=(8, 16, 16), g_width=8)  # a small network: the structure is the paper's


def _frame(h, w, seed=0, lead=()):
    rng = np.random.default_rng(seed)
    s = lead + (h, w)
    return {"color": rng.gamma(1.0, 0.5, s + (3,)).astype(np.float32),
            "dx": rng.normal(0, 0.2, s + (3,)).astype(np.float32),
            "dy": rng.normal(0, 0.2, s + (3,)).astype(np.float32),
            "albedo": rng.random(s + (3,)).astype(np.float32),
            "normal": rng.uniform(-1, 1, s + (3,)).astype(np.float32),
            "depth": rng.uniform(0.5, 4.0, s + (1,)).astype(np.float32)}


def _mu(x, mu=16.0):
    return np.sign(x) * np.log1p(np.abs(x) * mu) / np.log1p(mu)


@pytest.mark.slow  # 22 s of compilation; the stability suite runs gradnet at 1x1 in the default run
@pytest.mark.parametrize("hw", [(1, 1), (7, 5), (33, 64)])
def test_any_size_gives_a_finite_image_of_that_size(hw):
    params = G.init(jax.random.PRNGKey(0), CFG)
    out = G.apply(params, Buffers(**_frame(*hw)), CFG)
    assert out.shape == hw + (3,)
    assert bool(jnp.all(jnp.isfinite(out))) and bool(jnp.all(out >= 0))


def test_parameter_count_of_the_default_network():
    """Default widths (24, 48, 96), four residual blocks of 192 channels, last deconvolution to 24
    channels joined with the 16 input channels by a 3x3 conv, G-branch of width 32: 3,160,480
    parameters (docs/methods/gradnet.md); without the input skip the last deconvolution gives the 3
    output channels itself: 3,135,184."""
    assert G.num_params(G.Config()) == 3_160_480
    assert G.num_params(G.Config(input_skip=False)) == 3_135_184


def test_needs_are_the_papers_inputs():
    assert G.needs(CFG) == {"color", "dx", "dy", "albedo", "normal", "depth"}


def test_features_are_scaled_to_unit_range():
    f = _frame(4, 4)
    feat = np.asarray(G.features(jnp.asarray(f["albedo"]), jnp.asarray(f["normal"]), jnp.asarray(f["depth"])))
    assert feat.shape == (4, 4, 7)
    np.testing.assert_allclose(feat[..., 3:6], (f["normal"] + 1) / 2, rtol=1e-6)
    np.testing.assert_allclose(feat[..., 6:], f["depth"] / f["depth"].max(), rtol=1e-6)
    assert feat.min() >= 0 and feat.max() <= 1


def _nonzero_output(params):
    """The output layer starts at zero (the network starts at T(I_b)); give it random weights so the
    loss checks see an output that differs from the base image."""
    out = jax.tree_util.tree_map(lambda a: 0.1 * np.random.default_rng(5).standard_normal(a.shape).astype(np.float32),
                                 params["out"])
    return {**params, "out": out}


@pytest.mark.parametrize("head", [0, 4])
def test_output_layer_starts_at_zero_so_the_network_starts_at_the_base_image(head):
    """With or without the full-resolution head (`Config.head_width`): its last conv is zero too, so
    adding it to a trained network changes nothing until it is trained."""
    cfg = dataclasses.replace(CFG, head_width=head)
    f = _frame(8, 8, seed=4)
    params = G.init(jax.random.PRNGKey(2), cfg)
    y, _, x = G.predict(params, f, cfg)
    np.testing.assert_array_equal(np.asarray(y), np.asarray(x["tb"]))
    assert ("head" in params) == bool(head) and ("head" in G.param_groups(cfg)["autoencoder"]) == bool(head)


def test_losses_against_a_hand_computation_on_4x4():
    """Eq. 8-11 computed with plain loops in NumPy (tolerance 1e-5 relative, float32)."""
    f = _frame(4, 4, seed=3)
    params = _nonzero_output(G.init(jax.random.PRNGKey(1), CFG))
    t = {k: float(v) for k, v in G.loss_terms(params, f, CFG).items()}
    y, Gm, x = G.predict(params, f, CFG)
    y = np.asarray(y, np.float64)  # T(I_hat)
    Gm = np.asarray(Gm, np.float64)  # (4, 4, 7, 3)
    tb = _mu(np.maximum(f["color"], 0).astype(np.float64))
    feat = np.asarray(x["feat"], np.float64)
    hdr = np.sign(y) * ((1 + 16.0) ** np.abs(y) - 1) / 16.0
    # Eq. 8
    data = np.mean([np.abs(y[i, j] - tb[i, j]).sum() for i in range(4) for j in range(4)])
    # Eq. 9
    gx = [np.abs(_mu(hdr[i, j + 1] - hdr[i, j]) - _mu(f["dx"][i, j].astype(np.float64))).sum()
          for i in range(4) for j in range(3)]
    gy = [np.abs(_mu(hdr[i + 1, j] - hdr[i, j]) - _mu(f["dy"][i, j].astype(np.float64))).sum()
          for i in range(3) for j in range(4)]
    grad = np.mean(gx) + np.mean(gy)

    # Eq. 10 / 11
    def first(img):
        tot, n = 0.0, 0
        for i in range(4):
            for j in range(4):
                for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                    a, b = i + di, j + dj
                    if not (0 <= a < 4 and 0 <= b < 4):
                        continue
                    w = math.exp(-np.sum((tb[i, j] - tb[a, b]) ** 2) / (2 / 18))
                    pred = Gm[i, j].T @ (feat[a, b] - feat[i, j])
                    tot += w * np.abs(img[a, b] - img[i, j] - pred).sum()
                    n += 1
        return tot / n

    np.testing.assert_allclose(t["data"], data, rtol=1e-5)
    np.testing.assert_allclose(t["grad"], grad, rtol=1e-5)
    np.testing.assert_allclose(t["first"], first(y), rtol=1e-5)
    np.testing.assert_allclose(t["g_branch"], first(tb), rtol=1e-5)


def test_gradient_loss_vanishes_for_exact_gradients():
    rng = np.random.default_rng(5)
    img = rng.gamma(1.0, 1.0, (6, 7, 3)).astype(np.float32)
    dx = np.zeros_like(img)
    dy = np.zeros_like(img)
    dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy[:-1] = img[1:] - img[:-1]
    x = {"tdx": G.mu_law(jnp.asarray(dx), CFG.mu), "tdy": G.mu_law(jnp.asarray(dy), CFG.mu)}
    assert float(G.grad_loss(jnp.asarray(img), x, CFG)) < 1e-6  # float32 rounding of the differences


def test_first_order_weights_against_numpy():
    rng = np.random.default_rng(2)
    tb = rng.random((5, 6, 3)).astype(np.float32)
    w = [np.asarray(v) for v in G.first_order_weights(jnp.asarray(tb), CFG)]
    right = np.exp(-np.sum((tb[:, 1:] - tb[:, :-1]) ** 2, -1, keepdims=True) * 9.0)  # 1/(2/18) = 9
    down = np.exp(-np.sum((tb[1:] - tb[:-1]) ** 2, -1, keepdims=True) * 9.0)
    np.testing.assert_allclose(w[0], right, rtol=1e-6)
    np.testing.assert_allclose(w[1], right, rtol=1e-6)  # the left pairs, seen from the other pixel
    np.testing.assert_allclose(w[2], down, rtol=1e-6)
    np.testing.assert_allclose(w[3], down, rtol=1e-6)
    # the literal reading of Eq. 10: the same weights on I_b = T^-1(T(I_b)) (mu-law, mu = 16)
    hdr = np.sign(tb) * np.expm1(np.abs(tb) * np.log1p(16.0)) / 16.0
    wh = [np.asarray(v) for v in G.first_order_weights(jnp.asarray(tb), dataclasses.replace(CFG, weights_domain="hdr"))]
    np.testing.assert_allclose(wh[0], np.exp(-np.sum((hdr[:, 1:] - hdr[:, :-1]) ** 2, -1, keepdims=True) * 9.0),
                               rtol=1e-5)
    with pytest.raises(ValueError, match="weights_domain"):
        dataclasses.replace(CFG, weights_domain="log")


def test_residual_block_reading_changes_the_function_not_the_parameters():
    """``res_act_after_sum=False`` (Fig. 4's one LReLU per block) drops the LReLU after the skip sum:
    the same parameters, a different output where the sum is negative."""
    cfg = dataclasses.replace(CFG, widths=(4, 4, 4), res_blocks=1, g_width=4, input_skip=False)
    plain = dataclasses.replace(cfg, res_act_after_sum=False)
    p = G.init(jax.random.PRNGKey(0), cfg)
    assert jax.tree_util.tree_structure(p) == jax.tree_util.tree_structure(G.init(jax.random.PRNGKey(0), plain))
    x = jnp.asarray(np.random.default_rng(0).normal(size=(1, 4, 4, 8)), jnp.float32)
    block = lambda c: G.layers(c)["res"][0][1](p["res"]["0"], x)  # noqa: E731
    a, b = np.asarray(block(cfg)), np.asarray(block(plain))
    np.testing.assert_allclose(a, np.where(b > 0, b, 0.01 * b), rtol=1e-5, atol=1e-6)
    assert np.any(b < 0)


def test_postprocess_keeps_an_output_that_already_agrees_with_the_base():
    """Eq. 13 with out == base is the identity (tolerance 1e-5 relative: float32 blur ratios); a
    uniformly scaled output is scaled back to the base's local mean. Both properties hold for any
    kernel: a radius-7 Gaussian keeps the test's compile short (the paper's radius-45 kernel, 91
    shifted slices per axis, takes ~14 s to compile; the stability suite runs it)."""
    cfg = dataclasses.replace(CFG, pp_radius=7, pp_sigma=3.0)
    rng = np.random.default_rng(4)
    base = jnp.asarray(rng.gamma(1.0, 1.0, (40, 50, 3)).astype(np.float32))
    np.testing.assert_allclose(np.asarray(G.postprocess(base, base, cfg)), np.asarray(base), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(G.postprocess(base * 2.0, base, cfg)), np.asarray(base), rtol=1e-5)
    zero = jnp.zeros_like(base)  # guard: a black output stays black (no 0/0)
    assert bool(jnp.all(G.postprocess(zero, base, cfg) == 0))


def test_lambda_schedule_in_steps():
    """Eq. 14: 0 through epoch 5, then 0.1 x 1.1^(epoch - 5), capped at 2; an epoch is
    epoch_patches / train_batch autoencoder steps, i.e. twice that many trainer steps."""
    c = G.Config(epoch_patches=64, train_batch=8)  # 8 autoencoder steps = 16 trainer steps per epoch
    assert G.lambda_at(0, c) == 0.0 and G.lambda_at(5 * 16 - 1, c) == 0.0
    assert G.lambda_at(5 * 16, c) == pytest.approx(0.11)
    assert G.lambda_at(9 * 16, c) == pytest.approx(0.1 * 1.1 ** 5)
    assert G.lambda_at(10_000 * 16, c) == 2.0


def test_training_never_reads_a_reference():
    """The batch carries no reference; poisoning one in changes nothing (the loss is a function of
    the noisy inputs only)."""
    f = _frame(16, 16, seed=7, lead=(2,))
    params = G.init(jax.random.PRNGKey(2), CFG)
    clean = {**f, "lambda": np.float32(0.5)}
    poisoned = {**clean, "reference": np.full_like(f["color"], np.nan)}
    for group in ("autoencoder", "gbranch", None):
        a = float(G.loss(params, clean, CFG, group=group))
        b = float(G.loss(params, poisoned, CFG, group=group))
        assert np.isfinite(a) and a == b


@pytest.mark.slow  # 20 s: two full gradients
def test_groups_are_trained_separately():
    """The autoencoder's loss has no gradient on the G-branch (Eq. 10 holds G fixed) and Eq. 11 none
    on the autoencoder, so the alternating updates touch only their own group (the full-resolution
    head, `Config.head_width`, included: it belongs to the autoencoder)."""
    cfg = dataclasses.replace(CFG, head_width=4)
    f = {**_frame(16, 16, seed=8, lead=(2,)), "lambda": np.float32(1.0)}
    params = _nonzero_output(G.init(jax.random.PRNGKey(3), cfg))
    params["head"] = jax.tree_util.tree_map(lambda a: a + 0.1, params["head"])  # its last conv starts at 0
    ga = jax.grad(lambda p: G.loss(p, f, cfg, group="autoencoder"))(params)
    gg = jax.grad(lambda p: G.loss(p, f, cfg, group="gbranch"))(params)
    norm = lambda t: float(sum(jnp.sum(jnp.abs(v)) for v in jax.tree_util.tree_leaves(t)))  # noqa: E731
    assert norm(ga["gbranch"]) == 0.0 and norm(gg["data"]) + norm(gg["dec"]) + norm(gg["out"]) + norm(gg["head"]) == 0.0
    for k in ("data", "grad", "res", "dec", "out", "head"):
        assert norm(ga[k]) > 0, k
    assert norm(gg["gbranch"]) > 0
    assert set(G.param_groups(cfg)["autoencoder"]) | set(G.param_groups(cfg)["gbranch"]) == set(params)


def test_alternating_group_steps_learn_and_touch_only_their_own_group():
    """A learning check in the default run (a tiny network, seconds): the trainer's alternating
    steps (`jaxdenoise.train.make_stepper`, Sec. 4.3) on one batch lower both groups' losses, and a
    step of one group leaves the other's params exactly as they were."""
    from jaxdenoise import train
    from jaxdenoise.methods import get

    cfg = dataclasses.replace(CFG, widths=(4, 4, 4), res_blocks=1, g_width=4)
    method = get("gradnet", cfg)
    run = train.TrainConfig.for_method(method, learning_rate=1e-2, schedule="constant", clip_norm=None)
    batch = {**_frame(16, 16, seed=8, lead=(2,)), "lambda": np.float32(1.0)}
    params = _nonzero_output(G.init(jax.random.PRNGKey(3), cfg))
    groups = train.param_groups(method, run, params)
    state = train.State(params=params, opt_state=train.optimizer_state(groups, params))
    advance = train.make_stepper(method, run, groups)
    seen = {g.name: [] for g in groups}  # each group's loss at each of its steps (before the update)
    for _ in range(16):
        group = groups[state.step % len(groups)]
        prev = state.params
        value, ok = advance(state, batch)
        assert ok
        seen[group.name].append(value)
        for k in set(prev) - set(group.keys):  # exact: the other group, and FROZEN entries, untouched
            for a, b in zip(jax.tree_util.tree_leaves(prev[k]), jax.tree_util.tree_leaves(state.params[k])):
                np.testing.assert_array_equal(a, b)
    assert all(v[-1] < 0.95 * v[0] for v in seen.values()), seen


def test_fine_tuning_may_change_the_loss_but_not_the_model():
    """Weights given to `train(init_from=...)` must match the run's model config; the loss and its
    schedule (fields marked training-only) and the training data (``train_*``) may differ."""
    from jaxdenoise.checkpoint import config_to_dict
    from jaxdenoise.train import model_fields

    saved = config_to_dict(CFG)
    same_model = (dataclasses.replace(CFG, lambda_epochs=0, lambda_start=2.0, alpha=0.5, first_order=False),
                  dataclasses.replace(CFG, train_spps=(64, 256), train_crop=128))
    for cfg in same_model:
        assert model_fields(cfg, config_to_dict(cfg)) == model_fields(cfg, saved)
    for cfg in (dataclasses.replace(CFG, widths=(8, 16, 32)), dataclasses.replace(CFG, mu=8.0),
                dataclasses.replace(CFG, pp_sigma=10.0)):
        assert model_fields(cfg, config_to_dict(cfg)) != model_fields(cfg, saved)


def test_illegal_renders_are_found():
    """NaN anywhere or negative base radiance marks a render; signed gradients do not."""
    ok = {k: np.abs(v) for k, v in _frame(4, 4, seed=3).items()}
    signed = {**ok, "dx": -ok["dx"], "dy": -ok["dy"]}  # negative gradients are legal
    nan = {**ok, "normal": ok["normal"].copy()}
    nan["normal"][1, 2, 1] = np.nan
    neg = {**ok, "color": ok["color"].copy()}
    neg["color"][0, 0, 1] = -0.1
    inf = {**ok, "dy": ok["dy"].copy()}
    inf["dy"][3, 3, 0] = np.inf
    assert [G.is_illegal(r) for r in (ok, signed, nan, neg, inf)] == [False, False, True, True, True]


def test_dataset_from_a_folder_and_from_its_export_without_references(tmp_path, monkeypatch):
    """A data folder's renders with NaN or negative base radiance (which the EXR contract refuses)
    are dropped and counted, not an error; the kept renders export without the reference (GradNet
    never reads it) and train the same crops from the export (to float16 / 8-bit rounding); renders
    at other sampling rates are not training data."""
    from conftest import make_shot, synthetic_frame
    from jaxdenoise.pipeline import open_training_data

    monkeypatch.setenv("JAXDENOISE_CACHE", str(tmp_path / "cache"))
    fields = ("color", "dx", "dy", "albedo", "normal", "depth")
    for s in range(5):
        f = synthetic_frame(16, 16, seed=s, fields=fields)
        if s == 1:
            f = f.replace(color=np.where(np.arange(16)[:, None, None] == 3, np.nan, f.color).astype(np.float32))
        if s == 3:
            f = f.replace(color=f.color - 2.0)  # negative radiance
        (tmp_path / "data" / f"scene_{s}").mkdir(parents=True)
        make_shot(tmp_path / "data" / f"scene_{s}", np.ones((16, 16, 3), np.float32), {64: f, 16: f}, {"primal": "gpt"})
    cfg = dataclasses.replace(CFG, train_crop=8, train_batch=4)
    with pytest.warns(RuntimeWarning):
        ds = G.make_dataset(tmp_path / "data", cfg, progress=False)
    assert ds.dropped == {"renders": 5, "dropped": 2} and len(ds) == 3
    assert [f["shot"] for f in ds.frames] == ["scene_0", "scene_2", "scene_4"]
    summary = ds.export(tmp_path / "train.npz", n=100, whole=True, spps=(64,), leave_out=("reference",))
    assert summary["count"] == 3 and summary["left_out"] == ["reference"]
    with pytest.raises(ValueError, match="lacks.*reference"):
        open_training_data(tmp_path / "train.npz", ("dx", "dy", *G.FEATURES))
    with pytest.raises(ValueError, match="leave_out names.*'variance'"):
        ds.export(tmp_path / "x.npz", n=1, whole=True, leave_out=("variance",))
    ex = G.make_dataset(tmp_path / "train.npz", cfg, progress=False)
    assert ex.dropped == {"renders": 3, "dropped": 0} and len(ex) == 3 and "reference" not in ex.items
    a = G.batch(ds, 5, cfg, np.random.default_rng(0))
    b = G.batch(ex, 5, cfg, np.random.default_rng(0))
    assert a.keys() == b.keys() and "reference" not in b
    np.testing.assert_allclose(b["color"], a["color"], rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(b["normal"], a["normal"], atol=1 / 255)
    with pytest.raises(ValueError, match="no render at spp"):
        G.make_dataset(tmp_path / "train.npz", dataclasses.replace(cfg, train_spps=(256,)), progress=False)


def test_training_renders_must_hold_the_configured_primal(tmp_path, monkeypatch):
    """The base image of a GradNet training render is the G-PT primal (the header's ``primal``,
    data_gen --primal gpt; Guo et al. Sec. 5.1) unless the config says ``train_primal = "base"``: a
    folder of base renders (or of renders from before data_gen recorded it, when the base was the only
    I_b), or one mixing both, is refused with the fix named; an export carries the primals of its
    cache, and one written before exports recorded them is refused."""
    from conftest import make_shot, synthetic_frame

    monkeypatch.setenv("JAXDENOISE_CACHE", str(tmp_path / "cache"))
    fields = ("color", "dx", "dy", "albedo", "normal", "depth")
    f = synthetic_frame(16, 16, seed=0, fields=fields)
    for name, attrs in (("gpt", {"primal": "gpt"}), ("base", {"primal": "base"}), ("old", {})):
        (tmp_path / name / "scene_0").mkdir(parents=True)
        make_shot(tmp_path / name / "scene_0", np.ones((16, 16, 3), np.float32), {64: f}, attrs)
    cfg = dataclasses.replace(CFG, train_crop=8, train_batch=4)
    assert cfg.train_primal == "gpt" and len(G.make_dataset(tmp_path / "gpt", cfg, progress=False)) == 1
    for name in ("base", "old"):
        with pytest.raises(ValueError, match=r"I_b is \['base'\].*train_primal is 'gpt'.*--primal gpt"):
            G.make_dataset(tmp_path / name, cfg, progress=False)
        assert len(G.make_dataset(tmp_path / name, dataclasses.replace(cfg, train_primal="base"), progress=False)) == 1
    (tmp_path / "gpt" / "scene_1").mkdir()
    make_shot(tmp_path / "gpt" / "scene_1", np.ones((16, 16, 3), np.float32), {64: f}, {"primal": "base"})
    with pytest.raises(ValueError, match=r"I_b is \['base', 'gpt'\]"):
        G.make_dataset(tmp_path / "gpt", cfg, progress=False)
    ds = G.make_dataset(tmp_path / "base", dataclasses.replace(cfg, train_primal="base"), progress=False)
    assert ds.export(tmp_path / "base.npz", n=1, whole=True, leave_out=("reference",))["primals"] == ["base"]
    with pytest.raises(ValueError, match="train_primal is 'gpt'"):
        G.make_dataset(tmp_path / "base.npz", cfg, progress=False)
    z = dict(np.load(tmp_path / "base.npz"))
    summary = json.loads(bytes(z["summary"]).decode())
    del summary["primals"]
    z["summary"] = np.frombuffer(json.dumps(summary).encode(), np.uint8)
    np.savez(tmp_path / "older.npz", **z)
    with pytest.raises(ValueError, match="does not say which I_b"):
        G.make_dataset(tmp_path / "older.npz", dataclasses.replace(cfg, train_primal="base"), progress=False)
    with pytest.raises(ValueError, match="train_primal"):
        G.Config(train_primal="primal")


def test_an_overshooting_output_decodes_finite_with_a_finite_gradient():
    """T^-1 grows as 17^y: an output of 100 would overflow float32 (Inf, NaN gradient); `to_hdr`
    clamps it to T(HDR_MAX) first, for both compressions."""
    y = jnp.array([100.0, -100.0, 0.5, 0.0], jnp.float32)
    for cfg in (CFG, G.Config(compression="log")):
        hdr = G.to_hdr(y, cfg)
        assert bool(jnp.all(jnp.isfinite(hdr)))
        np.testing.assert_allclose(np.asarray(hdr[:2]), [G.HDR_MAX, -G.HDR_MAX], rtol=1e-4)
        # inside the clamp, Eq. 6 inverted by hand: ((1 + mu) ** y - 1) / mu, or exp(y) - 1 for log
        want = ((1 + cfg.mu) ** 0.5 - 1) / cfg.mu if cfg.compression == "mu-law" else math.expm1(0.5)
        np.testing.assert_allclose(float(hdr[2]), want, rtol=1e-6)
        g = jax.grad(lambda v: jnp.sum(G.to_hdr(v, cfg)))(y)
        assert bool(jnp.all(jnp.isfinite(g)))


@pytest.mark.slow  # two short training runs with validation (about 30 s); CI runs the slow set too
def test_unsupervised_selection_reads_no_reference(tmp_path, monkeypatch):
    """``select="loss"`` picks ``best/`` by the unsupervised validation loss (Eq. 7 at the schedule's
    end on whole validation frames): with every validation reference poisoned with NaN the same step
    is chosen and the losses are the same, while the reference scores (reported beside) become inf."""
    import json

    from conftest import fit, make_shot, synthetic_frame
    from jaxdenoise import train as T

    monkeypatch.setenv("JAXDENOISE_CACHE", str(tmp_path / "cache"))
    fields = ("color", "dx", "dy", "albedo", "normal", "depth")
    for part, seeds in (("data", range(3)), ("val", range(10, 12))):
        for s in seeds:
            (tmp_path / part / f"scene_{s}").mkdir(parents=True)
            f = synthetic_frame(16, 16, seed=s, fields=fields)
            make_shot(tmp_path / part / f"scene_{s}", np.abs(f.color), {64: f}, {"primal": "gpt"})
    cfg = dataclasses.replace(CFG, widths=(4, 4, 4), res_blocks=1, g_width=4, train_crop=8, train_batch=2)
    kw = dict(config=cfg, steps=5, val_data=str(tmp_path / "val"), validate_every=1, select="loss",
              learning_rate=1e-2, progress=False)
    fit("gradnet", tmp_path / "data", tmp_path / "clean", **kw)
    original = T.load_validation

    def poisoned(*a, **k):
        return [{**f, "reference": np.full_like(f["reference"], np.nan)} for f in original(*a, **k)]

    monkeypatch.setattr(T, "load_validation", poisoned)
    fit("gradnet", tmp_path / "data", tmp_path / "poisoned", **kw)
    a, b = (json.loads((tmp_path / r / "best" / "selection.json").read_text()) for r in ("clean", "poisoned"))
    assert a["select"] == "loss" and a["selected_step"] == b["selected_step"]
    assert [v["loss"] for v in a["validation"]] == [v["loss"] for v in b["validation"]]
    assert len({v["loss"] for v in a["validation"]}) > 1  # the loss moves: the choice is a real one
    assert all(math.isfinite(v["relmse"]) for v in a["validation"])
    assert all(v["relmse"] == math.inf for v in b["validation"])
    with pytest.raises(T.TrainError, match="no validation_loss"):
        fit("demc", tmp_path / "data", tmp_path / "x", steps=1, select="loss", val_data=str(tmp_path / "val"))
