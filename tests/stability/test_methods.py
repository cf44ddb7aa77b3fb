"""Every registered method on every stiff case (docs/architecture.md "Numerical stability").

Parametrized over `jaxdenoise.methods.names()` at collection time, so a method registered later is
covered without editing this file. The pass rule and the NaN/Inf policy are in ``cases.py``:
finite output of the input's shape with max |out| <= 100 (max |input| + 1), a finite gradient
w.r.t. the parameters for trainable methods, or the case's stated clear error.

Default run: the 8x8 float32 cases with gradients (one forward and one gradient compile per
method), 1x1 (forward) and the NaN/Inf cases (no compile). ``-m slow`` adds 7x5 and float16 and the
gradients on 1x1, 7x5 and float16. ``experiments/stability_report.py`` runs everything.
"""
from __future__ import annotations

import importlib
import re
import sys

import numpy as np
import pytest

from jaxdenoise import api
from jaxdenoise.methods import MethodError

from . import cases as C

registry = importlib.import_module("jaxdenoise.methods")  # (jaxdenoise.methods is shadowed by a function)
NAMES = registry.names()
FAST_GRAD_CASES = tuple(c for c in C.VALUE_CASES if c.size == (C.H, C.W) and c.dtype == np.float32)
SLOW_GRAD_CASES = tuple(c for c in C.VALUE_CASES if c not in FAST_GRAD_CASES)
# Each of these costs every method one more compile (tens of seconds for LBF on 2 cores): -m slow.
SLOW_CASES = ("size_7x5", "float16")


def _trainable_or_broken(name: str) -> bool:
    """Collection-time filter for gradient tests; a method that fails to load stays in (and fails)."""
    try:
        return C.is_trainable(name)
    except Exception:  # noqa: BLE001 - the failure is reported by the test itself
        return True


def _assert_unavailable_is_clear(name: str, why: str) -> None:
    assert isinstance(why, str) and len(why) > 10, f"{name}: requirements() must explain itself, got {why!r}"
    assert name in why or "pip install" in why, f"{name}: the reason should name the method or the fix: {why!r}"
    buffers, _ = C.CASE_BY_NAME["baseline"].buffers()
    with pytest.raises(MethodError, match=re.escape(why)):
        api.denoise(buffers, method=name)


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name, marks=pytest.mark.slow if c.name in SLOW_CASES else ())
                                  for c in C.CASES])
@pytest.mark.parametrize("name", NAMES)
def test_method_case(name, case):
    m = C.method(name)
    why = m.requirements()
    if why is not None:  # not skipped: the unavailability itself must be reported clearly
        _assert_unavailable_is_clear(name, why)
        return
    out = C.check_method(name, case, grad=case in FAST_GRAD_CASES)
    assert out.passed, (f"method '{name}', case '{case.name}' ({case.what}): {out.detail}  "
                        f"[rule: finite, |out| <= 100 (max |in| + 1), or {case.allowed.describe() if case.allowed else 'no error'}]")


@pytest.mark.slow
@pytest.mark.parametrize("case", SLOW_GRAD_CASES, ids=lambda c: c.name)
@pytest.mark.parametrize("name", [n for n in NAMES if _trainable_or_broken(n)])
def test_method_gradient_odd_cases(name, case):
    out = C.check_method(name, case, grad=True)
    assert out.passed, f"method '{name}', case '{case.name}': {out.detail} [rule: gradient finite]"


def test_catalogue_gives_every_buffer():
    # every case carries every buffer, so each method's needs() alone decides what it reads
    assert C._all_fields_present()
    for case in C.VALUE_CASES:
        b, ref = case.buffers()
        assert b.color.shape[:2] == case.size and ref.shape == b.color.shape
        assert np.dtype(b.color.dtype) == np.dtype(case.dtype)


def test_unavailable_method_reports_clearly(monkeypatch):
    """A method with a missing optional package (oidn without pyoidn) says so, naming the fix."""
    oidn = importlib.import_module("jaxdenoise.methods.oidn")
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # makes `import pyoidn` raise ImportError
    why = oidn.requirements()
    assert why is not None and "pyoidn" in why and "pip install" in why, why
    _assert_unavailable_is_clear("oidn", why)
