"""jaxdenoise.train: the generic loop (checkpoints, resume, weights, resolved config) on a tiny LBF
dataset written through the real EXR path."""
from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from jaxdenoise import checkpoint
from jaxdenoise.methods import lbf
from jaxdenoise.train import TrainConfig, TrainError, restore_like  # restore_like: checkpoint's, as TrainError

from conftest import fit, registered, synthetic_frame

CFG = lbf.Config(radius=2, prefilter=False, spike_removal=False, features=("normal", "albedo"),
                 train_spps=(4, 8), train_crop=8, train_scenes_per_step=2)


def write_rooms(root):
    """Two 10x10 scenes, spp 4 and 8, two noise instances each (also used by tests/test_interrupts.py)."""
    from jaxdenoise.io import write_buffers, write_image

    rng = np.random.default_rng(0)
    for s in range(2):
        d = root / f"scene_{s:03d}"
        d.mkdir(parents=True)
        yy, xx = np.mgrid[0:10, 0:10]
        ref = np.stack([0.2 + 0.05 * xx, 0.3 + 0.02 * yy, 0.5 + 0 * xx], -1).astype(np.float32) * (1 + s)
        write_image(d / "reference.exr", ref)
        for spp in (4, 8):
            for i in range(2):
                b = synthetic_frame(10, 10, seed=10 * s + i, spp=spp,
                                    fields=("color", "color_var", "normal", "normal_var", "albedo", "albedo_var"))
                col = np.maximum(ref * (1 + rng.normal(size=ref.shape) / np.sqrt(spp)), 0).astype(np.float32)
                write_buffers(d / f"spp{spp:04d}_{i:02d}.exr", b.replace(color=col, color_var=ref ** 2 / spp))
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_rooms(tmp_path_factory.mktemp("rooms"))


def _params(run):
    p, meta = checkpoint.load(run / "weights")
    return p, meta


def test_train_writes_weights_config_and_resumes_identically(dataset, tmp_path):
    full = fit("lbf", dataset, tmp_path / "full", steps=4, config=CFG, progress=False, checkpoint_every=2)
    assert full["steps_done"] == 4 and np.isfinite(full["final_loss"])  # exact step count
    resolved = json.loads((tmp_path / "full" / "train_config.json").read_text())
    assert resolved["config"]["train_spps"] == [4, 8] and resolved["train"]["optimizer"] == "rprop"  # exact

    part = fit("lbf", dataset, tmp_path / "part", steps=2, config=CFG, progress=False, checkpoint_every=2)
    assert part["steps_done"] == 2
    resumed = fit("lbf", dataset, tmp_path / "part", steps=4, config=CFG, progress=False, checkpoint_every=2,
                  resume=True)
    assert resumed["steps_this_run"] == 2 and resumed["steps_done"] == 4  # exact
    a, meta = _params(tmp_path / "full")
    b, _ = _params(tmp_path / "part")
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)  # same batches, same updates
    # the normalization statistics come from the training set and are not trained
    assert float(np.max(np.abs(a["norm"]["std"] - 1.0))) > 1e-3
    assert meta["method"] == "lbf" and checkpoint.config_from_dict(lbf.Config, meta["config"]) == CFG  # exact


def test_resume_with_other_config_fails(dataset, tmp_path):
    fit("lbf", dataset, tmp_path / "run", steps=1, config=CFG, progress=False)
    other = dataclasses.replace(CFG, hidden=(4,))
    with pytest.raises(TrainError, match="checkpoint is for"):
        fit("lbf", dataset, tmp_path / "run", steps=2, config=other, progress=False, resume=True)
    # a checkpoint saved before a config field existed (its default keeps the old behaviour) resumes
    cfile = tmp_path / "run" / "checkpoint" / checkpoint.CONFIG_FILE
    meta = json.loads(cfile.read_text())
    field = next(f.name for f in dataclasses.fields(lbf.Config) if getattr(CFG, f.name) == getattr(lbf.Config(), f.name))
    del meta["config"][field]
    cfile.write_text(json.dumps(meta))
    assert fit("lbf", dataset, tmp_path / "run", steps=2, config=CFG, progress=False, resume=True)["steps_this_run"] == 1


