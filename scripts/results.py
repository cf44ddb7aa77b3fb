"""The result pages' tables, written from the committed JSON (``docs/results/``).

A page keeps its prose by hand and its numbers here: every table between

    <!-- results: NAME -->
    ...
    <!-- /results -->

is what the renderer ``NAME`` below writes from the JSON it names; a study page an experiment writes
whole (``STUDIES``) is what that experiment's ``page(res)`` writes from its JSON; and every committed
``bench`` report (a folder with ``results.json`` + ``config.json``) has its ``results.md`` rewritten
from its records by `jaxdenoise.bench.report_markdown`. So a number on a page is a number in a JSON file,
and a page cannot keep a figure its data no longer has (``tests/test_results_pages.py`` runs
``--check`` in the default test run).

    python scripts/results.py            # rewrite every generated table and bench report
    python scripts/results.py --check    # exit 1, naming each page that differs from its JSON

An experiment that re-measures writes its JSON; this script then brings the pages up to date.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

RESULTS = ROOT / "docs" / "results"
EXPERIMENTS = ROOT / "experiments"
if str(EXPERIMENTS) not in sys.path:  # the experiments' shared helpers, imported as `common` as they do
    sys.path.insert(0, str(EXPERIMENTS))

from common import num  # noqa: E402  (one number formatter for every page: a hole is an error)
BLOCK = re.compile(r"<!-- results: (?P<name>[\w.-]+) -->\n(?P<body>.*?)<!-- /results -->", re.S)


class PageError(Exception):
    """A page names a table this script does not know, or a table's JSON lacks a value it reads."""


# -- reading and formatting -----------------------------------------------------------------------

def load(results: Path, rel: str) -> dict:
    path = results / rel
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise PageError(f"{path}: no such result file") from None
    except json.JSONDecodeError as e:
        raise PageError(f"{path}: not valid JSON ({e})") from None


def table(header: list[str], rows: list[list[str]], align: str | None = None) -> str:
    """A Markdown table; ``align`` one letter per column (l/r), default: first left, rest right."""
    align = align or "l" + "r" * (len(header) - 1)
    sep = ["---" if a == "l" else "---:" for a in align]
    return "\n".join("| " + " | ".join(r) + " |" for r in [header, sep] + rows)


def bold_min(cells: list[str], values: list[float]) -> list[str]:
    """Bold the cell holding the smallest value (ties: all of them)."""
    lo = min(values)
    return [f"**{c}**" if v == lo else c for c, v in zip(cells, values)]


def bold_max(cells: list[str], values: list[float]) -> list[str]:
    hi = max(values)
    return [f"**{c}**" if v == hi else c for c, v in zip(cells, values)]


def summary_row(summary: list[dict], method: str, spp: int, rel: str) -> dict:
    for r in summary:
        if r["method"] == method and r["spp"] == spp:
            return r
    raise PageError(f"{rel}: no summary row for method {method!r} at {spp} spp")


# -- renderers ------------------------------------------------------------------------------------

TABLES: dict[str, Callable[[Path], str]] = {}


def renderer(name: str):
    def register(fn):
        TABLES[name] = fn
        return fn
    return register


def bind(name: str, fn: Callable[..., str], *args) -> None:
    """Register ``name`` as the generic renderer ``fn`` on ``args`` (the JSON path, rows, columns)."""
    TABLES[name] = lambda results: fn(results, *args)


def bench_wide(results: Path, rel: str, methods: list[str], spps: list[int],
               skipped: tuple[tuple[str, int], ...] = ()) -> str:
    """Methods down, RelMSE and SSIM per rate across, from a bench report's summary; the best
    RelMSE and SSIM at each rate in bold. ``skipped``: (method, spp) cells the bench skipped on
    every frame (each must be in the report's ``skipped`` list, with its reason printed), shown
    as "-"."""
    report = load(results, rel)
    summary = report["summary"]
    reasons = {}
    for m, s in skipped:
        why = {r["reason"] for r in report["skipped"] if r["method"] == m and f"spp{s:04d}" in r["file"]}
        if not why or any(r["method"] == m and r["spp"] == s for r in summary):
            raise PageError(f"{rel}: {m} at {s} spp is not skipped on every frame")
        reasons[m, s] = "; ".join(sorted(why))
    cells = {(m, s): None if (m, s) in reasons else summary_row(summary, m, s, rel) for m in methods for s in spps}
    cols: list[list[str]] = []
    for s in spps:
        for key, fmt, pick in (("relmse", None, bold_min), ("ssim", ".4f", bold_max)):
            have = [m for m in methods if cells[m, s] is not None]
            vals = [cells[m, s][key] for m in have]
            bolded = dict(zip(have, pick([num(v) if fmt is None else num(v, fmt) for v in vals], vals)))
            cols.append([bolded.get(m, "-") for m in methods])
    header = ["method"] + [f"{s} spp {k}" for s in spps for k in ("RelMSE", "SSIM")]
    frames = {c["frames"] for c in cells.values() if c is not None}
    rows = [[m] + [c[i] for c in cols] for i, m in enumerate(methods)]
    notes = "".join(f" {m} at {s} spp: skipped by the bench ({why})." for (m, s), why in reasons.items())
    return table(header, rows) + f"\n\nFrames per cell: {', '.join(str(f) for f in sorted(frames))}.{notes}"


def bench_time(results: Path, rel: str, methods: list[str], spp: int) -> str:
    """Median time per frame, compile time and memory at one rate, from a bench report's summary."""
    summary = load(results, rel)["summary"]
    rows = []
    for m in methods:
        r = summary_row(summary, m, spp, rel)
        rows.append([m, num(1e3 * r["seconds"], ".1f"), num(r["compile_seconds"], ".2f"),
                     num(r["rss_peak_mb"], ".1f"), "-" if r.get("xla_mb") is None else num(r["xla_mb"], ".1f")])
    return table(["method", "time per frame (ms, median)", "compile (s)", "RSS peak MB", "XLA MB"], rows)


def network_speed(results: Path, rel: str) -> str:
    """One network step at the JSON's size against OIDN measured in the same run."""
    d = load(results, rel)
    w, h = d["size"]
    from bench_conv import oidn_gflop

    o, mm = d["oidn"], d["matmul_2048"]
    og = oidn_gflop(h, w)
    rows = [["OIDN (pyoidn)", num(1e3 * o["median_s"], ",.0f"), num(og, ".1f") + " (counted)",
             num(og / o["median_s"], ".3g"), "1", "-"]]
    for m, r in d["methods"].items():
        cells = [f"`{m}`", num(1e3 * r["median_s"], ",.0f"), num(r["gflop"], ".1f"), num(r["gflops"], ".3g"),
                 f"{num(r['vs_oidn'], '.2f')}x"]  # num first: it names a hole in the JSON
        need = r["gflop"] / o["median_s"]
        rows.append(cells + [f"{num(need, '.3g')} ({num(need / mm['gflops'], '.2f')})"])
    return (table([f"{w}x{h}, median of {d['runs']}", "ms", "GFLOP (XLA)", "GFLOP/s", "time / OIDN's",
                   "GFLOP/s to take OIDN's time (of the matmul's)"], rows)
            + f"\n\nPeak for reference: a 2048^3 float32 matmul in the same run, {num(mm['gflops'], '.0f')} GFLOP/s; "
            f"{d['cpus']} cores, jax {d['jax']}, load average {num(d['load_before'][0], '.1f')} before, "
            f"{num(d['load_after'][0], '.1f')} after. OIDN's operations are counted from its published U-Net "
            "(`experiments/bench_conv.py`, `oidn_gflop`: the model its `high` quality runs on colour + albedo + "
            "normal), a multiply-add as 2 as in XLA's count; the last column is the rate a network's own count "
            "would need to take OIDN's time, and that rate over the matmul's.")


# demc ---------------------------------------------------------------------------------------------

@renderer("demc-heldout")
def _demc_heldout(results: Path) -> str:
    return bench_wide(results, "bench_heldout_demc/results.json",
                      ["input", "gaussian", "bilateral", "lbf", "demc", "oidn"], [4, 16, 64])


@renderer("demc-rates-library")
def _demc_rates_library(results: Path) -> str:
    return bench_wide(results, "bench_demc_rates/library_eval/results.json",
                      ["input", "lbf", "demc-paper", "demc", "oidn"], [1, 4, 16, 64], skipped=(("lbf", 1),))


@renderer("demc-rates-heldout")
def _demc_rates_heldout(results: Path) -> str:
    return bench_wide(results, "bench_demc_rates/heldout/results.json",
                      ["input", "lbf", "demc-paper", "demc", "oidn"], [1, 4, 16, 64], skipped=(("lbf", 1),))


bind("demc-heldout-time", bench_time, "bench_heldout_demc/results.json", ["bilateral", "lbf", "demc", "oidn"], 4)


bind("demc-speed", network_speed, "network_speed.json")


