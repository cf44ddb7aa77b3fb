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
from jaxdenoise.train import TrainError, restore_like, train

from conftest import synthetic_frame

CFG = lbf.Config(radius=2, prefilter=False, spike_removal=False, features=("normal", "albedo"),
                 train_spps=(4, 8), train_crop=8, train_scenes_per_step=2)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two 10x10 scenes, spp 4 and 8, two noise instances each."""
    from jaxdenoise.io import write_buffers, write_image

    root = tmp_path_factory.mktemp("rooms")
    rng = np.random.default_rng(0)
    for s in range(2):
        d = root / f"scene_{s:03d}"
        d.mkdir()
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


def _params(run):
    p, meta = checkpoint.load(run / "weights")
    return p, meta


def test_train_writes_weights_config_and_resumes_identically(dataset, tmp_path):
    full = train("lbf", dataset, tmp_path / "full", steps=4, config=CFG, progress=False, checkpoint_every=2)
    assert full["steps_done"] == 4 and np.isfinite(full["final_loss"])  # exact step count
    resolved = json.loads((tmp_path / "full" / "train_config.json").read_text())
    assert resolved["config"]["train_spps"] == [4, 8] and resolved["train"]["optimizer"] == "rprop"  # exact

    part = train("lbf", dataset, tmp_path / "part", steps=2, config=CFG, progress=False, checkpoint_every=2)
    assert part["steps_done"] == 2
    resumed = train("lbf", dataset, tmp_path / "part", steps=4, config=CFG, progress=False, checkpoint_every=2,
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
    train("lbf", dataset, tmp_path / "run", steps=1, config=CFG, progress=False)
    other = dataclasses.replace(CFG, hidden=(4,))
    with pytest.raises(TrainError, match="checkpoint is for"):
        train("lbf", dataset, tmp_path / "run", steps=2, config=other, progress=False, resume=True)


def test_missing_data_and_bad_optimizer_raise(tmp_path, dataset):
    with pytest.raises(FileNotFoundError, match="reference.exr"):
        train("lbf", tmp_path, tmp_path / "out", steps=1, config=CFG, progress=False)
    with pytest.raises(TrainError, match="optimizer"):
        train("lbf", dataset, tmp_path / "o2", steps=1, config=CFG, progress=False, optimizer="sgd")


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
    full = train("lbf", dataset, tmp_path / "full", steps=4, **kw)
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

    train("lbf", dataset, tmp_path / "part", steps=2, **kw)
    resumed = train("lbf", dataset, tmp_path / "part", steps=4, resume=True, **kw)
    assert [v["step"] for v in resumed["validation"]] == steps
    for a, b in zip(resumed["validation"], full["validation"]):
        np.testing.assert_allclose(a["relmse"], b["relmse"], rtol=1e-5)  # same params, same scores


def test_validation_data_errors_name_the_folder_and_rate(dataset, tmp_path):
    from jaxdenoise.methods import get
    from jaxdenoise.train import load_validation

    with pytest.raises(TrainError, match=r"no validation render at spp \[16\]"):
        load_validation(get("lbf", CFG), dataset, [16])
    with pytest.raises(FileNotFoundError, match="no shot found"):
        train("lbf", dataset, tmp_path / "o", steps=1, config=CFG, progress=False, val_data=tmp_path)
    with pytest.raises(TrainError, match="validate_every"):
        train("lbf", dataset, tmp_path / "o2", steps=1, config=CFG, progress=False, validate_every=-1)


def test_cli_train_rejects_bad_validation_rates(capsys):
    from jaxdenoise.cli import main

    with pytest.raises(SystemExit):
        main(["train", "lbf", "--data", "d", "--out", "o", "--val-spps", "4,x"])
    assert "expected comma-separated integers" in capsys.readouterr().err


def test_fine_tuning_starts_from_the_given_weights_and_scores_them_first(dataset, tmp_path):
    from jaxdenoise.methods import get
    from jaxdenoise.train import load_validation, validate

    train("lbf", dataset, tmp_path / "base", steps=2, config=CFG, progress=False)
    base, _ = checkpoint.load(tmp_path / "base" / "weights")
    tuned = train("lbf", dataset, tmp_path / "tuned", steps=2, config=CFG, progress=False, validate_every=2,
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
        train("lbf", dataset, tmp_path / "o", steps=1, config=dataclasses.replace(CFG, hidden=(4,)),
              progress=False, init_from=tmp_path / "base" / "weights")