def test_missing_data_and_bad_optimizer_raise(tmp_path, dataset):
    with pytest.raises(FileNotFoundError, match="reference.exr"):
        fit("lbf", tmp_path, tmp_path / "out", steps=1, config=CFG, progress=False)
    with pytest.raises(TrainError, match="optimizer"):
        fit("lbf", dataset, tmp_path / "o2", steps=1, config=CFG, progress=False, optimizer="sgd")


def test_restore_like_checks_shapes():
    tmpl = {"a": np.zeros(3), "b": (np.zeros(2), {})}
    out = restore_like(tmpl, {"a": np.ones(3), "b": [np.ones(2)]})
    assert isinstance(out["b"], tuple) and out["b"][1] == {}  # structure of the template, exact
    with pytest.raises(TrainError, match="shape"):
        restore_like(tmpl, {"a": np.ones(4), "b": [np.ones(2)]})


def test_validation_keeps_the_best_params_and_resumes_its_record(dataset, tmp_path):
    from jaxdenoise.methods import get
    from jaxdenoise.train import load_validation, validate

    kw = dict(config=CFG, progress=False, checkpoint_every=2, validate_every=2, val_data=dataset, val_spps=[4])
    full = fit("lbf", dataset, tmp_path / "full", steps=4, **kw)
    steps = [v["step"] for v in full["validation"]]
    assert steps == [2, 4]  # every 2 steps; the end (step 4) is not scored twice
    best = min(full["validation"], key=lambda v: v["relmse"])
    assert full["best"]["step"] == best["step"] and full["best"]["relmse"] == best["relmse"]  # exact
    assert set(best["per_spp"]) == {"4"}  # val_spps honoured: one rate
    params, meta = checkpoint.load(tmp_path / "full" / "best")
    assert meta["steps"] == best["step"] and meta["validation"]["relmse"] == best["relmse"]
    # the stored params reproduce the stored score
    method = get("lbf", CFG)
    frames = load_validation(method, dataset, [4])
    assert len(frames) == 2 and all(f["file"].endswith("spp0004_00.exr") for f in frames)  # first instance
    rescored = validate(method, restore_like(params, params), frames)
    np.testing.assert_allclose(rescored["relmse"], best["relmse"], rtol=1e-6)
    assert "best validation RelMSE" in full["line"]
    # the whole curve beside best/ (past the step it holds) and weights/: what a weights README ships
    for folder in ("best", "weights"):
        curve = json.loads((tmp_path / "full" / folder / "selection.json").read_text())
        assert [v["step"] for v in curve["validation"]] == steps and curve["selected_step"] == best["step"]
        assert [v["relmse"] for v in curve["validation"]] == [v["relmse"] for v in full["validation"]]

    fit("lbf", dataset, tmp_path / "part", steps=2, **kw)
    resumed = fit("lbf", dataset, tmp_path / "part", steps=4, resume=True, **kw)
    assert [v["step"] for v in resumed["validation"]] == steps
    for a, b in zip(resumed["validation"], full["validation"]):
        np.testing.assert_allclose(a["relmse"], b["relmse"], rtol=1e-5)  # same params, same scores


def test_weight_average_is_the_ema_of_the_iterates_and_resumes(dataset, tmp_path):
    kw = dict(config=CFG, progress=False, checkpoint_every=1)

    def iterate(n):  # the same batches in every run: p0 (init) .. p3 are the iterates of one run
        fit("lbf", dataset, tmp_path / f"plain{n}", steps=n, **kw)
        return _params(tmp_path / f"plain{n}")[0]

    iterates = [iterate(n) for n in range(4)]
    expect = iterates[0]
    for p in iterates[1:]:
        expect = jax.tree_util.tree_map(lambda e, x: 0.5 * e + 0.5 * x, expect, p)
    val = dict(val_data=dataset, val_spps=[4], validate_every=3)
    full = fit("lbf", dataset, tmp_path / "ema", steps=3, ema=0.5, **kw, **val)
    got, _ = _params(tmp_path / "ema")
    for x, y in zip(jax.tree_util.tree_leaves(expect), jax.tree_util.tree_leaves(got)):
        np.testing.assert_allclose(y, x, rtol=1e-5, atol=1e-7)
    assert any(float(np.max(np.abs(np.asarray(a) - np.asarray(b)))) > 1e-6  # the average is not the last iterate
               for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(iterates[3])))
    rec = full["validation"][-1]
    assert set(rec["raw"]) == {"relmse", "relmse_geomean", "per_spp"} and rec["raw"]["relmse"] != rec["relmse"]
    # interrupted after step 2 and resumed: the checkpoint carries the average
    fit("lbf", dataset, tmp_path / "part", steps=2, ema=0.5, **kw)
    fit("lbf", dataset, tmp_path / "part", steps=3, ema=0.5, resume=True, **kw)
    for x, y in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(_params(tmp_path / "part")[0])):
        np.testing.assert_allclose(y, x, rtol=1e-5, atol=1e-7)
    with pytest.raises(TrainError, match="ema"):
        fit("lbf", dataset, tmp_path / "bad", steps=1, ema=1.0, **kw)


