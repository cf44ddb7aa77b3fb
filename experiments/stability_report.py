"""Run the numerical-stability catalogue and write ``docs/results/stability.md`` (+ ``.json``).

    python experiments/stability_report.py [--methods a,b] [--out docs/results/stability.md] [--no-grad]

Every registered method x every case of ``tests/stability/cases.py`` (gradients everywhere, unlike
the default test run, which leaves the 7x5 / float16 gradients to ``pytest -m slow``), every public
filter x case and x bandwidth parameter, every screened-Poisson solver x case x alpha. Each cell is
``ok``, ``clear error`` (the call refused the input with the stated error), ``unavailable`` (the
method cannot run here, with its reason) or ``FAIL`` (with the reason under the table). The catalogue
and the pass rule live in ``tests/stability/cases.py`` and are shared with the tests, so the report
and ``pytest tests/stability`` cannot disagree.
"""
from __future__ import annotations

import argparse
import datetime
import importlib
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the catalogue lives with the tests: tests/stability/cases.py

import jax  # noqa: E402
from tqdm import tqdm  # noqa: E402

from jaxdenoise.fsutil import write_json, write_text  # noqa: E402
from tests.stability import cases as C  # noqa: E402
from common import num  # noqa: E402

SYMBOL = {C.OK: "ok", C.CLEAR: "clear error", C.UNAVAILABLE: "unavailable", C.FAIL: "**FAIL**"}
WORST = [C.FAIL, C.UNAVAILABLE, C.CLEAR, C.OK]  # a cell that merges several runs shows the worst


def _merge(outcomes: list[C.Outcome]) -> C.Outcome:
    for status in WORST:
        hit = [o for o in outcomes if o.status == status]
        if hit:
            return hit[0]
    return C.Outcome(C.OK)