@renderer("demc-ablation")
def _demc_ablation(results: Path) -> str:
    """The equal-budget variants (Sec. 4.4, Fig. 9-10): per seed at the first rate, means per rate."""
    d = load(results, "demc_ablation.json")
    names = {"demc": "DEMC", "nosn": "DEMC-noSN (no fusion sub-network)", "semc": "SEMC (one encoder)"}
    groups: dict[str, list[str]] = {}
    for key, s in d["scores"].items():
        if key not in ("main", "finetune"):  # the long runs, not the equal-budget variants
            groups.setdefault(s["variant"], []).append(key)
    spps = d["spp"]

    mean = lambda key, field, spp: _mean(d, key, field, spp)
    rows = []
    for variant, keys in groups.items():
        if variant not in names:
            raise PageError(f"demc_ablation.json: unknown variant {variant!r}")
        keys = sorted(keys)
        first = spps[0]
        rows.append([names[variant], " / ".join(num(mean(k, "relmse", first), ".3g") for k in keys),
                     " / ".join(num(mean(k, "ssim", first), ".4f") for k in keys)]
                    + [num(sum(mean(k, "relmse", s) for k in keys) / len(keys)) for s in spps]
                    + [num(sum(mean(k, "ssim", s) for k in keys) / len(keys), ".4f") for s in spps])
    return table(["variant", f"{spps[0]} spp RelMSE (seeds)", f"{spps[0]} spp SSIM (seeds)"]
                 + [f"mean {s} spp RelMSE" for s in spps] + [f"mean {s} spp SSIM" for s in spps], rows,
                 "lll" + "r" * (2 * len(spps)))


@renderer("demc-long-runs")
def _demc_long_runs(results: Path) -> str:
    """The main run and the shipped fine-tune scored by the same script as the variants."""
    d = load(results, "demc_ablation.json")
    rows = []
    for key, label in (("main", "main run"), ("finetune", "fine-tune of the main run (shipped)")):
        rows.append([label] + [f"{num(_mean(d, key, 'relmse', s))} / {num(_mean(d, key, 'ssim', s), '.4f')}"
                               for s in d["spp"]])
    return table(["weights"] + [f"{s} spp RelMSE / SSIM" for s in d["spp"]], rows)


def _mean(d: dict, key: str, field: str, spp: int) -> float:
    rs = [r[field] for r in d["scores"][key]["rows"] if r["spp"] == spp]
    if not rs:
        raise PageError(f"demc_ablation.json: {key} has no rows at {spp} spp")
    return sum(rs) / len(rs)


@renderer("demc-position-norm")
def _demc_position_norm(results: Path) -> str:
    d = load(results, "demc_position_norm.json")
    rows = []
    for key, r in sorted(d["runs"].items()):
        norm, seed = key.rsplit("_s", 1)
        rows.append([norm, seed, num(r["as rendered"]), num(r["rescaled"]), num(r["final_loss"], ".3f")])
    return (table(["position normalization", "seed", "validation RelMSE", "scene rescaled", "final loss"], rows)
            + f"\n\n{d['steps']} steps of {d['batch']} crops of {d['crop']}x{d['crop']} per run.")


# rae ----------------------------------------------------------------------------------------------

def rae_temporal(results: Path, rel: str) -> str:
    d = load(results, rel)
    methods = ["input", "gaussian", "oidn", "rae", "rae-per-frame"]
    by = {(r["sequence"], r["spp"], r["method"]): r for r in d["rows"]}
    keys = sorted({(r["sequence"], r["spp"]) for r in d["rows"]}, key=lambda k: (k[0], k[1]))
    rows = []
    for seq, spp in keys:
        def get(m, field):
            r = by.get((seq, spp, m))
            if r is None:
                raise PageError(f"{rel}: no row for {m} on {seq} at {spp} spp")
            return r[field]
        rel_v = [get(m, "relmse") for m in methods]
        tmp_v = [get(m, "temporal") for m in methods if m != "gaussian"]
        rows.append([seq, str(spp)] + bold_min([num(v, ".3g") for v in rel_v], rel_v)
                    + [" / ".join(num(v, ".3g") for v in tmp_v)]
                    + [" / ".join(num(get(m, "ssim"), ".3f") for m in ("input", "oidn", "rae"))])
    return table(["fly-through", "spp", "input", "gaussian", "OIDN", "rae (state carried)", "rae per frame",
                  "temporal error: input / OIDN / rae / per frame", "SSIM: input / OIDN / rae"], rows,
                 "lr" + "r" * 5 + "ll")


bind("rae-temporal", rae_temporal, "rae_temporal.json")


bind("rae-temporal-cbox", rae_temporal, "rae_temporal_cbox.json")


def rae_temporal_means(results: Path, rel: str, methods: list[str]) -> str:
    """Means over the fly-throughs of ``rel``, per rate (RelMSE, SSIM, temporal error) of ``methods``."""
    d = load(results, rel)
    spps = sorted({r["spp"] for r in d["rows"]})
    rows = []
    for s in spps:
        cells = []
        for field, spec in (("relmse", ".3g"), ("ssim", ".3f"), ("temporal", ".3g")):
            vals = []
            for m in methods:
                rs = [r[field] for r in d["rows"] if r["spp"] == s and r["method"] == m]
                if not rs:
                    raise PageError(f"{rel}: no {m} rows at {s} spp")
                vals.append(sum(rs) / len(rs))
            cells.append(" / ".join(num(v, spec) for v in vals))
        rows.append([str(s)] + cells)
    names = " / ".join(methods)
    return table(["spp", f"RelMSE: {names}", "SSIM", "temporal error"], rows, "rlll")


def rae_frames(results: Path, rel: str, methods: list[str]) -> str:
    """Per method and rate over the fly-throughs of ``rel``: the temporal error (mean over every frame
    pair, the median pair, the worst pair) beside twice the mean RelMSE (what two frames with
    independent errors of that size give) and the worst frame's RelMSE; and the colour level of the
    first frame (zero state for a recurrent method) and of the later ones (state carried): per
    channel, the median over those frames of all fly-throughs."""
    from statistics import median

    d = load(results, rel)
    rows = []
    for m in methods:
        for s in sorted({r["spp"] for r in d["rows"] if r["method"] == m}):
            rs = [r for r in d["rows"] if r["method"] == m and r["spp"] == s]
            if any("temporal_per_pair" not in r for r in rs):
                raise PageError(f"{rel}: {m} at {s} spp has no per-pair record (re-run experiments/rae_temporal.py)")
            pairs = [v for r in rs for v in r["temporal_per_pair"]]
            frames = [v for r in rs for v in r["relmse_per_frame"]]
            first = [r["level_per_frame"][0] for r in rs]
            later = [lv for r in rs for lv in r["level_per_frame"][1:]]
            rows.append([m, str(s), num(sum(pairs) / len(pairs), ".3g"), num(median(pairs), ".3g"),
                         num(max(pairs), ".3g"), num(2 * sum(frames) / len(frames), ".3g"), num(max(frames), ".3g")]
                        + ["/".join(num(median(lv[c] for lv in group), ".3f") for c in range(3))
                           for group in (first, later)])
    return table(["method", "spp", "temporal error", "median pair", "worst pair", "2 x RelMSE", "worst frame RelMSE",
                  "level, frame 0 (R/G/B)", "level, frames 1-6"], rows, "lr" + "r" * 7)


# the procedural fly-throughs (the paper-recipe weights, then registered as rae)
bind("rae-temporal-means", rae_temporal_means, "rae_temporal.json", ["input", "oidn", "rae", "rae-per-frame"])
# issue 34: the scene library's evaluation fly-throughs, the rate-general rae against the paper's recipe
bind("rae-rates-temporal", rae_temporal_means, "rae_rates/temporal.json",
     ["input", "oidn", "oidn+taa", "rae-paper", "rae-0.9.15", "rae-0.9.16", "rae-0.9.19", "rae-0.9.20", "rae-gain1.3",
      "rae-0.9.21", "rae-frames", "rae"])
bind("rae-rates-frames", rae_frames, "rae_rates/temporal.json",
     ["oidn", "oidn+taa", "rae-paper", "rae-0.9.15", "rae-0.9.16", "rae-0.9.19", "rae-0.9.20", "rae-gain1.3",
      "rae-0.9.21", "rae-frames", "rae", "rae-per-frame"])


@renderer("rae-outlier-clamp")
def _rae_outlier_clamp(results: Path) -> str:
    """The outlier clamp's choice on the validation fly-throughs (experiments/rae_rates.py clamp)."""
    d = load(results, "rae_rates/outlier_clamp.json")
    spps = sorted(next(iter(d["factors"].values()))["per_spp"], key=int)
    rows = []
    for f, r in sorted(d["factors"].items(), key=lambda kv: float(kv[0])):
        rows.append([("**" + f + "**" if f == d["chosen"] else f) + (" (off)" if float(f) == 0 else ""),
                     num(r["relmse_geomean"], ".4g")] + [num(r["per_spp"][s], ".4g") for s in spps]
                    + ["/".join(num(v, ".3f") for v in r["level"][s]) for s in spps])
    return (table(["factor", "geometric mean", *(f"RelMSE {s} spp" for s in spps),
                   *(f"level {s} spp (R/G/B)" for s in spps)], rows)
            + f"\n\nChosen (bold): the lowest geometric mean among the factors whose level moves by less than "
            f"{d['level_tolerance']:g} (every channel and rate) from the unclamped one. Weights `{d['init']}`, "
            f"validation `{d['val_data']}`. Command: `{d['command']}`.")


@renderer("rae-level-match")
def _rae_level_match(results: Path) -> str:
    """The level match at inference measured on the validation fly-throughs (experiments/rae_rates.py match)."""
    return _level_match_table(load(results, "rae_rates/level_match.json"))