def test_validation_data_errors_name_the_folder_and_rate(dataset, tmp_path):
    from jaxdenoise.methods import get
    from jaxdenoise.train import load_validation

    with pytest.raises(TrainError, match=r"no validation render at spp \[16\]"):
        load_validation(get("lbf", CFG), dataset, [16])
    with pytest.raises(FileNotFoundError, match="no shot found"):
        fit("lbf", dataset, tmp_path / "o", steps=1, config=CFG, progress=False, val_data=tmp_path)
    with pytest.raises(TrainError, match="validate_every"):
        fit("lbf", dataset, tmp_path / "o2", steps=1, config=CFG, progress=False, validate_every=-1)


def test_cli_train_rejects_bad_validation_rates(capsys):
    from jaxdenoise.cli import main

    with pytest.raises(SystemExit):
        main(["train", "lbf", "--data", "d", "--out", "o", "--val-spps", "4,x"])
    assert "expected comma-separated integers" in capsys.readouterr().err


def test_fine_tuning_starts_from_the_given_weights_and_scores_them_first(dataset, tmp_path):
    from jaxdenoise.methods import get
    from jaxdenoise.train import load_validation, validate

    fit("lbf", dataset, tmp_path / "base", steps=2, config=CFG, progress=False)
    base, _ = checkpoint.load(tmp_path / "base" / "weights")
    tuned = fit("lbf", dataset, tmp_path / "tuned", steps=2, config=CFG, progress=False, validate_every=2,
                val_data=dataset, val_spps=[4, 8], init_from=tmp_path / "base" / "weights")
    assert [v["step"] for v in tuned["validation"]] == [0, 2]  # the starting weights are scored first
    method = get("lbf", CFG)
    start = validate(method, restore_like(base, base), load_validation(method, dataset, [4, 8]))
    np.testing.assert_allclose(tuned["validation"][0]["relmse"], start["relmse"], rtol=1e-6)
    out, _ = checkpoint.load(tmp_path / "tuned" / "weights")
    np.testing.assert_array_equal(out["norm"]["mean"], base["norm"]["mean"])  # frozen entries come along
    assert not np.allclose(out["net"]["0"]["w"], base["net"]["0"]["w"])  # and the network was trained from there
    # another network shape cannot start from these weights
    with pytest.raises(TrainError, match="trained with config"):
        fit("lbf", dataset, tmp_path / "o", steps=1, config=dataclasses.replace(CFG, hidden=(4,)),
            progress=False, init_from=tmp_path / "base" / "weights")


def test_a_cli_run_resolves_the_method_once(dataset, tmp_path, monkeypatch):
    """`jaxdenoise train` with validation, EMA and a resume: the registry is read once (the CLI's
    `methods.get`); initialisation, parameter groups, the step, validation and resume receive the
    resolved `Method`."""
    from jaxdenoise import methods
    from jaxdenoise.cli import main

    class Counting(dict):
        reads = 0

        def __getitem__(self, name):
            Counting.reads += 1
            return super().__getitem__(name)

    monkeypatch.setattr(methods, "_REGISTRY", Counting(methods._REGISTRY))  # restored after the test
    # "lbf" with the tiny config: the same Method as the tests above, so their compiled steps are reused
    methods.register("lbf", "jaxdenoise.methods.lbf", **dataclasses.asdict(CFG))
    args = ["train", "lbf", "--data", str(dataset), "--out", str(tmp_path / "run"), "--val-data", str(dataset),
            "--val-spps", "4", "--validate-every", "1", "--ema", "0.5", "--quiet"]
    assert main(args + ["--steps", "2"]) == 0 and Counting.reads == 1  # exact
    assert main(args + ["--steps", "3", "--resume"]) == 0 and Counting.reads == 2  # exact: one per run
    resolved = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert resolved["train"]["steps"] == 3 and resolved["train"]["optimizer"] == "rprop"  # CLI, then TRAIN default


