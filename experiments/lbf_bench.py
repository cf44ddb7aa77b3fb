"""Error against run time of `lbf`, `lbf-nlm` and their peers (`bilateral`, `nlm`, `gaussian`,
`oidn`, raw `input`) on held-out frames, through the project's bench harness (`jaxdenoise.bench`).

    python experiments/lbf_bench.py --data runs/lbf_eval_data --spp 4,16,64 --out docs/results/lbf_bench

A folder of links holding only the chosen sampling rates (the first render of each, header spp) is benchmarked; the harness
writes results.json, results.md and error_vs_time.png into --out.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxdenoise import bench  # noqa: E402
from jaxdenoise.data import discover, renders_by_spp  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--spp", default="4,16,64")
    ap.add_argument("--methods", default="input,gaussian,bilateral,nlm,lbf,lbf-nlm,oidn")
    ap.add_argument("--runs", type=int, default=bench.MIN_RUNS)
    ap.add_argument("--work", default="runs/lbf_bench_data")
    ap.add_argument("--out", default="docs/results/lbf_bench")
    args = ap.parse_args()
    spps = {int(s) for s in args.spp.split(",")}
    work = Path(args.work)
    for shot in discover(args.data):
        d = work / shot.name
        d.mkdir(parents=True, exist_ok=True)
        first = [rs[0].path for s, rs in renders_by_spp(shot, spps).items()]  # instance 00 of each rate
        for p in [shot.reference] + first:
            if not (d / p.name).exists():
                (d / p.name).symlink_to(p.resolve())
    report = bench.run(work, args.methods.split(","), args.out, runs=args.runs)
    print(bench.one_line(report))


if __name__ == "__main__":
    main()