@renderer("rae-level-match-0921")
def _rae_level_match_0921(results: Path) -> str:
    """The level match's gain limit re-chosen on 0.9.21's pipeline, the gain axis extended (rae_rates.py match)."""
    return _level_match_table(load(results, "rae_rates/match_0921/level_match.json"))


@renderer("rae-level-match-0922")
def _rae_level_match_0922(results: Path) -> str:
    """The level match re-chosen on every validation fly-through with the output cut as an axis (rae_rates.py match)."""
    return _level_match_table(load(results, "rae_rates/match_0922/level_match.json"))


def _level_match_table(d: dict) -> str:
    """A row per setting of an ``experiments/rae_rates.py match`` choice, with its rule."""
    spps = sorted(d["settings"]["off"]["per_spp"], key=int)
    rows = [[("**" + k + "**" if k == d["chosen"] else k), num(r["relmse_geomean"], ".4g")]
            + [num(r["per_spp"][s], ".4g") for s in spps]
            + ["/".join(num(v, ".3f") for v in r["level"][s]) for s in spps] + [num(r["level_distance"], ".3f")]
            for k, r in sorted(d["settings"].items(), key=lambda kv: (kv[1]["config"]["match_level"],
                                                                      kv[1]["config"].get("match_max_gain", 0),
                                                                      kv[1]["config"].get("match_output_cut", False)))]
    cut = any(r["config"].get("match_output_cut") for r in d["settings"].values())
    return (table(["setting (sigma px, gain limit)", "geometric mean", *(f"RelMSE {s} spp" for s in spps),
                   *(f"level {s} spp (R/G/B)" for s in spps), "largest distance from 1"], rows)
            + ("\n\nLabels: sS gG kK = sigma S px, gain limit G, the target's outliers cut at K x their 3x3 median; "
               "' o': the target also cut at K x the output's brightest neighbour (`match_output_cut`)." if cut else "")
            + f"\n\nChosen (bold): among the settings whose geometric mean is at most {d['relmse_tolerance']:g}x "
            f"off's and whose RelMSE at every rate is at most {d['rate_tolerance']:g}x off's there, the one with "
            f"the smallest largest level distance from 1; off unless that beats off's. Weights `{d['init']}`, "
            f"validation `{d['val_data']}`. Command: `{d['command']}`.")


@renderer("rae-exact-pixels")
def _rae_exact_pixels(results: Path) -> str:
    """Exact pixels kept or not, measured on the validation fly-throughs and single frames
    (experiments/rae_rates.py exact)."""
    d = load(results, "rae_rates/exact_pixels.json")
    rows = []
    for k, r in d["settings"].items():
        cells = [f"{num(f['relmse_geomean'], '.4g')} ({f['kept']:,} kept, {f['not_exact']} not exact)"
                 for f in (r["folders"][x] for x in d["folders"])]
        rows.append([("**" + k + "**" if k == d["chosen"] else k), num(r["relmse_geomean"], ".4g"), *cells])
    return (table(["setting", "geometric mean, every frame", *(f"`{x}`" for x in d["folders"])], rows,
                  "lr" + "r" * len(d["folders"]))
            + "\n\nSettings: off; the variance rule alone (`keep_exact`, window 0); the variance rule and the "
            "window rule with an N x N square (wN). Each folder: the geometric mean of its frames' RelMSE (the "
            "fly-throughs with the state carried), the pixels kept over its frames, and those kept whose input "
            "differs from the reference by more than 5 % in a channel. Chosen (bold): the lowest geometric mean over "
            f"every frame; off unless that beats off's. Weights `{d['init']}`. Command: `{d['command']}`.")


def _temporal_choice_table(d: dict, legend: str) -> str:
    """A setting's row per setting of an ``experiments/rae_rates.py`` temporal choice (``taa``, ``accumulate``):
    score and, per rate, RelMSE / temporal error / level; ``legend`` says what the labels mean."""
    spps = sorted(d["settings"]["off"]["per_spp"], key=int)
    halo = all("halo" in row for r in d["settings"].values() for row in r["rows"])  # recorded since 0.9.21
    rows = [[("**" + k + "**" if k == d["chosen"] else k), num(r["score"], ".4g")]
            + [f"{num(r['per_spp'][x]['relmse'], '.4g')} / {num(r['per_spp'][x]['temporal'], '.4g')} / "
               + "/".join(num(v, ".3f") for v in r["per_spp"][x]["level"]) for x in spps]
            + ([str(sum(row["halo"] for row in r["rows"]))] if halo else [])
            for k, r in d["settings"].items()]
    return (table(["setting", "score", *(f"{x} spp: RelMSE / temporal error / level R/G/B" for x in spps)]
                  + (["halo px"] if halo else []), rows, "lr" + "r" * (len(spps) + halo))
            + ("\n\nHalo px: pixels above 4x the reference's 9x9 maximum (`jaxdenoise.metrics.halo_pixels`), every "
               "pixel of every frame of the fly-throughs." if halo else "")
            + f"\n\nSettings: {legend} Per rate: the means over the validation fly-throughs (state carried) of their "
            "frames' mean RelMSE and of their temporal error, and the colour level of their frames after the first "
            "(per channel, the median over those frames of the median box-mean ratio over every lit pixel). Score: the "
            "geometric mean over fly-throughs and rates of sqrt(RelMSE x temporal error). Chosen (bold): the lowest "
            "score among the settings whose RelMSE at every rate is at most off's and whose level is at most "
            f"{d['level_slack']:g} further from 1 than off's (every rate and channel); off unless that beats off's. "
            f"{d['sequences']} sequences from "
            f"{', '.join(f'`{x}`' for x in d['folders'])}; weights `{d['init']}`. Command: `{d['command']}`.")


@renderer("rae-taa")
def _rae_taa(results: Path) -> str:
    """Temporal anti-aliasing settings measured on the validation fly-throughs (experiments/rae_rates.py taa)."""
    return _temporal_choice_table(load(results, "rae_rates/taa.json"), (
        "off, or aA wW tT = `taa_alpha` A (history capped at 1 / A frames), the clamp's W x W neighbourhood (0: no "
        "clamp), the tangent-plane tolerance T (a fraction of the depth; 0: no geometric test)."))


@renderer("rae-accumulate")
def _rae_accumulate(results: Path) -> str:
    """Input accumulation settings measured on the validation fly-throughs (experiments/rae_rates.py accumulate)."""
    return _temporal_choice_table(load(results, "rae_rates/accumulate/accumulate.json"), (
        "off, or sS tT cC = `accumulate_samples` S (a frame of n spp keeps at most S / n frames of history: at "
        "n >= S none, so those rows repeat off's), the tangent-plane tolerance T (a fraction of the depth), the "
        "history's clamp at C x the larger of the frame's level and its 3x3 maximum."))


@renderer("rae-background")
def _rae_background(results: Path) -> str:
    """Keeping the input on background pixels, measured on the validation fly-throughs (rae_rates.py background)."""
    return _temporal_choice_table(load(results, "rae_rates/background/background.json"), (
        "off, or on = `keep_background` (a pixel with a zero normal, the environment seen directly, keeps its "
        "input)."))


@renderer("rae-match-frames")
def _rae_match_frames(results: Path) -> str:
    """The level match over time, measured on the validation fly-throughs (rae_rates.py match-frames)."""
    return _temporal_choice_table(load(results, "rae_rates/match_frames/match-frames.json"), (
        "off (each frame's own gain), or fF tT = `match_frames` F (the match's target and its gain span at most F "
        "frames: a pixel whose input the accumulation averaged over n frames keeps F / n frames of gains), the "
        "tangent-plane tolerance T (a fraction of the depth; 0: no geometric test)."))


@renderer("rae-single-sample")
def _rae_single_sample(results: Path) -> str:
    """The outlier clamp without its floor on single-sample pixels, measured on the validation fly-throughs and
    single frames (rae_rates.py single-sample)."""
    d = load(results, "rae_rates/single_sample/single_sample.json")
    spps = sorted(d["settings"]["off"]["per_spp"], key=int)
    singles = sorted(d["settings"]["off"]["single"]["level"], key=int)
    rows = [[("**" + k + "**" if k == d["chosen"] else k), num(r["score"], ".4g")]
            + [f"{num(r['per_spp'][x]['relmse'], '.4g')} / " + "/".join(num(v, ".3f") for v in r["per_spp"][x]["level"])
               for x in spps]
            + [str(sum(row["halo"] for row in r["rows"])), num(r["single"]["relmse_geomean"], ".4g")]
            + ["/".join(num(v, ".3f") for v in r["single"]["level"][x]) + f" ({r['single']['halo'][x]})"
               for x in singles] + [str(r["halo_total"])]
            for k, r in d["settings"].items()]
    return (table(["setting", "fly-through score", *(f"fly-throughs {x} spp: RelMSE / level R/G/B" for x in spps),
                   "fly-through halo px", "single frames: geometric mean",
                   *(f"single {x} spp: level R/G/B (halo px)" for x in singles), "halo px in all"], rows,
                  "lr" + "r" * (len(spps) + len(singles) + 4))
            + "\n\nSettings: off, or rX = `outlier_rel_sd` X (a pixel of >= 2 spp whose relative standard error is at "
            "least X is cut at the outlier clamp's 8x its brightest neighbour, without the frame-level floor). "
            "Fly-throughs: as in the temporal choices on this page (means over the validation fly-throughs, state carried; the "
            "level of their frames after the first over every lit pixel; the score the geometric mean of sqrt(RelMSE x "
            "temporal error)). Single frames: the geometric mean of every frame's RelMSE, and per rate the surface "
            "level pooled over the folders (median over frames) and the surface halo pixels "
            f"(`{'`, `'.join(d['single_folders'])}`). Chosen (bold): among the settings whose fly-through RelMSE at "
            f"every rate and single-frame geometric mean are at most {d['relmse_tolerance']:g}x off's and whose levels "
            f"are at most {d['level_slack']:g} further from 1 than off's, the fewest halo pixels in all (ties: the "
            f"score); off unless that has fewer than off's. {d['sequences']} sequences from "
            f"{', '.join(f'`{x}`' for x in d['folders'])}; weights `{d['init']}`. Command: `{d['command']}`.")