def test_cli_trains_at_the_given_rates_and_selects_by_the_geometric_mean(dataset, tmp_path, monkeypatch):
    """``--train-spps`` sets the config's training rates (recorded with the weights); ``--select
    geomean`` picks best/ by the geometric mean of the validation RelMSE, recorded beside the mean."""
    from jaxdenoise import methods
    from jaxdenoise.cli import main

    monkeypatch.setattr(methods, "_REGISTRY", dict(methods._REGISTRY))  # restored after the test
    methods.register("lbf", "jaxdenoise.methods.lbf", **dataclasses.asdict(CFG))
    out = tmp_path / "run"
    assert main(["train", "lbf", "--data", str(dataset), "--out", str(out), "--val-data", str(dataset),
                 "--validate-every", "1", "--steps", "3", "--train-spps", "8", "--select", "geomean", "--quiet"]) == 0
    resolved = json.loads((out / "train_config.json").read_text())
    assert resolved["config"]["train_spps"] == [8] and resolved["train"]["select"] == "geomean"  # exact
    _, meta = checkpoint.load(out / "best")
    assert meta["config"]["train_spps"] == [8]  # the shipped config says which rates it saw
    curve = json.loads((out / "best" / "selection.json").read_text())
    assert curve["select"] == "relmse_geomean"
    vals = curve["validation"]
    for v in vals:  # both rates scored; the geometric mean is that of the frames' RelMSE
        assert set(v["per_spp"]) == {"4", "8"} and 0 < v["relmse_geomean"] <= v["relmse"]
    assert curve["selected_step"] == min(vals, key=lambda v: v["relmse_geomean"])["step"]
    with pytest.raises(TrainError, match="select must be one of"):
        dataclasses.replace(TrainConfig(), select="median")
    # --select geomean_halo: every record counts its halo pixels; best/ is the lowest geometric mean among
    # the validations with no more of them than the first
    out = tmp_path / "halo"
    assert main(["train", "lbf", "--data", str(dataset), "--out", str(out), "--val-data", str(dataset),
                 "--validate-every", "1", "--steps", "3", "--select", "geomean_halo", "--quiet"]) == 0
    curve = json.loads((out / "best" / "selection.json").read_text())
    vals = curve["validation"]
    assert curve["select"] == "relmse_geomean" and len(vals) == 3
    for v in vals:
        assert set(v["halo_per_spp"]) == set(v["per_spp"]) and v["halo"] == sum(v["halo_per_spp"].values()) >= 0
    ok = [v for v in vals if v["halo"] <= vals[0]["halo"]]
    assert curve["selected_step"] == min(ok, key=lambda v: v["relmse_geomean"])["step"]


def test_halo_selection_never_takes_a_validation_with_more_halo_pixels_than_the_first():
    from jaxdenoise.train import selectable

    first = {"halo": 3, "relmse_geomean": 0.1}
    assert selectable("geomean_halo", first, {"halo": 3}) and not selectable("geomean_halo", first, {"halo": 4})
    assert selectable("geomean", first, {"halo": 40})  # the other rules ignore the count
    assert selectable("geomean_halo", {"relmse_geomean": 0.1}, {"halo": 40})  # an older run's record: no count


# -- schedules, clipping, devices, imports -----------------------------------------------------------

def test_schedules_in_steps():
    from jaxdenoise.solvers.optim import schedule

    f = schedule("rampup_rsqrt", 1e-3, every=100, factor=10)
    # hand-computed: 1e-3 * 10 ** (t / 100 - 1) below 100 steps, 1e-3 * sqrt(100 / t) from there
    for t, want in ((0, 1e-4), (50, 1e-3 * 10 ** -0.5), (100, 1e-3), (400, 5e-4)):
        assert float(f(t)) == pytest.approx(want, rel=1e-5)
    g = schedule("step", 1e-4, every=736, factor=0.95)  # Guo 2019: 0.95 every other epoch
    assert float(g(735)) == pytest.approx(1e-4, rel=1e-6) and float(g(736)) == pytest.approx(0.95e-4, rel=1e-6)
    assert float(schedule("exponential", 1.0, every=10, factor=0.5)(20)) == pytest.approx(0.25, rel=1e-6)
    with pytest.raises(ValueError, match="unknown name 'cosine'"):
        schedule("cosine", 1e-3)


