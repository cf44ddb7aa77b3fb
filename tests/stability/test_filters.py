"""Public filters and screened-Poisson solvers on the stiff cases (docs/architecture.md "Numerical stability").

Filters: every name in ``jaxdenoise.filters.__all__`` (minus helpers) must have an entry in
``cases.FILTERS`` (how to call it), so a filter added later fails `test_every_public_filter_is_covered`
until it is catalogued. Each runs on every case and on bandwidth parameters from 0 to 1e30 (and
inf, which must be refused naming the parameter); see ``cases.check_filter`` for the rule (finite,
inside the input's per-channel range for normalized filters, finite gradient w.r.t. the image and
the parameter).

Solvers: every ``jaxdenoise.solvers.poisson_*`` with alpha from 1e-6 to 1e6; with exact gradients
and with gradients that are exact up to 1e-4 noise, each must return the primal (tolerance
1e-2 (max |base| + 1)); alpha <= 0, inf, NaN and NaN/Inf inputs must be refused with a
`SolverError` naming the argument.
"""
from __future__ import annotations

import math

import numpy as np
import pytest


from . import cases as C

FILTER_NAMES = C.public_filters()
SOLVER_NAMES = C.public_solvers()
FAST = lambda c: c.size == (C.H, C.W) and c.dtype == np.float32  # noqa: E731 - one compile per filter
# Gradients are checked on the 8x8 float32 cases by default; on 1x1, 7x5 and float16 with -m slow.


def test_every_public_filter_is_covered():
    missing = sorted(set(FILTER_NAMES) - set(C.FILTERS))
    assert not missing, f"public filters without an entry in tests/stability/cases.py FILTERS: {missing}"
    assert FILTER_NAMES, "jaxdenoise.filters exports no filter"


def _tiered(cases):
    """8x8 float32, 1x1 and the bad-value cases by default; 7x5 and float16 (one more compile each)
    with -m slow."""
    return [pytest.param(c, id=c.name, marks=pytest.mark.slow if c.name in ("size_7x5", "float16") else ())
            for c in cases]


@pytest.mark.parametrize("case", _tiered(C.CASES))
@pytest.mark.parametrize("name", FILTER_NAMES)
def test_filter_case(name, case):
    out = C.check_filter(name, case, 1.0, grad=FAST(case))
    assert out.passed, f"filter '{name}', case '{case.name}' ({case.what}): {out.detail}"


@pytest.mark.slow
@pytest.mark.parametrize("case", [c for c in C.VALUE_CASES if not FAST(c)], ids=lambda c: c.name)
@pytest.mark.parametrize("name", FILTER_NAMES)
def test_filter_gradient_odd_cases(name, case):
    out = C.check_filter(name, case, 1.0, grad=True)
    assert out.passed, f"filter '{name}', case '{case.name}': {out.detail}"


@pytest.mark.parametrize("p", C.PARAM_VALUES + (C.PARAM_INF,), ids=lambda p: f"p={p:g}")
@pytest.mark.parametrize("case", ["baseline", "firefly_1e6"])
@pytest.mark.parametrize("name", FILTER_NAMES)
def test_filter_bandwidth_extremes(name, case, p):
    # a static parameter (remove_spikes' n_std) recompiles per value: its gradient w.r.t. the image
    # is checked once, in test_filter_case
    out = C.check_filter(name, C.CASE_BY_NAME[case], p, grad=not C.FILTERS[name].static_param)
    assert out.passed, f"filter '{name}', case '{case}', parameters {C.FILTERS[name].params} = {p}: {out.detail}"
    if not math.isfinite(p):
        assert out.status == C.CLEAR, f"filter '{name}' accepted a parameter of {p}"


def test_gaussian_default_radius_with_huge_sigma():
    # radius=None means ceil(3 sigma): sigma -> infinity must still give a finite blur (the
    # per-channel mean, tolerance 1e-5 relative) or a FilterError naming sigma / radius
    out = C.check_gaussian_default_radius(1e30)
    assert out.passed, out.detail


# == screened Poisson ============================================================================
# 8x8 float32 and 1x1 by default (one compile per solver and shape); 7x5 and float16 with -m slow.
FAST_SOLVER_CASES = ("baseline", "firefly_1e6", "black", "size_1x1")
SOLVER_PARAMS = [pytest.param(c, marks=() if c in FAST_SOLVER_CASES else pytest.mark.slow) for c in C.SOLVER_CASES]


@pytest.mark.parametrize("alpha", C.ALPHAS, ids=lambda a: f"alpha={a:g}")
@pytest.mark.parametrize("case", SOLVER_PARAMS)
@pytest.mark.parametrize("name", SOLVER_NAMES)
def test_solver_alpha(name, case, alpha):
    out = C.check_solver(name, C.CASE_BY_NAME[case], alpha, grad=True)
    assert out.passed, f"solver '{name}', case '{case}', alpha {alpha:g}: {out.detail}"


@pytest.mark.parametrize("gradients", ["exact", "near"])
@pytest.mark.parametrize("alpha", C.ALPHAS, ids=lambda a: f"alpha={a:g}")
@pytest.mark.parametrize("case", SOLVER_PARAMS)
@pytest.mark.parametrize("name", SOLVER_NAMES)
def test_solver_consistent_gradients_return_primal(name, case, alpha, gradients):
    out = C.check_solver(name, C.CASE_BY_NAME[case], alpha, gradients=gradients, primal_tol=1e-2)
    assert out.passed, f"solver '{name}', case '{case}', alpha {alpha:g}, {gradients} gradients: {out.detail}"


@pytest.mark.parametrize("alpha", C.BAD_ALPHAS, ids=lambda a: f"alpha={a:g}")
@pytest.mark.parametrize("name", SOLVER_NAMES)
def test_solver_refuses_bad_alpha(name, alpha):
    out = C.check_solver(name, C.CASE_BY_NAME["baseline"], alpha)
    assert out.status == C.CLEAR, f"solver '{name}', alpha {alpha}: {out.status}: {out.detail}"


@pytest.mark.parametrize("case", ["nan_color", "inf_color", "nan_dx"])
@pytest.mark.parametrize("name", SOLVER_NAMES)
def test_solver_refuses_nan_inputs(name, case):
    out = C.check_solver(name, C.CASE_BY_NAME[case], 1.0)
    assert out.status == C.CLEAR, f"solver '{name}', case '{case}': {out.status}: {out.detail}"