@renderer("rae-match-frames-first")
def _rae_match_frames_first(results: Path) -> str:
    """The first grid of the level match over time: F frames of gains at every rate (replaced)."""
    return _temporal_choice_table(load(results, "rae_rates/match_frames/first/match-frames.json"), (
        "off, or fF tT = F frames of gains at every pixel, whatever the input accumulation averaged, the tangent-plane "
        "tolerance T (a version of `match_frames` measured and replaced: the field now counts the target's frames "
        "too)."))


@renderer("rae-accumulate-knee")
def _rae_accumulate_knee(results: Path) -> str:
    """The first accumulation grid: Karis's weights on the history's bilinear taps, no clamp (dropped)."""
    return _temporal_choice_table(load(results, "rae_rates/accumulate/knee/accumulate.json"), (
        "off, or aA tT kK = a history of at most 1 / A frames at every rate, the tangent-plane tolerance T, the "
        "history's four bilinear taps weighed by 1 / (1 + luminance / (K x the frame's level)) (a version of "
        "`accumulate_step` measured and replaced: these labels' fields no longer exist)."))


@renderer("rae-input-arms")
def _rae_input_arms(results: Path) -> str:
    """Issue 34's input transforms at an equal budget: the validation curve of each arm."""
    d = load(results, "rae_rates/arms.json")
    labels = {"power": "demodulated colour ^ 0.2 (the paper's)", "rate": "^ 0.2, plus the rate channel",
              "linear": "linear (the 0.2 power in the loss only)"}
    rows = []
    for arm, label in labels.items():
        for v in d["runs"][arm]["validation"]:
            rows.append([label, f"{v['step']:,}", num(v["relmse_geomean"], ".4g")]
                        + [num(v["per_spp"][s], ".4g") for s in ("1", "4", "16")])
    return table(["input", "step", "validation RelMSE (geometric mean)", "1 spp (mean)", "4 spp", "16 spp"], rows,
                 "lrrrrr") + "\n\n" + d["note"]


@renderer("rae-train-gpu")
def _rae_train_gpu(results: Path) -> str:
    d = load(results, "rae_train_gpu.json")
    rows = []
    for key, r in d["runs"].items():
        rows.append([key, r["variant"], str(r["seed"]), f"{r['steps']:,}", f"{r['crops_seen']:,}", f"{r['crop']}",
                     num(r["seconds"], ".0f"), f"{num(r['best']['relmse'], '.4g')} / {num(r['best']['ssim'], '.4f')} "
                     f"(step {r['best']['step']:,})"])
    return table(["run", "variant", "seed", "steps", "sequences seen", "crop", "seconds", "best validation RelMSE / SSIM"],
                 rows, "llrrrrrr")


@renderer("rae-ablation")
def _rae_ablation(results: Path) -> str:
    """The ablation runs compared at the step every run reached."""
    d = load(results, "rae_train_gpu.json")
    variants = {"full": "combined loss L_s + L_g + L_t, all inputs (the paper)",
                "spatial": "spatial loss L_s only, all inputs", "noaux": "combined loss, no auxiliary input"}
    step = d["studies"]["loss"]["step"]
    rows = []
    for short, label in variants.items():
        cells, ssims = [], []
        for seed in (0, 1):
            r = d["runs"][f"abl_{short}_s{seed}"]
            v = [x for x in r["validation"] if x["step"] == step]
            if not v:
                raise PageError(f"rae_train_gpu.json: abl_{short}_s{seed} has no validation at step {step}")
            cells.append(f"{num(v[0]['relmse'])} / {num(v[0]['ssim'], '.4f')}")
            ssims.append(v[0]["ssim"])
        rows.append([label] + cells + [num(sum(ssims) / 2, ".4f")])
    return table(["variant", "seed 0 RelMSE / SSIM", "seed 1 RelMSE / SSIM", "mean SSIM"], rows) + \
        f"\n\nAll at step {step:,}, validation on the 4 validation fly-throughs at 1 spp."


bind("rae-bench-time", bench_time, "bench_rae_test/results.json", ["gaussian", "oidn", "rae"], 1)


@renderer("rae-speed")
def _rae_speed(results: Path) -> str:
    d = load(results, "network_speed.json")
    r = d["methods"]["rae"]
    return (network_speed(results, "network_speed.json")
            + f"\n\n`rae`'s carried state at {d['size'][0]}x{d['size'][1]}: {num(r['state_mb'], '.0f')} MB.")


# lbf ----------------------------------------------------------------------------------------------

@renderer("lbf-claims")
def _lbf_claims(results: Path) -> str:
    """Claims (a) and (b): LBF against the best global setting of the same filter (searched at the
    trained rates only) and the input, at the trained rates and above them."""
    d = load(results, "lbf_heldout/lbf_eval.json")
    rows = []
    for p in d["per_spp"]:
        g = p.get("global_best")
        keys = ["input", "lbf", "lbf-nlm"] + (["global_best"] if g else [])
        rel_v = [p[k]["relmse"] for k in keys]
        cells = dict(zip(keys, bold_min([num(v) for v in rel_v], rel_v)))
        rows.append([str(p["spp"]), str(p["frames"]), cells["input"], cells.get("global_best", "-"),
                     f"`{g['setting']}`" if g else "-", cells["lbf"], cells["lbf-nlm"],
                     num(p["global_best"]["ssim"], ".4f") if g else "-", num(p["lbf"]["ssim"], ".4f"),
                     num(p["lbf-nlm"]["ssim"], ".4f")])
    return table(["spp", "frames", "input", "best global setting", "setting", "lbf", "lbf-nlm",
                  "SSIM global", "SSIM lbf", "SSIM lbf-nlm"], rows, "rrrrlrrrrr")


@renderer("lbf-ablation")
def _lbf_ablation(results: Path) -> str:
    d = load(results, "lbf_ablation.json")
    by: dict[tuple[str, str], list[dict]] = {}
    for r in d["results"]:
        by.setdefault((r["group"], r["variant"]), []).append(r)
    spps = [str(s) for s in d["test_spp"]]
    rows = []
    for (group, variant), rs in by.items():
        mean = lambda f: sum(f(r) for r in rs) / len(rs)
        rows.append([group, variant, str(len(rs)), num(mean(lambda r: r["test_relmse"]))]
                    + [num(mean(lambda r, s=s: r["test_relmse_by_spp"][s])) for s in spps]
                    + [num(mean(lambda r: r["test_ssim"]), ".4f")])
    return (table(["claim", "variant", "seeds", "RelMSE (all)"] + [f"RelMSE {s} spp" for s in spps] + ["SSIM"], rows,
                  "llr" + "r" * (len(spps) + 2))
            + f"\n\nInput RelMSE {num(d['input_relmse'])}; {d['steps']} RPROP steps per variant, "
            f"{len(d['train_scenes'])} training scenes, {d['test_frames']} held-out frames.")


@renderer("lbf-timing")
def _lbf_timing(results: Path) -> str:
    d = load(results, "lbf_timing.json")
    rows = []
    g = d["gaussian_sigma2"]["median_s"]
    named = [(f"`{m}`", r) for m, r in d["methods"].items()]
    named += [(f"`{m}` at commit {b['commit']} (a worktree of it, same frame)", r)
              for b in d.get("before", []) for m, r in b["methods"].items()]
    for m, r in named:
        rows.append([m, num(r["features"]["median_s"], ".2f"), num(r["filter"]["median_s"], ".2f"),
                     num(r["network"]["median_s"], ".3f"), f"**{num(r['total_median'], '.1f')}**",
                     f"{num(r['total_median'] / g, ',.0f')}x"])
    return (table([f"{d['width']}x{d['height']}, seconds (median of {d['runs']})", "features", "filter", "network",
                   "total", "vs a Gaussian blur"], rows)
            + f"\n\nThe Gaussian blur (sigma 2) of the same frame: {num(1e3 * g, '.1f')} ms. "
            f"Load average {num(d['load_avg_start'][0], '.1f')} at start, {num(d['load_avg_end'][0], '.1f')} at end.")


@renderer("lbf-bench")
def _lbf_bench(results: Path) -> str:
    return bench_wide(results, "bench_heldout/results.json", ["input", "gaussian", "bilateral", "nlm", "lbf", "lbf-nlm",
                                                              "oidn"], [4, 16, 64])