def _table(rows: dict[str, dict[str, list]], names: list[str], cols: list[str], first: str,
           partial: tuple[str, ...] = ()) -> tuple[str, list[str]]:
    """Markdown table of the JSON's ``{row: {column: [status, detail]}}`` plus the notes (every FAIL,
    clear error and unavailable reason, numbered). Every row of ``names`` has every column; a row
    of ``partial`` runs only some ("-" in the others)."""
    if set(rows) != set(names):
        raise ValueError(f"rows {sorted(rows)} are not the configured {sorted(names)}")
    notes: list[str] = []
    lines = [f"| {first} | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for name in names:
        cells = rows[name]
        if set(cells) - set(cols):
            raise ValueError(f"{name}: cells {sorted(set(cells) - set(cols))} outside the columns {cols}")
        out = []
        for col in cols:
            if name in partial and col not in cells:
                out.append("-")
                continue
            status, detail = cells[col]
            text = SYMBOL[status]
            if status != C.OK:
                notes.append(f"{name} / {col}: {status}: {detail.splitlines()[0] if detail else ''}")
                text += f" [{len(notes)}]"
            out.append(text)
        lines.append(f"| {name} | " + " | ".join(out) + " |")
    return "\n".join(lines), notes


def _notes(notes: list[str]) -> str:
    return "\n".join(f"{i}. {n.replace('|', '/')}" for i, n in enumerate(notes, 1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=None, help="comma-separated registered methods (default: all)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "results" / "stability.md"))
    ap.add_argument("--no-grad", action="store_true", help="skip the gradient checks (faster)")
    args = ap.parse_args(argv)

    registry = importlib.import_module("jaxdenoise.methods")
    names = registry.names() if args.methods is None else [s.strip() for s in args.methods.split(",") if s.strip()]
    grad = not args.no_grad
    filters = C.public_filters()
    solvers = C.public_solvers()
    config = {"methods": names, "filters": filters, "solvers": solvers, "grad": grad,
              "cases": [c.name for c in C.CASES], "filter_params": list(C.PARAM_VALUES) + [C.PARAM_INF],
              "alphas": list(C.ALPHAS), "bad_alphas": [str(a) for a in C.BAD_ALPHAS],
              "jax": jax.__version__, "python": platform.python_version(), "machine": platform.machine(),
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "command": "python experiments/stability_report.py" + (" " + " ".join(argv or sys.argv[1:])).rstrip()}

    total = (len(names) * len(C.CASES) + len(filters) * (len(C.CASES) + 2 * (len(C.PARAM_VALUES) + 1))
             + len(solvers) * (len(C.SOLVER_CASES) * len(C.ALPHAS) * 3 + len(C.BAD_ALPHAS) + 3))
    bar = tqdm(total=total, desc="stability", unit="run")
    t0 = time.perf_counter()

    m_rows: dict[str, dict[str, C.Outcome]] = {}
    for n in names:
        m_rows[n] = {}
        for case in C.CASES:
            bar.set_postfix_str(f"{n} / {case.name}")
            try:
                m_rows[n][case.name] = C.check_method(n, case, grad=grad)
            except Exception as e:  # noqa: BLE001 - a crash of the harness itself is a FAIL too
                m_rows[n][case.name] = C.Outcome(C.FAIL, f"harness: {type(e).__name__}: {e}")
            bar.update()

    f_rows: dict[str, dict[str, C.Outcome]] = {}
    p_rows: dict[str, dict[str, C.Outcome]] = {}
    for n in filters:
        f_rows[n], p_rows[n] = {}, {}
        for case in C.CASES:
            bar.set_postfix_str(f"{n} / {case.name}")
            f_rows[n][case.name] = C.check_filter(n, case, 1.0, grad=grad) if n in C.FILTERS else \
                C.Outcome(C.FAIL, "not catalogued in tests/stability/cases.py FILTERS")
            bar.update()
        for p in C.PARAM_VALUES + (C.PARAM_INF,):
            runs = []
            for cname in ("baseline", "firefly_1e6"):
                if n in C.FILTERS:
                    runs.append(C.check_filter(n, C.CASE_BY_NAME[cname], p,
                                               grad=grad and not C.FILTERS[n].static_param))
                bar.update()
            p_rows[n][f"{p:g}"] = _merge(runs) if runs else C.Outcome(C.FAIL, "not catalogued")

    if "gaussian" in filters:
        p_rows["gaussian (default radius)"] = {"1e+30": C.check_gaussian_default_radius(1e30)}

    s_rows: dict[str, dict[str, C.Outcome]] = {}
    s_bad: dict[str, dict[str, C.Outcome]] = {}
    for n in solvers:
        s_rows[n], s_bad[n] = {}, {}
        for cname in C.SOLVER_CASES:
            runs = []
            for alpha in C.ALPHAS:
                bar.set_postfix_str(f"{n} / {cname} / alpha {alpha:g}")
                for gradients in C.GRADIENTS:
                    o = C.check_solver(n, C.CASE_BY_NAME[cname], alpha, gradients=gradients,
                                       grad=grad and gradients == "rendered")
                    if o.status != C.OK:
                        o = C.Outcome(o.status, f"alpha {alpha:g}, {gradients} gradients: {o.detail}")
                    runs.append(o)
                    bar.update()
            s_rows[n][cname] = _merge(runs)
        for alpha in C.BAD_ALPHAS:
            s_bad[n][f"alpha={alpha}"] = C.check_solver(n, C.CASE_BY_NAME["baseline"], alpha)
            bar.update()
        for cname in ("nan_color", "inf_color", "nan_dx"):
            s_bad[n][cname] = C.check_solver(n, C.CASE_BY_NAME[cname], 1.0)
            bar.update()
    bar.close()
    seconds = time.perf_counter() - t0

    config["case_descriptions"] = {c.name: c.what + (f" (may refuse: {c.allowed.describe()})" if c.allowed else "")
                                   for c in C.CASES}
    raw = {"config": config, "seconds": seconds,
           "methods": {n: {c: [o.status, o.detail] for c, o in r.items()} for n, r in m_rows.items()},
           "filters": {n: {c: [o.status, o.detail] for c, o in r.items()} for n, r in f_rows.items()},
           "filter_params": {n: {c: [o.status, o.detail] for c, o in r.items()} for n, r in p_rows.items()},
           "solvers": {n: {c: [o.status, o.detail] for c, o in r.items()} for n, r in s_rows.items()},
           "solver_refusals": {n: {c: [o.status, o.detail] for c, o in r.items()} for n, r in s_bad.items()}}
    out = Path(args.out)
    write_json(out.with_suffix(".json"), raw)
    write_text(out, page(raw))
    cells = [cell for key in TABLES for row in raw[key].values() for cell in row.values()]
    n_fail = sum(status == C.FAIL for status, _ in cells)
    print(f"stability: {len(cells)} cells, {n_fail} FAIL, {seconds:.0f} s -> {out}")
    return 1 if n_fail else 0


TABLES = ("methods", "filters", "filter_params", "solvers", "solver_refusals")


def page(res: dict) -> str:
    """``stability.md`` from ``stability.json`` alone: the tables first, then the pass rule, the
    NaN/Inf policy and the cases (their descriptions as the run's catalogue stated them)."""
    config = res["config"]
    cases = config["cases"]
    cells = [cell for key in TABLES for row in res[key].values() for cell in row.values()]
    n_fail = sum(status == C.FAIL for status, _ in cells)
    m_table, m_notes = _table(res["methods"], config["methods"], cases, "method")
    f_table, f_notes = _table(res["filters"], config["filters"], cases, "filter")
    extra = sorted(set(res["filter_params"]) - set(config["filters"]))  # rows such as `gaussian (default radius)`
    p_table, p_notes = _table(res["filter_params"], config["filters"] + extra,
                              [f"{p:g}" for p in config["filter_params"]], "filter \\ p", partial=tuple(extra))
    solver_cases = [c for c in cases if any(c in r for r in res["solvers"].values())]
    s_table, s_notes = _table(res["solvers"], config["solvers"], solver_cases, "solver")
    refused = [f"alpha={a}" for a in config["bad_alphas"]] + [
        c for c in cases if any(c in r for r in res["solver_refusals"].values())]
    b_table, b_notes = _table(res["solver_refusals"], config["solvers"], refused, "solver")
    case_list = "\n".join(f"- `{c}`: {config['case_descriptions'][c]}" for c in cases)
    alphas = config["alphas"]

    return f"""# Numerical stability: every method, filter and solver on stiff inputs

Written by `{config['command']}` on {config['date']} (jax {config['jax']}, {config['machine']});
{len(cells)} cells, **{n_fail} FAIL**; {num(res['seconds'], '.0f')} s. Gradients {'checked' if config['grad'] else 'not checked'}.
The catalogue and the pass rule are `tests/stability/cases.py`, shared with `pytest tests/stability`
(the default test run leaves the 7x5 and float16 cases and the gradients on 1x1 to `pytest -m slow`).
Cells: **ok**, **clear error** (the call refused the input with the stated error), **unavailable**
(the method cannot run here, with its reason), **FAIL**: the rules are under *Pass rule* below.

## Methods (through `jaxdenoise.methods.get(name)`: `init` or shipped weights, `apply`, gradient)

{m_table}

{_notes(m_notes)}

## Filters on the cases (every bandwidth parameter = 1)

{f_table}

{_notes(f_notes)}

## Filters over bandwidth parameters p (cases `baseline` and `firefly_1e6`)

For `gaussian` p is sigma (0 = zero bandwidth); for the bilateral / NL-means family p is every
lambda = 1 / (2 theta^2) (0 = infinite bandwidth, 1e30 = zero bandwidth); for `remove_spikes` it is
`n_std`. p = inf must be refused naming the parameter. The row `gaussian (default radius)` calls
`gaussian(image, sigma)` without `radius` (default `ceil(3 sigma)`) at the one p it shows ("-": not
run): it must return the per-channel mean or refuse naming sigma / radius.

{p_table}

{_notes(p_notes)}

## Screened Poisson solvers, alpha in {', '.join(f'{a:g}' for a in alphas)}

Each cell merges the {len(alphas)} alphas and the three gradient sets (rendered, exact, near-exact).

{s_table}

{_notes(s_notes)}

## Screened Poisson solvers on refused inputs

{b_table}

{_notes(b_notes)}

## Pass rule

- **ok**: the output has the input's pixel grid, every value is finite and
  max |out| <= 100 (max |input| + 1); for trainable methods the gradient of RelMSE(apply(params,
  buffers), reference) w.r.t. the parameters is finite; for filters the output stays inside the
  input's per-channel range (normalized filters; tolerance 1e-5 (max |input| + 1), 1e-3 for float16)
  and the gradient w.r.t. the filtered buffer and the parameter is finite; for solvers, with exact
  gradients (and with gradients exact up to 1e-4 noise) the result returns the primal to
  1e-2 (max |base| + 1), and the gradient w.r.t. (base, dx, dy, alpha) is finite.
- **clear error**: the call raised the exception type the case allows and the message names the bad
  input (the footnote quotes it).
- **FAIL**: anything else (non-finite or absurd output, wrong shape, an unclear exception).

## NaN / Inf policy

`jaxdenoise.io.read_buffers` rejects NaN/Inf at read time (or repairs them by the documented
policy), and `jaxdenoise.denoise` / `jaxdenoise.load` check every buffer the method reads before
calling it (`BuffersError` naming the buffer and the count). A bare jitted `apply` cannot look at
values, so its behaviour on NaN/Inf is unspecified (NaN typically propagates); the NaN/Inf cases of
the method table therefore go through `jaxdenoise.denoise`: **clear error** when the method reads
the poisoned buffer, **ok** when it does not (the buffer is dropped and the output is finite).
Filters and solvers validate concrete (non-jitted) arguments themselves and must refuse NaN/Inf
with an error naming the argument; under `jit` they cannot, so callers validate first.

## Cases

{case_list}
"""


if __name__ == "__main__":
    sys.exit(main())
