"""experiments/export_training.py: a method's training and validation exports within the budget
that travels to a device machine, with every rate and the whole-frame statistics."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import make_shot, synthetic_frame

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ("color", "normal", "position", "albedo", "albedo2")


def _script():
    spec = importlib.util.spec_from_file_location("export_training", ROOT / "experiments" / "export_training.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _folder(root: Path, scenes: int, seed: int) -> Path:
    for s in range(scenes):
        shot = root / f"scene_{s:04d}"
        shot.mkdir(parents=True)
        make_shot(shot, synthetic_frame(32, 32, seed=seed + s).color,
                  {spp: synthetic_frame(32, 32, seed=seed + 10 * s + spp, fields=FIELDS) for spp in (1, 4)})
    return root


def test_exports_fit_the_budget_with_every_rate_and_the_statistics(tmp_path, monkeypatch):
    from jaxdenoise.pipeline import load_export

    x = _script()
    monkeypatch.setenv("JAXDENOISE_CACHE", str(tmp_path / "cache"))  # not the user's cache
    lib, proc = _folder(tmp_path / "library_train", 2, 10), _folder(tmp_path / "rooms", 1, 50)
    val = _folder(tmp_path / "library_val", 1, 90)
    budget = x.repository_mib() + 3.0
    out = tmp_path / "export"
    assert x.main(["demc", "--train", str(lib), str(proc), "--val", str(val), "--spps", "1,4", "--crop", "16",
                   "--budget-mib", f"{budget}", "--out", str(out)]) == 0
    s = json.loads((out / "exports.json").read_text())
    assert s["train_shots"] == 3 and s["total_mib"] <= budget
    assert set(s["train"]["per_rate"]) == {"1", "4"} and s["val"]["per_rate"] == {"1": 1, "4": 1}
    tr = load_export(out / "train.npz")
    assert {"position_mean", "position_std"} <= set(tr.stats)  # whole-frame statistics travel
    assert s["train"]["count"] == len(np.asarray(tr.stats["position_mean"]))
    with pytest.raises(Exception, match="leave no room"):
        x.main(["demc", "--train", str(lib), "--val", str(val), "--spps", "1,4", "--budget-mib", "1",
                "--out", str(tmp_path / "e2")])