def test_clip_by_global_norm():
    from jaxdenoise.solvers.optim import clip_by_global_norm

    g = {"a": np.array([3.0, 0.0], np.float32), "b": np.array([[4.0]], np.float32)}
    clipped, norm = clip_by_global_norm(g, 1.0)
    assert float(norm) == pytest.approx(5.0, rel=1e-6)
    np.testing.assert_allclose(clipped["a"], [0.6, 0.0], rtol=1e-6)
    same, _ = clip_by_global_norm(g, 10.0)
    np.testing.assert_array_equal(same["b"], g["b"])  # under the bound: untouched
    zero, n0 = clip_by_global_norm({"a": np.zeros(2, np.float32)}, 1.0)
    assert float(n0) == 0.0 and np.all(np.isfinite(zero["a"]))


def test_schedule_reaches_training(dataset, tmp_path):
    s = fit("lbf", dataset, tmp_path / "sched", steps=2, config=CFG, progress=False, optimizer="adam",
            learning_rate=1e-3, schedule="rampup_rsqrt", schedule_every=4, schedule_factor=10.0, clip_norm=1.0)
    assert s["steps_done"] == 2 and np.isfinite(s["final_loss"])
    with pytest.raises(TrainError, match="needs optimizer 'adam'"):
        fit("lbf", dataset, tmp_path / "bad", steps=1, config=CFG, progress=False, optimizer="rprop",
            schedule="step")


_TRAIN_SCRIPT = """
import json, sys
sys.path.insert(0, {tests!r})
import jax
from jaxdenoise.methods import lbf
from conftest import fit
from test_train import CFG
s = fit("lbf", {data!r}, {out!r}, steps=3, config=CFG, progress=False, optimizer="adam", learning_rate=1e-2)
import jaxdenoise.checkpoint as ck
meta = ck.load({out!r} + "/checkpoint")[1]
print(json.dumps({{"devices": jax.local_device_count(), "history": meta["history"]}}))
"""


def _run(code: str, env_extra: dict) -> str:
    import os
    import subprocess
    import sys

    env = {**os.environ, "JAX_PLATFORMS": "cpu", **env_extra}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout.strip().splitlines()[-1]


@pytest.mark.slow  # two subprocesses that each compile the trainer: ~13 s (the default run's 10-minute budget)
def test_two_devices_give_the_same_loss_trajectory_as_one(dataset, tmp_path):
    """Data parallel over 2 forced CPU devices: the batch (2 scenes x 2 spp = 4 crops) is split in
    two, the gradients reduced by XLA; the 3-step loss history equals the single-device one within
    1e-5 relative (a different summation order of the same float32 terms)."""
    from pathlib import Path

    tests = str(Path(__file__).parent)
    one = json.loads(_run(_TRAIN_SCRIPT.format(tests=tests, data=str(dataset), out=str(tmp_path / "one")), {}))
    two = json.loads(_run(_TRAIN_SCRIPT.format(tests=tests, data=str(dataset), out=str(tmp_path / "two")),
                          {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}))
    assert one["devices"] == 1 and two["devices"] == 2
    np.testing.assert_allclose(two["history"], one["history"], rtol=1e-5)


def test_training_path_imports_without_openimageio_mitsuba_and_jaxopt():
    """A GPU machine may have none of them: block their import and take a training step."""
    code = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("OpenImageIO", "mitsuba", "drjit", "jaxopt"):
            raise ImportError("blocked: " + name)
sys.meta_path.insert(0, Block())
import numpy as np, jax
import jaxdenoise, jaxdenoise.train
from jaxdenoise.methods import get, lbf
from jaxdenoise.train import TrainConfig, make_optimizer, step_fn
cfg = lbf.Config(radius=1, prefilter=False, features=("normal",), train_spps=(4,), train_crop=6)
params = lbf.init(jax.random.PRNGKey(0), cfg)
tc = TrainConfig(optimizer="adam", learning_rate=1e-3)
state = make_optimizer(tc)[0](params)
r = np.random.default_rng(0)
f = lambda *s: r.uniform(0.1, 1, size=s).astype(np.float32)
batch = {"x": f(2, 6, 6, 8), "color": f(2, 6, 6, 3), "color_var": f(2, 6, 6, 3), "reference": f(2, 6, 6, 3),
         "spp": np.full(2, 4, np.float32), "guides": {"normal": f(2, 6, 6, 3)}, "guide_vars": {"normal": f(2, 6, 6, 1)}}
