"""DEMC's ablations of Sec. 4.4 / Fig. 10 scored on held-out frames: DEMC vs SEMC vs DEMC-noSN,
two seeds each, trained at an equal budget by ``experiments/train_demc.py run`` (their best weights
by validation), plus the main run's weights.

    python experiments/demc_ablation.py --weights runs/demc_gpu/x --data runs/bench_heldout_data \\
        --spp 4,16,64 --out docs/results/demc_ablation.json

Every weights folder (``<variant>_s<seed>``, found recursively under ``--weights``) is loaded with its
own config (`jaxdenoise.load`), run on every render of ``--data`` at the given rates, and scored
with the project's RelMSE and SSIM (docs/metrics.md). Prints a Markdown table (mean over frames;
mean and spread over the two seeds) and writes the per-frame scores as JSON.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxdenoise import load, metrics  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import get  # noqa: E402
from jaxdenoise.train import load_validation  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default="runs/demc_gpu/x")
    ap.add_argument("--data", default="runs/bench_heldout_data")
    ap.add_argument("--spp", default="4,16,64")
    ap.add_argument("--out", default="docs/results/demc_ablation.json")
    args = ap.parse_args()
    spps = [int(s) for s in args.spp.split(",")]
    folders = sorted(p.parent for p in Path(args.weights).rglob("params.npz") if p.parent.name not in ("weights", "checkpoint"))
    # the project's loader of scored frames: the first render of each shot at each rate
    frames = [(Path(f["file"]).parent.name, f["spp"], f["buffers"], f["reference"])
              for f in load_validation(get("demc"), args.data, spps)]
    scores: dict[str, list] = {}
    for folder in folders:
        name = folder.name if folder.name != "best" else folder.parent.name
        fn = load("demc", folder)
        rows = []
        for shot, spp, buf, ref in frames:
            out = np.asarray(fn(buf))
            rows.append({"shot": shot, "spp": spp, "relmse": float(metrics.relmse(out, ref)),
                         "ssim": float(metrics.ssim(out, ref))})
        scores[name] = {"variant": fn.method.config.variant, "rows": rows}
        print(name, {s: round(float(np.mean([r["relmse"] for r in rows if r["spp"] == s])), 5) for s in spps},
              flush=True)
    write_json(Path(args.out), {"data": args.data, "spp": spps, "weights": args.weights, "scores": scores})
    print("\n| model | " + " | ".join(f"{s} spp RelMSE | {s} spp SSIM" for s in spps) + " |")
    print("|---|" + "---|---|" * len(spps))
    for name, sc in scores.items():
        cells = []
        for s in spps:
            rs = [r for r in sc["rows"] if r["spp"] == s]
            cells += [f"{np.mean([r['relmse'] for r in rs]):.4f}", f"{np.mean([r['ssim'] for r in rs]):.4f}"]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
