"""Dask's overhead against the serial writer (`python -m data_gen dataset`), in one run:

    python experiments/bench_scale_out.py --count 8 --res 32 --out docs/results

The same dataset (``--count`` scenes of the ``mixed`` family, spp 4, a 64-spp reference) is rendered
into fresh folders serially, on a local Dask cluster of 1 worker and of 2 workers (single-threaded
each; this machine has 2 cores), repeated ``--repeats`` times in alternation; reported: the wall time
of each (median), the overhead per task of the 1-worker cluster against the serial writer ((Dask-1
wall - serial wall) / scenes) and the speed-up of 2 workers. Each run is a separate process, so
Mitsuba's start-up is in every number alike. Writes ``scale_out.json`` and ``scale_out.md`` (`page`:
the page from the JSON alone).
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from common import all_measured, write_study  # noqa: E402


# the modes, in the page's order: the extra arguments of `python -m data_gen dataset`
MODES = {"serial": [], "dask local:1": ["--scheduler", "local:1"], "dask local:2": ["--scheduler", "local:2"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=8)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="docs/results")
    args = ap.parse_args()
    base = [sys.executable, "-m", "data_gen", "dataset", "--family", "mixed", "--count", str(args.count), "--res",
            str(args.res), "--spp", "4", "--ref-spp", "64", "--no-progress"]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    times: dict[str, list[float]] = {m: [] for m in MODES}
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for mode, extra in MODES.items():
                out = Path(tmp) / f"{mode.replace(' ', '_').replace(':', '')}_{r}"
                t0 = time.perf_counter()
                p = subprocess.run(base + extra + ["--out", str(out)], env=env, capture_output=True, text=True)
                if p.returncode:
                    raise SystemExit(f"{mode}: {p.stderr[-1000:]}")
                times[mode].append(time.perf_counter() - t0)
                shutil.rmtree(out)
                print(f"{mode} run {r}: {times[mode][-1]:.1f} s", flush=True)
    med = {m: statistics.median(v) for m, v in times.items()}
    per_task = (med["dask local:1"] - med["serial"]) / args.count
    res = {"command": "python " + " ".join(sys.argv), "count": args.count, "res": args.res, "times": times,
           "median": med, "overhead_per_task_s": per_task, "speedup_2_workers": med["serial"] / med["dask local:2"],
           "load_at_start": load, "load_at_end": os.getloadavg()[0], "cpu_count": os.cpu_count()}
    out = Path(args.out)
    write_study(out, "scale_out.json", "scale_out.md", res, page)
    print(f"scale_out: {med} -> {out / 'scale_out.md'}")


def page(res: dict) -> str:
    """``scale_out.md`` from ``scale_out.json`` alone (a missing value raises, never prints a hole)."""
    all_measured(res, "scale_out.json")
    times, med = res["times"], res["median"]
    repeats = {len(times[m]) for m in MODES}
    if len(repeats) != 1:
        raise ValueError(f"scale_out.json: the modes have different numbers of runs {sorted(repeats)}")
    (repeats,) = repeats
    lines = ["# Scale-out: Dask against the serial writer", "",
             "| mode | wall s (median) | runs |", "|---|---:|---|"]
    for m in MODES:
        lines.append(f"| {m} | {med[m]:.1f} | {', '.join(f'{x:.1f}' for x in times[m])} |")
    lines += ["", f"Overhead of a 1-worker local cluster against the serial writer: **{res['overhead_per_task_s']:.2f} s "
                  f"per task** (cluster start-up and shut-down included, spread over {res['count']:d} tasks); 2 workers "
                  f"on this {res['cpu_count']:d}-core machine: {res['speedup_2_workers']:.2f}x the serial writer's speed.",
              "",
              "On a real cluster the start-up is paid once by the user's scheduler, and each task is one "
              "scene of seconds to minutes of rendering: the per-task cost that remains is Dask's "
              "scheduling (milliseconds) and the worker's Mitsuba start-up (once per worker). Recipe: "
              "docs/data_gen.md, *Beyond one machine*.", "",
              "## Run", "",
              f"Command: `{res['command']:s}`. {res['count']:d} scenes at {res['res']:d}x{res['res']:d} (spp 4, 64-spp "
              f"reference), each mode a fresh process and folder, {repeats} repeats in alternation; "
              f"{res['cpu_count']:d} cores, load average {res['load_at_start']:.2f} at start, {res['load_at_end']:.2f} "
              "at the end."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