p, s, value, ok = step_fn(get("lbf", cfg), tc)(params, state, batch)
assert bool(ok) and np.isfinite(float(value))
assert not any(m.split(".")[0] in ("OpenImageIO", "mitsuba", "jaxopt") for m in sys.modules)
print("ok")
"""
    assert _run(code, {}) == "ok"


def test_parameter_groups_alternate_with_their_own_optimizers(tmp_path):
    """Step t updates group t mod 2 only, with its own Adam state and step size (a: 1e-2, b: 0.5);
    a resumed run equals an uninterrupted one (exact: the same jitted steps)."""
    import jax.numpy as jnp

    with registered("groups", "fake_groups"):
        fit("groups", tmp_path, tmp_path / "one", steps=1, progress=False, optimizer="adam",
                  learning_rate=1e-2)
        p1, _ = checkpoint.load(tmp_path / "one" / "weights")
        # step 0 moved a only, by Adam's first step (= lr in magnitude); b untouched
        np.testing.assert_allclose(p1["a"], 1 + 1e-2, rtol=1e-5)
        np.testing.assert_array_equal(p1["b"], np.ones(3))
        fit("groups", tmp_path, tmp_path / "two", steps=2, progress=False, optimizer="adam", learning_rate=1e-2)
        p2, meta = checkpoint.load(tmp_path / "two" / "checkpoint")
        np.testing.assert_allclose(p2["params"]["b"], 1 - 0.5, rtol=1e-5)  # group b's own step size
        assert set(p2["opt_state"]) == {"a", "b"}  # one optimizer state per group
        fit("groups", tmp_path, tmp_path / "res", steps=3, progress=False, optimizer="adam", learning_rate=1e-2,
            checkpoint_every=1)
        part = tmp_path / "part"
        fit("groups", tmp_path, part, steps=1, progress=False, optimizer="adam", learning_rate=1e-2)
        fit("groups", tmp_path, part, steps=3, progress=False, optimizer="adam", learning_rate=1e-2, resume=True)
        a, _ = checkpoint.load(tmp_path / "res" / "weights")
        b, _ = checkpoint.load(part / "weights")
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(x, y)
        assert float(jnp.sum(jnp.abs(jnp.asarray(a["norm"])))) == 0.0  # FROZEN: never trained


@pytest.mark.slow  # a training-scale check (the default run's 10-minute budget)
def test_small_conv_net_overfits_four_crops(tmp_path):
    """A small U-Net (jaxdenoise.nn) through the generic trainer memorizes 4 noisy -> clean crops:
    the loss falls by more than 100x in 400 Adam steps (measured: 166x)."""

    with registered("convnet", "fake_convnet"):
        fit("convnet", tmp_path, tmp_path / "run", steps=400, progress=False, optimizer="adam",
            learning_rate=3e-3, checkpoint_every=400)
    meta = checkpoint.load(tmp_path / "run" / "checkpoint")[1]
    first, last = meta["history"][0], float(np.mean(meta["history"][-5:]))
    assert last < first / 100, (first, last)


def test_a_tiny_conv_net_learns_its_crops(tmp_path):
    """The default run's learning check of the conv-net family (the 400-step overfit above is `slow`):
    a one-level U-Net of width 8 through the generic trainer lowers its loss on 4 fixed crops by
    more than 5x in 80 Adam steps."""
    import fake_convnet

    with registered("convnet", "fake_convnet"):
        fit("convnet", tmp_path, tmp_path / "run", config=fake_convnet.Config(widths=(8,)), steps=80,
            progress=False, optimizer="adam", learning_rate=1e-2, checkpoint_every=80)
    meta = checkpoint.load(tmp_path / "run" / "checkpoint")[1]
    first, last = meta["history"][0], float(np.mean(meta["history"][-5:]))
    assert last < first / 5, (first, last)
