"""Every shipped weight on a frame it never trained on (tests/data/golden, the built-in scene at
64x64): the score recorded when it was shipped (``jaxdenoise/weights/NAME/golden.json``, written by
``python tests/data/make_golden.py record NAME``), within the recorded relative tolerance, and the
recorded margin below the input. A zeroed, shuffled or identity weight file misses the recorded
score (measured with ``make_golden.py broken``: docs in tests/data/make_golden.py)."""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent / "data"))

import make_golden  # noqa: E402

from jaxdenoise.methods import get  # noqa: E402


def test_every_shipped_weight_has_a_golden_record():
    shipped = {n for n in make_golden.RATES}
    for name in ("lbf", "lbf-nlm", "demc", "demc-paper", "rae", "rae-paper", "gradnet"):
        folder = get(name).weights_dir
        assert (folder / "params.npz").is_file() and name in shipped
        assert (folder / "golden.json").is_file(), f"{folder}: run python tests/data/make_golden.py record {name}"


@pytest.mark.parametrize("name", list(make_golden.RATES))
def test_shipped_weight_reaches_its_recorded_score(name):
    folder = get(name).weights_dir
    rec = json.loads((folder / "golden.json").read_text())
    got = make_golden.score(name)
    same_file = hashlib.sha256((folder / "params.npz").read_bytes()).hexdigest() == rec["params_sha256"]
    hint = "" if same_file else " (params.npz changed since it was recorded: re-record it if the change is meant)"
    assert got["input_relmse"] == pytest.approx(rec["input_relmse"], rel=1e-6)  # the same golden frame
    assert got["relmse"] == pytest.approx(rec["relmse"], rel=rec["tolerance"]), f"{name}: {got} vs {rec}{hint}"
    assert got["relmse"] * rec["margin"] <= got["input_relmse"], f"{name}: {got}, margin {rec['margin']}"