bind("lbf-bench-time", bench_time, "bench_heldout/results.json", ["bilateral", "nlm", "lbf", "lbf-nlm", "oidn"], 4)


# gradnet ------------------------------------------------------------------------------------------

@renderer("gradnet-eval")
def _gradnet_eval(results: Path) -> str:
    d = load(results, "gradnet_eval.json")
    methods = ["input", "poisson-l2", "poisson-l1", "gradnet", "gradnet-no-postprocess"]
    rows = []
    for spp in sorted(d["summary"], key=int):
        s = d["summary"][spp]
        rel_v = [s[m]["relmse"] for m in methods]
        ssim_v = [s[m]["ssim"] for m in methods]
        rc = bold_min([num(v) for v in rel_v], rel_v)
        sc = bold_max([num(v, ".3f") for v in ssim_v], ssim_v)
        rows.append([spp] + [f"{a} / {b}" for a, b in zip(rc, sc)])
    return table(["spp", "input", "poisson-l2", "poisson-l1", "gradnet", "gradnet, no post-process"], rows)


@renderer("gradnet-ratios")
def _gradnet_ratios(results: Path) -> str:
    d = load(results, "gradnet_eval.json")
    rows = []
    for spp in sorted(d["summary"], key=int):
        s = d["summary"][spp]
        per = [r for r in d["rows"] if str(r["spp"]) == spp]
        if len(per) != s["frames"]:
            raise PageError(f"gradnet_eval.json: {len(per)} frame rows at {spp} spp, summary says {s['frames']}")
        geo = math.exp(sum(math.log(r["poisson-l1"]["relmse"] / r["gradnet"]["relmse"]) for r in per) / len(per))
        rows.append([spp, f"{num(s['l2_over_gradnet'], '.1f')}x", f"{num(s['l1_over_gradnet'], '.2f')}x",
                     f"{num(geo, '.2f')}x",
                     f"{s['gradnet_wins_per_frame_l1']}, {s['gradnet_wins_per_frame_l2']} of {s['frames']}"])
    return table(["spp", "L2 / GradNet (mean)", "L1 / GradNet (mean)", "L1 / GradNet (geometric mean over frames)",
                  "frames where GradNet beats L1, L2"], rows)


def gradnet_eval_pairs(results: Path, column: str, runs: list[tuple[str, str]], ratios: bool) -> str:
    """`gradnet_eval.py` reports side by side, one row per (rate, report): mean RelMSE of the input,
    the solvers and GradNet (best in bold), with ``ratios`` GradNet's ratio to each solver, and the
    frames where GradNet beats L1, L2. ``runs``: (label, JSON path), the first report's rates."""
    methods = ["input", "poisson-l2", "poisson-l1", "gradnet"]
    loaded = [(label, load(results, rel)) for label, rel in runs]
    rows = []
    for spp in sorted(loaded[0][1]["summary"], key=int):
        for label, d in loaded:
            if spp not in d["summary"]:
                raise PageError(f"{column} {label!r}: no {spp}-spp summary")
            s = d["summary"][spp]
            vals = [s[m]["relmse"] for m in methods]
            extra = [f"{num(s['l1_over_gradnet'], '.2f')}x", f"{num(s['l2_over_gradnet'], '.2f')}x"] if ratios else []
            rows.append([spp, label] + bold_min([num(v) for v in vals], vals) + extra
                        + [f"{s['gradnet_wins_per_frame_l1']}, {s['gradnet_wins_per_frame_l2']} of {s['frames']}"])
    head = ["spp", column, *methods] + (["L1 / GradNet", "L2 / GradNet"] if ratios else [])
    head.append("frames where GradNet beats L1, L2")
    return table(head, rows, "ll" + "r" * (len(head) - 2))


# issue 35 item 1: the same validation frames with I_b the base paths' mean and the G-PT primal
bind("gradnet-primal", gradnet_eval_pairs, "I_b",
     [("base paths' mean", "gradnet_primal/val_base.json"), ("G-PT primal", "gradnet_primal/val_gpt.json")], False)
# issue 35 items 1 and 6: the 256x256 G-PT test frames, the shipped weights and the G-PT run at half
# and at the whole schedule (each chosen by the unsupervised loss)
bind("gradnet-test256", gradnet_eval_pairs, "gradnet weights",
     [("shipped (base-path data)", "gradnet_primal/test256_gpt_shipped.json"),
      ("G-PT run, 16,000 steps (unsupervised selection)", "gradnet_primal/test256_gpt_run.json"),
      ("G-PT run, 32,000 steps (unsupervised selection)", "gradnet_primal/test256_gpt_run32k.json")], True)
# issue 35 item 3: the G-PT run re-made and shipped (0.9.5), on the first 4 of those frames re-rendered
bind("gradnet-shipped-gpt", gradnet_eval_pairs, "gradnet weights",
     [("before 0.9.5 (base-path data, reference-selected)", "gradnet_primal/test256_gpt4_before.json"),
      ("0.9.5 (G-PT data, last step, loss-selected)", "gradnet_primal/test256_gpt4_shipped.json")], True)


# issue 35 item 6: all 10 of those test scenes rendered (0.9.9), the shipped weights
bind("gradnet-test256-10", gradnet_eval_pairs, "gradnet weights",
     [("0.9.5 (shipped), 10 frames", "gradnet_primal/test256_gpt10_shipped.json")], True)
# issue 35 item 6: the scene library's evaluation scenes with G-PT gradients (built differently from the
# training family), the 0.9.5 weights
bind("gradnet-library", gradnet_eval_pairs, "gradnet weights",
     [("0.9.5 (shipped)", "gradnet_library/eval_gpt.json")], True)


@renderer("gradnet-library-frames")
def _gradnet_library_frames(results: Path) -> str:
    """The library report frame by frame: RelMSE of the input, the solvers, GradNet with and without
    Eq. 13's post-process (best of the four methods in bold)."""
    d = load(results, "gradnet_library/eval_gpt.json")
    methods = ["input", "poisson-l2", "poisson-l1", "gradnet"]
    rows = []
    for r in sorted(d["rows"], key=lambda r: (int(r["spp"]), r["shot"])):
        vals = [r[m]["relmse"] for m in methods]
        rows.append([str(r["spp"]), r["shot"]] + bold_min([num(v, ".4g") for v in vals], vals)
                    + [num(r["gradnet-no-postprocess"]["relmse"], ".4g")])
    return table(["spp", "frame", *methods, "gradnet, no post-process"], rows, "ll" + "r" * 5)


@renderer("gradnet-remade")
def _gradnet_remade(results: Path) -> str:
    """The re-rendered frames and the re-made run against the first making of each, frame by frame:
    RelMSE then (the 10-frame reports) / now (the 4-frame ones), and the post-process's effect (Fig. 5)."""
    then_old = load(results, "gradnet_primal/test256_gpt_shipped.json")
    then_run = load(results, "gradnet_primal/test256_gpt_run32k.json")
    now_old = load(results, "gradnet_primal/test256_gpt4_before.json")
    now_new = load(results, "gradnet_primal/test256_gpt4_shipped.json")

    def by_key(d):
        return {(str(r["spp"]), r["shot"]): r for r in d["rows"]}

    t_old, t_run, n_old, n_new = map(by_key, (then_old, then_run, now_old, now_new))
    rows = []
    for key in sorted(n_new, key=lambda k: (int(k[0]), k[1])):
        if key not in t_old or key not in t_run or key not in n_old:
            raise PageError(f"gradnet-remade: frame {key[1]} at {key[0]} spp is missing from a report")
        pairs = [(t_old[key]["input"], n_old[key]["input"]), (t_old[key]["poisson-l1"], n_old[key]["poisson-l1"]),
                 (t_old[key]["gradnet"], n_old[key]["gradnet"]), (t_run[key]["gradnet"], n_new[key]["gradnet"])]
        rows.append([key[0], key[1]] + [f"{num(a['relmse'], '.4g')} / {num(b['relmse'], '.4g')}" for a, b in pairs]
                    + [num(n_new[key]["gradnet-no-postprocess"]["relmse"], ".4g")])
    return table(["spp", "frame", "input", "poisson-l1", "gradnet, base-path weights", "gradnet, G-PT run",
                  "G-PT run, no post-process (now)"], rows, "ll" + "r" * 5)


@renderer("gradnet-equal-time")
def _gradnet_equal_time(results: Path) -> str:
    """Every method on G-PT and plain renders, ordered by total time (render + denoise, medians)."""
    rows = load(results, "gradnet_equal_time/rows.json")["rows"]
    out = []
    for r in sorted(rows, key=lambda r: r["render_seconds"] + r["seconds"]):
        out.append([r["method"], str(r["spp"]), str(r["frames"]), num(r["relmse"]), num(r["ssim"], ".4f"),
                    num(r["render_seconds"], ".3f"), num(r["seconds"], ".3f"),
                    num(r["render_seconds"] + r["seconds"], ".3f")])
    return table(["method", "spp", "frames", "RelMSE", "SSIM", "render s", "denoise s", "total s"], out)


bind("gradnet-speed", network_speed, "gradnet_speed.json")


