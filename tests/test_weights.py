"""Tampered weights are refused with an error that says which file and what (issue: reliability):
a missing array, a wrong shape, a config for another method, NaN weights, a pickled object inside
the .npz, a damaged .npz, a config.json that is not JSON."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import jaxdenoise as jd
from jaxdenoise.checkpoint import WeightsError
from jaxdenoise.methods import MethodError

SHIPPED = "jaxdenoise/weights/lbf"


@pytest.fixture
def weights(tmp_path):
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    d = tmp_path / "w"
    shutil.copytree(root / SHIPPED, d)
    return d


def _rewrite(folder, change):
    with np.load(folder / "params.npz") as z:
        flat = {k: z[k] for k in z.files}
    change(flat)
    np.savez(folder / "params.npz", **flat)


def test_intact_copy_loads(weights):
    assert jd.load("lbf", weights).method.name == "lbf"


@pytest.mark.parametrize("case,change,message", [
    ("missing array", lambda f: f.pop("net/0/w"), r"entry 'net/0/w' is missing"),
    ("wrong shape", lambda f: f.__setitem__("net/0/w", np.zeros((3, 3), np.float32)),
     r"entry 'net/0/w' has shape \(3, 3\); expected \(36, 10\)"),
    ("NaN weights", lambda f: f["net/0/b"].__setitem__(0, np.nan), r"entry 'net/0/b' has 1 NaN/Inf value"),
    ("extra array", lambda f: f.__setitem__("net/9/w", np.zeros(2, np.float32)), r"unexpected entries \['net/9/w'\]"),
])
def test_tampered_arrays_are_refused(weights, case, change, message):
    _rewrite(weights, change)
    with pytest.raises(WeightsError, match=message):
        jd.load("lbf", weights)


def test_pickled_object_is_refused_not_unpickled(weights):
    def add_object(f):
        f["net/0/w"] = np.array([{"evil": 1}], dtype=object)

    with np.load(weights / "params.npz") as z:
        flat = {k: z[k] for k in z.files}
    add_object(flat)
    np.savez(weights / "params.npz", **flat)  # numpy pickles object arrays on save
    with pytest.raises(WeightsError, match=r"entry 'net/0/w' is a pickled object"):
        jd.load("lbf", weights)


def test_damaged_files_and_foreign_configs_are_refused(weights, tmp_path):
    (weights / "params.npz").write_bytes((weights / "params.npz").read_bytes()[:100])
    with pytest.raises(WeightsError, match=r"params.npz: not a readable .npz parameter file"):
        jd.load("lbf", weights)
    other = tmp_path / "w2"
    shutil.copytree(tmp_path / "w", other, dirs_exist_ok=True)
    from pathlib import Path

    shutil.copy(Path(__file__).resolve().parents[1] / SHIPPED / "params.npz", other / "params.npz")
    meta = json.loads((other / "config.json").read_text())
    meta["method"] = "poisson-l2"
    (other / "config.json").write_text(json.dumps(meta))
    with pytest.raises(WeightsError, match=r"weights are for method 'poisson-l2', not 'lbf'"):
        jd.load("lbf", other)
    meta["method"] = "lbf"
    meta["config"]["alpha"] = 0.2  # a poisson config key
    (other / "config.json").write_text(json.dumps(meta))
    with pytest.raises(WeightsError, match=r"config.json does not fit method 'lbf'.*unknown key\(s\) \['alpha'\]"):
        jd.load("lbf", other)
    (other / "config.json").write_text("{not json")
    with pytest.raises(WeightsError, match=r"config.json: not valid JSON"):
        jd.load("lbf", other)
    with pytest.raises(MethodError, match="no weights at"):
        jd.load("lbf", tmp_path / "nothing")