@renderer("gradnet-multispp")
def _gradnet_multispp(results: Path) -> str:
    d = load(results, "gradnet_multispp_curve.json")
    v = d["validation"]
    spps = sorted(v[0]["per_spp"], key=int)
    best = min(v, key=lambda r: r["relmse"])
    rows = [[f"{len(v)} validations, steps {v[0]['step']:,}-{v[-1]['step']:,} (range)"]
            + [f"{num(min(r['per_spp'][s] for r in v), '.3g')}-{num(max(r['per_spp'][s] for r in v), '.3g')}"
               for s in spps],
            [f"best (step {best['step']:,})"] + [num(best["per_spp"][s], ".3g") for s in spps]]
    return table(["16/64/256-spp training, validation RelMSE"] + [f"{s} spp" for s in spps], rows) + \
        f"\n\nStopped at step {d['stopped_at_step']:,}."


@renderer("gradnet-loss-optimum")
def _gradnet_loss_optimum(results: Path) -> str:
    rows = []
    for rel in ("gradnet_loss_optimum_test16.json", "gradnet_loss_optimum.json", "gradnet_loss_optimum_test64.json",
                "gradnet_loss_optimum_test256.json"):
        d = load(results, rel)
        m = d["mean"]
        keys = [k for k in ("input", "optimum_alpha1", "optimum_alpha0.2", "poisson-l1") if k in m]
        rows.append([f"`{rel}`", str(d["spp"]), str(len(d["rows"]))] +
                    [num(m[k]) if k in m else "-" for k in ("input", "optimum_alpha1", "optimum_alpha0.2", "poisson-l1")])
        if not keys:
            raise PageError(f"{rel}: no mean scores")
    return table(["frames", "spp", "count", "input", "loss optimum (alpha 1)", "loss optimum (alpha 0.2)", "poisson-l1"],
                 rows, "lrrrrrr")


def ablation_curves(results: Path, rel: str) -> str:
    """Validation RelMSE of every variant of one ``gradnet_ablation.py`` study at every validation."""
    d = load(results, rel)["results"]
    steps = sorted({v["step"] for r in d.values() for v in r["validation"]})
    rows = []
    for name, r in d.items():
        by = {v["step"]: v["relmse"] for v in r["validation"]}
        rows.append([name] + [num(by[s]) if s in by else "-" for s in steps])
    last = steps[-1]
    vals = [next((v["relmse"] for v in r["validation"] if v["step"] == last), math.inf) for r in d.values()]
    for row, v in zip(rows, vals):
        if v == min(vals):
            row[-1] = f"**{row[-1]}**"
    return table(["variant"] + [f"step {s:,}" for s in steps], rows)


bind("gradnet-ablation", ablation_curves, "gradnet_ablation/ablation.json")


bind("gradnet-decoder", ablation_curves, "gradnet_decoder/ablation.json")


@renderer("gradnet-ablation-seeds")
def _gradnet_ablation_seeds(results: Path) -> str:
    """The loss study over three seeds: each seed's last validation, and the seed mean at each."""
    studies = [load(results, f"{folder}/ablation.json")["results"]
               for folder in ("gradnet_ablation", "gradnet_ablation_seed1", "gradnet_ablation_seed2")]
    rows = []
    for name in studies[0]:
        curves = []
        for i, st in enumerate(studies):
            if name not in st:
                raise PageError(f"seed {i}'s study lacks the variant {name!r}")
            curves.append({v["step"]: v["relmse"] for v in st[name]["validation"]})
        steps = sorted(set.intersection(*(set(c) for c in curves)))
        mean = [sum(c[s] for c in curves) / len(curves) for s in steps]
        rows.append([name] + [num(c[steps[-1]]) for c in curves] + [" / ".join(num(m) for m in mean)])
    return table(["variant", "seed 0", "seed 1", "seed 2", f"seed mean, steps {' / '.join(f'{s:,}' for s in steps)}"],
                 rows, "lrrrl") + f"\n\nSeeds' columns: validation RelMSE at step {steps[-1]:,}."


def seeded_study(results: Path, rel: str, column: str) -> str:
    """A ``gradnet_ablation.py --seeds`` study: each variant's last validation per seed, and the
    seed mean per rate."""
    d = load(results, rel)["results"]
    variants: dict[str, list[dict]] = {}
    for r in d.values():
        variants.setdefault(r["variant"], []).append(r)
    seeds = sorted({r["seed"] for r in d.values()})
    rows, means = [], []
    for name, runs in variants.items():
        if sorted(r["seed"] for r in runs) != seeds:
            raise PageError(f"{rel}: {name!r} lacks a seed of {seeds}")
        last = [sorted(r["validation"], key=lambda v: v["step"])[-1] for r in sorted(runs, key=lambda r: r["seed"])]
        if len({v["step"] for v in last}) != 1:
            raise PageError(f"{rel}: {name!r} ends at different steps across seeds")
        spps = sorted(last[0]["per_spp"], key=int)
        mean = sum(v["relmse"] for v in last) / len(last)
        means.append(mean)
        rows.append([name] + [num(v["relmse"]) for v in last] + [num(mean)]
                    + [num(sum(v["per_spp"][k] for v in last) / len(last)) for k in spps])
    for row, m in zip(rows, means):
        if m == min(means):
            row[len(seeds) + 1] = f"**{row[len(seeds) + 1]}**"
    return table([column] + [f"seed {s}" for s in seeds] + ["seed mean"] + [f"mean, {k} spp" for k in spps], rows) + \
        f"\n\nValidation RelMSE (mean over the frames at every rate) at step {last[0]['step']:,}, the run's last."


# issue 35 item 2: the two open readings; item 6: Fig. 12 and Fig. 17 on G-PT renders
bind("gradnet-readings", seeded_study, "gradnet_readings/ablation.json", "reading")
bind("gradnet-loss-gpt", seeded_study, "gradnet_ablation_gpt/ablation.json", "variant")


@renderer("gradnet-pixels")
def _gradnet_pixels(results: Path) -> str:
    """Issue 35 item 4: pixels per step against the learning rate at equal wall time, each variant's
    validation at the end of its budget."""
    d = load(results, "gradnet_pixels/ablation.json")
    rows, means = [], []
    for name, r in d["results"].items():
        last = sorted(r["validation"], key=lambda v: v["step"])[-1]
        spps = sorted(last["per_spp"], key=int)
        means.append(last["relmse"])
        rows.append([name, f"{r['pixels_per_step']:,}", f"{r['steps']:,}", num(r["seconds"], ".0f"),
                     num(last["relmse"]), num(last["relmse_geomean"])] + [num(last["per_spp"][k]) for k in spps])
    for row, m in zip(rows, means):
        if m == min(means):
            row[4] = f"**{row[4]}**"
    return table(["variant", "pixels a step", "steps in the budget", "seconds", "validation RelMSE (mean)",
                  "geometric mean"] + [f"{k} spp" for k in spps], rows)


@renderer("gradnet-converged")
def _gradnet_converged(results: Path) -> str:
    d = load(results, "gradnet_ablation_converged/ablation.json")["results"]
    rows = []
    for name, r in d.items():
        v = r["validation"]
        late = sorted(x["relmse"] for x in v if x["step"] >= 12000)
        if not late:
            raise PageError(f"gradnet_ablation_converged: {name} has no validation from step 12,000")
        med = late[len(late) // 2] if len(late) % 2 else (late[len(late) // 2 - 1] + late[len(late) // 2]) / 2
        rows.append([name, f"{num(r['best']['relmse'])} ({r['best']['step']:,})", num(med),
                     f"{num(v[-1]['relmse'])} ({v[-1]['step']:,})"])
    return table(["validation RelMSE, 64 spp (8 frames)", "best (step)", "median, steps 12,000 on", "last (step)"], rows)


TRIED = [("gradnet_eval.json", "shipped: L_all, 64x64 crops, 32,000 steps, 256 renders at 64 spp, seed 0"),
         ("gradnet_eval_no_first_order.json", "L_data + L_grad, full schedule (Fig. 12's other arm)"),
         ("gradnet_eval_seed1_L_all.json", "L_all, full schedule, seed 1"),
         ("gradnet_eval_x3_data.json", "3x the training renders (stopped at step 17,400)"),
         ("gradnet_eval_crop128.json", "128x128 crops at the same pixel budget, 8,000 steps"),
         ("gradnet_eval_crop128_14k.json", "128x128 crops continued to 14,000 steps"),
         ("gradnet_eval_ema.json", "weight average (EMA 0.999) of the main run")]


@renderer("gradnet-tried")
def _gradnet_tried(results: Path) -> str:
    """Every trained variant's best-validation weights on the same test frames."""
    rows = []
    l1 = None
    for rel, label in TRIED:
        s = load(results, rel)["summary"]
        spps = sorted(s, key=int)
        l1 = l1 or [s[x]["poisson-l1"]["relmse"] for x in spps]
        rows.append([label] + [num(s[x]["gradnet"]["relmse"]) for x in spps]
                    + [num(s[spps[-1]]["gradnet-no-postprocess"]["relmse"])])
    rows.append(["`poisson-l1`"] + [num(v) for v in l1] + ["-"])
    return table(["weights (best validation step)"] + [f"{x} spp" for x in spps] + [f"{spps[-1]} spp, no post-process"],
                 rows)


# filters and solvers -------------------------------------------------------------------------------

@renderer("filters-poisson-goals")
def _filters_poisson_goals(results: Path) -> str:
    """The filters / Poisson goals against the measurements of their pages' JSON (quiet runs)."""
    f = load(results, "bench_filters.json")
    w, h = f["size"]
    ours, gauss = f["ours"], f["gaussian"]
    l2 = load(results, "poisson_l2_quiet/poisson.json")["records"]
    dct = [r for r in l2 if r.get("table") == "l2" and r["solver"] == "dct"]
    cg = {r["alpha"]: r for r in l2 if r.get("table") == "l2" and r["solver"].startswith("cg")}
    pair = {r["impl"]: r["seconds"] for r in l2 if r.get("table") == "dct"}
    med = sorted(r["seconds"] for r in dct)
    dct_median = med[len(med) // 2] if len(med) % 2 else (med[len(med) // 2 - 1] + med[len(med) // 2]) / 2
    worst_res = max(r["residual"] for r in dct)
    small = min(dct, key=lambda r: r["alpha"])
    l1 = load(results, "poisson_l1_radmm/poisson.json")["records"]
    l1 = [r for r in l1 if r.get("table") == "l1"]
    preset = next(r for r in l1 if r["solver"] == "irls" and r["irls_iters"] == 20 and r["cg_iters"] == 50)
    converged = [r for r in l1 if r["energy_gap"] <= 1e-3]
    fastest = min(converged, key=lambda r: r["seconds"]) if converged else None
    admm = [r for r in converged if r["solver"] == "admm"]
    admm = min(admm, key=lambda r: r["seconds"]) if admm else None
    setting = lambda r: (f"{r['irls_iters']}x{r['cg_iters']}" if r["solver"] == "irls"  # noqa: E731
                         else f"{r['iters']} iterations")
    rows = [
        [f"cross-bilateral {2 * f['radius'] + 1}x{2 * f['radius'] + 1}, 5 features, {w}x{h}", "<= 3.4 s",
         f"{'met' if ours['median_s'] <= 3.4 else '**missed**'}: {num(ours['median_s'], '.1f')} s wall, "
         f"{num(ours['median_cpu_s'], '.0f')} s CPU (median of {f['runs']})",
         f"Gaussian on the same frame {num(gauss['median_s'], '.3f')} s; materializing filter "
         f"({f['small']['size'][0]}x{f['small']['size'][1]}): ours {num(f['naive_small']['median_s'] / f['ours_small']['median_s'], '.1f')}x faster",
         "`filters.md`"],
        [f"cross-bilateral memory at {w}x{h}", "fits comfortably",
         f"{num(ours['temp_bytes'] / 2**20, ',.0f')} MiB of XLA temporaries",
         f"the weight tensor alone would be {num(f['target']['materialized_weight_tensor_bytes'] / 2**20, ',.0f')} MiB",
         "`filters.md`"],
        ["L2 by DCT at 1280x720", "<= 25 ms, residual <= 1e-5 at alpha 1e-6..1e6",
         f"residual at most {num(worst_res, '.1e')} ({'met' if worst_res <= 1e-5 else '**missed**'}); "
         f"{num(1e3 * dct_median, '.1f')} ms, the median of the per-alpha medians "
         f"({'met' if dct_median <= 0.025 else '**missed**'}; range {num(1e3 * med[0], '.1f')}-{num(1e3 * med[-1], '.1f')} ms)",
         f"jaxopt CG at alpha {small['alpha']:g}: {num(cg[small['alpha']]['seconds'] / small['seconds'], '.0f')}x the "
         f"DCT's time, residual {num(cg[small['alpha']]['residual'], '.1e')}; `jax.scipy.fft.dctn` pair "
         f"{num(pair['jax.scipy.fft.dctn'] / pair['jaxdenoise dct_apply (2-D Makhoul)'], '.1f')}x ours",
         "`poisson_l2_quiet/poisson.md`"],
        ["L1 at 1280x720, alpha 0.2", "<= 2 s at energy gap <= 1e-3 (issue 37; Guo et al. Sec. 6.7: 0.67 s on a GPU)",
         (f"{'met' if fastest['seconds'] <= 2.0 else '**missed**'}: {fastest['solver']} {setting(fastest)}, "
          f"{num(fastest['seconds'], '.2f')} s at energy gap {num(fastest['energy_gap'], '.1e')}" if fastest
          else "**missed**: no setting reached an energy gap of 1e-3"),
         f"IRLS 20x50 preset {num(preset['seconds'], '.1f')} s at gap {num(preset['energy_gap'], '.1e')}"
         + (f"; plain ADMM at or below 1e-3: {setting(admm)}, {num(admm['seconds'], '.1f')} s" if admm else ""),
         "`poisson_l1_radmm/poisson.md`"],
    ]
    return table(["what", "goal", "measured", "peer in the same run", "page"], rows, "lllll")


# baselines for the network issues ------------------------------------------------------------------

BASELINE_METHODS = ["input", "lbf", "demc", "rae", "gradnet", "oidn"]


def baseline(results: Path, rel: str) -> str:
    """RelMSE (SSIM) per method and rate of a bench report; a method that did not run at a rate
    shows "-" only where the report's ``skipped`` list says why (e.g. LBF at 1 spp: no variance)."""
    d = load(results, rel)
    summary, skipped = d["summary"], d["skipped"]
    spps = sorted({r["spp"] for r in summary})
    methods = [m for m in BASELINE_METHODS if any(r["method"] == m for r in summary)]
    rows = []
    for m in methods:
        cells = []
        for s in spps:
            r = next((x for x in summary if x["method"] == m and x["spp"] == s), None)
            if r is None:
                if not any(k["method"] == m for k in skipped):
                    raise PageError(f"{rel}: no {m} row at {s} spp and no skipped entry saying why")
                cells.append("-")
            else:
                cells.append(f"{num(r['relmse'])} ({num(r['ssim'], '.3f')})")
        rows.append([m] + cells)
    for j, s in enumerate(spps):  # bold the lowest RelMSE per rate
        vals = [next((x["relmse"] for x in summary if x["method"] == m and x["spp"] == s), math.inf) for m in methods]
        lo = min(vals)
        for i, v in enumerate(vals):
            if v == lo:
                rows[i][j + 1] = f"**{rows[i][j + 1]}**"
    frames = sorted({r["frames"] for r in summary})
    return table(["method"] + [f"{s} spp" for s in spps], rows) + \
        f"\n\nRelMSE (SSIM), mean over frames ({', '.join(str(f) for f in frames)} per cell)."


bind("baseline-library-eval", baseline, "bench_library_eval/results.json")


bind("baseline-heldout", baseline, "bench_heldout_all/results.json")


def baseline_sequences(results: Path, rel: str) -> str:
    """Per method and rate of a bench report's fly-throughs: RelMSE (SSIM) mean over every frame of
    every sequence, and the temporal error (`jaxdenoise.metrics.temporal_error`) mean over the
    sequences; the lowest RelMSE and temporal error of each rate in bold."""
    d = load(results, rel)
    temporal, skipped = d["temporal"], d["skipped"]
    if not temporal:
        raise PageError(f"{rel}: no sequence records (a folder of frame_XXXX shots is benchmarked as one)")
    spps = sorted({t["spp"] for t in temporal})
    methods = [m for m in BASELINE_METHODS if any(t["method"] == m for t in temporal)]
    mean = lambda xs: sum(xs) / len(xs)
    cells: dict[tuple, tuple] = {}
    for m in methods:
        for sp in spps:
            ts = [t for t in temporal if t["method"] == m and t["spp"] == sp]
            if not ts:
                if not any(k["method"] == m for k in skipped):
                    raise PageError(f"{rel}: no {m} sequences at {sp} spp and no skipped entry saying why")
                continue
            cells[m, sp] = (mean([t["relmse"] for t in ts]), mean([t["ssim"] for t in ts]),
                            mean([t["temporal_error"] for t in ts]), len(ts), ts[0]["frames"])
    best = {sp: (min(v[0] for (m, s), v in cells.items() if s == sp),
                 min(v[2] for (m, s), v in cells.items() if s == sp)) for sp in spps}
    rows = []
    for m in methods:
        row = [m]
        for sp in spps:
            c = cells.get((m, sp))
            if c is None:
                row += ["-", "-"]
                continue
            a, b = f"{num(c[0])} ({num(c[1], '.3f')})", num(c[2])
            row += [f"**{a}**" if c[0] == best[sp][0] else a, f"**{b}**" if c[2] == best[sp][1] else b]
        rows.append(row)
    header = ["method"] + [h for sp in spps for h in (f"{sp} spp RelMSE (SSIM)", f"{sp} spp temporal")]
    counts = sorted({(v[3], v[4]) for v in cells.values()})
    return table(header, rows) + "\n\nMeans over " + ", ".join(f"{n} sequences of {f} frames" for n, f in counts) + \
        " per cell; temporal error: `jaxdenoise.metrics.temporal_error` (docs/metrics.md)."


bind("baseline-library-eval-seq", baseline_sequences, "bench_library_eval_seq/results.json")


# demo ---------------------------------------------------------------------------------------------

@renderer("demo-time")
def _demo_time(results: Path) -> str:
    d = load(results, "demo/demo.json")
    return table(["scene", "size", "spp", "reference spp", "rendered now", "render s", "demo s (render + bench)"],
                 [[f"`{d['scene']}`", f"{d['size']}x{d['size']}", ", ".join(str(s) for s in d["spp"]),
                   str(d["ref_spp"]), ", ".join(d["rendered_now"]) or "nothing (cached)",
                   num(d["render_seconds"], ".1f"), num(d["total_seconds"], ".0f")]], "lrrrlrr")


@renderer("demo-results")
def _demo_results(results: Path) -> str:
    """The demo report's own summary table (`jaxdenoise.bench.markdown_table`)."""
    from jaxdenoise import bench
    return bench.markdown_table(load(results, "demo/results.json")["summary"])


# -- pages ----------------------------------------------------------------------------------------

def render_page(text: str, results: Path, page: Path) -> str:
    def sub(m: re.Match) -> str:
        name = m["name"]
        if name not in TABLES:
            raise PageError(f"{page}: unknown table {name!r} (scripts/results.py knows {', '.join(sorted(TABLES))})")
        try:
            body = TABLES[name](results)
        except KeyError as e:
            raise PageError(f"{page}: table {name!r}: its JSON lacks {e}") from None
        except (IndexError, TypeError, ValueError) as e:
            raise PageError(f"{page}: table {name!r}: its JSON holds an unexpected value ({e})") from None
        except PageError as e:
            raise PageError(f"{page}: table {name!r}: {e}") from None
        return f"<!-- results: {name} -->\n\n{body}\n\n<!-- /results -->"
    return BLOCK.sub(sub, text)


# Pages an experiment writes whole, with the experiment's own ``page(res) -> str`` (the function its
# ``main`` writes the page with), from the JSON it writes beside: page -> (experiment module, JSON),
# paths relative to the results folder.
STUDIES: dict[str, tuple[str, str]] = {
    "conv.md": ("bench_conv", "conv.json"),
    "im2col/im2col.md": ("bench_im2col", "im2col/im2col.json"),
    "xla_flags/xla_flags.md": ("bench_xla_flags", "xla_flags/xla_flags.json"),
    "memory_reuse/xla_flags.md": ("bench_xla_flags", "memory_reuse/xla_flags.json"),
    "xnn_convolutions/xla_flags.md": ("bench_xla_flags", "xnn_convolutions/xla_flags.json"),
    "gradnet_profile/gradnet_profile.md": ("profile_gradnet", "gradnet_profile/gradnet_profile.json"),
    "network_memory/network_memory.md": ("network_memory", "network_memory/network_memory.json"),
    "first_call/first_call.md": ("first_call", "first_call/first_call.json"),
    "filters.md": ("bench_filters", "bench_filters.json"),
    "poisson.md": ("bench_poisson", "poisson.json"),
    "poisson_l1_quiet/poisson.md": ("bench_poisson", "poisson_l1_quiet/poisson.json"),
    "poisson_l2_quiet/poisson.md": ("bench_poisson", "poisson_l2_quiet/poisson.json"),
    "poisson_l1_radmm/poisson.md": ("bench_poisson", "poisson_l1_radmm/poisson.json"),
    "poisson_rendered/poisson.md": ("bench_poisson", "poisson_rendered/poisson.json"),
    "data_gen_gradient.md": ("bench_gradient_cost", "data_gen_gradient.json"),
    "data_gen_gradient_rerun/data_gen_gradient.md": ("bench_gradient_cost",
                                                     "data_gen_gradient_rerun/data_gen_gradient.json"),
    "data_gen_gradient_rerun2/data_gen_gradient.md": ("bench_gradient_cost",
                                                      "data_gen_gradient_rerun2/data_gen_gradient.json"),
    "data_gen_gradient_099/before/data_gen_gradient.md": ("bench_gradient_cost",
                                                          "data_gen_gradient_099/before/data_gen_gradient.json"),
    "data_gen_gradient_099/data_gen_gradient.md": ("bench_gradient_cost",
                                                   "data_gen_gradient_099/data_gen_gradient.json"),
    "data_gen_gradient_099/rerun/data_gen_gradient.md": ("bench_gradient_cost",
                                                         "data_gen_gradient_099/rerun/data_gen_gradient.json"),
    "demc_rates/recipes.md": ("demc_recipes", "demc_rates/recipes.json"),
    "demc_rates/level3/recipes.md": ("demc_recipes", "demc_rates/level3/recipes.json"),
    "data_gen.md": ("bench_data_gen", "data_gen.json"),
    "scale_out.md": ("bench_scale_out", "scale_out.json"),
    "lbf_timing.md": ("lbf_timing", "lbf_timing.json"),
    "lbf_ablation.md": ("lbf_ablation", "lbf_ablation.json"),
    "lbf_heldout/lbf_eval.md": ("lbf_eval", "lbf_heldout/lbf_eval.json"),
    "tune_bilateral.md": ("tune_filters", "tune_bilateral.json"),
    "tune_nlm.md": ("tune_filters", "tune_nlm.json"),
    "reliability.md": ("reliability_report", "reliability.json"),
    "stability.md": ("stability_report", "stability.json"),
    "inverse_rendering/inverse_rendering.md": ("inverse_rendering", "inverse_rendering/inverse_rendering.json"),
    "adaptive/adaptive.md": ("adaptive", "adaptive/adaptive.json"),
    "adaptive/variants.md": ("adaptive_variants", "adaptive/variants.json"),
    "adaptive/pooling_16spp/variants.md": ("adaptive_variants", "adaptive/pooling_16spp/variants.json"),
    "adaptive/pooling_64spp/variants.md": ("adaptive_variants", "adaptive/pooling_64spp/variants.json"),
    "gradient_emission/gradient_emission.md": ("gradient_emission", "gradient_emission/gradient_emission.json"),
    "tiling/tiling.md": ("tiling", "tiling/tiling.json"),
    "demc_rates/demc_levels.md": ("demc_levels", "demc_rates/demc_levels.json"),
    "demc_rates/indirect_val/demc_levels.md": ("demc_levels", "demc_rates/indirect_val/demc_levels.json"),
    "rae_rates/demc_levels.md": ("demc_levels", "rae_rates/demc_levels.json"),
    "rae_rates/level_term/demc_levels.md": ("demc_levels", "rae_rates/level_term/demc_levels.json"),
    "rae_rates/single_0921/demc_levels.md": ("demc_levels", "rae_rates/single_0921/demc_levels.json"),
    "rae_rates/single_0922/demc_levels.md": ("demc_levels", "rae_rates/single_0922/demc_levels.json"),
    "level_correction/level_correction.md": ("level_correction", "level_correction/level_correction.json"),
    "level_correction/choice.md": ("level_correction", "level_correction/choice.json"),
    "level_correction_val4/choice.md": ("level_correction", "level_correction_val4/choice.json"),
    "level_correction_0917/choice.md": ("level_correction", "level_correction_0917/choice.json"),
    "level_correction_val4_0918/choice.md": ("level_correction", "level_correction_val4_0918/choice.json"),
    "level_correction_margin/choice.md": ("level_correction", "level_correction_margin/choice.json"),
    "refine/demc/refine.md": ("refine_choice", "refine/demc/refine.json"),
    "refine/rae/refine.md": ("refine_choice", "refine/rae/refine.json"),
    "rae_rates/output_clamp/output_clamp.md": ("output_clamp_choice", "rae_rates/output_clamp/output_clamp.json"),
}

# Pages written by hand that state no measured number of their own (they point to the pages above).
HAND_WRITTEN: set[str] = set()  # none today: every page is generated or holds generated tables


def study_page(module: str) -> Callable[[dict], str]:
    import importlib
    return importlib.import_module(module).page


def expected(results: Path = RESULTS) -> dict[Path, str]:
    """Every generated page under ``results`` and what it should hold."""
    from jaxdenoise import bench
    out: dict[Path, str] = {}
    for page, (module, rel) in STUDIES.items():
        try:
            out[results / page] = study_page(module)(load(results, rel))
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as e:
            raise PageError(f"{results / page}: experiments/{module}.py's page() on {rel}: "
                            f"{type(e).__name__}: {e}") from None
    for page in sorted(results.rglob("*.md")):
        text = page.read_text()
        if BLOCK.search(text):
            if page in out:
                raise PageError(f"{page}: written whole by its experiment, yet holds result blocks")
            out[page] = render_page(text, results, page)
    for res in sorted(results.rglob("results.json")):
        if (res.parent / "config.json").exists():
            try:
                out[res.parent / "results.md"] = bench.report_markdown(bench.load_report(res.parent))
            except (KeyError, IndexError, TypeError, ValueError) as e:
                raise PageError(f"{res}: not a complete bench report ({type(e).__name__}: {e})") from None
    return out


def stale(results: Path = RESULTS) -> list[Path]:
    """The generated pages whose committed text differs from what their JSON gives."""
    return [p for p, text in expected(results).items() if not p.exists() or p.read_text() != text]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if a page differs from its JSON")
    ap.add_argument("--results", default=str(RESULTS), help="the results folder (default docs/results)")
    a = ap.parse_args(argv)
    results = Path(a.results)
    try:
        pages = expected(results)
    except PageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    changed = [p for p, text in pages.items() if not p.exists() or p.read_text() != text]
    if a.check:
        for p in changed:
            print(f"stale: {p} (run python scripts/results.py)")
        return 1 if changed else 0
    from jaxdenoise.fsutil import write_text
    for p in changed:
        write_text(p, pages[p])
        print(f"wrote {p}")
    print(f"{len(pages)} generated pages, {len(changed)} rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
