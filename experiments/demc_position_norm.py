"""DEMC's world-position normalization (docs/methods/demc.md): per frame (`position_norm="frame"`)
vs the training set's z-score (`"global"`, Sec. 4.2 read literally), trained at an equal, short
budget on this CPU (2 seeds each) and scored on held-out frames as rendered and with the scene's
world coordinates rescaled (x10 and shifted by (100, 0, -50): the same images in a scene modelled in
other units, which the network should not notice).

    python experiments/demc_position_norm.py --train runs/demc_data/demc_train.npz \\
        --data runs/bench_heldout_data --steps 300 --out docs/results/demc_position_norm.json
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxdenoise import load, metrics, train  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import demc, get  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", default="runs/demc_data/demc_train.npz")
    ap.add_argument("--data", default="runs/bench_heldout_data")
    ap.add_argument("--runs", default="runs/demc_posnorm")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--out", default="docs/results/demc_position_norm.json")
    args = ap.parse_args()
    frames = [(f["file"], f["buffers"], f["reference"]) for f in train.load_validation(get("demc"), args.data, (4,))]
    dataset = None
    res = {"steps": args.steps, "batch": args.batch, "crop": args.crop, "runs": {}}
    for mode in ("frame", "global"):
        for seed in (0, 1):
            cfg = demc.Config(position_norm=mode, train_batch=args.batch, train_crop=args.crop)
            method = get("demc", cfg)
            if dataset is None:
                dataset = train.load_data(method, args.train, progress=False)
            out = Path(args.runs) / f"{mode}_s{seed}"
            s = train.train(method, dataset, out, train.TrainConfig.for_method(
                method, resume=True, steps=args.steps, seed=seed, progress=False, learning_rate=5e-4,
                schedule="constant"))
            fn = load("demc", out / "weights")
            row = {"seconds": s["seconds"], "final_loss": s["final_loss"]}
            for label, scale, shift in (("as rendered", 1.0, 0.0), ("rescaled", 10.0, np.array([100.0, 0.0, -50.0]))):
                errs = []
                for _, buf, ref in frames:
                    b = dataclasses.replace(buf, position=(buf.position * scale + shift).astype(np.float32))
                    errs.append(float(metrics.relmse(np.asarray(fn(b)), ref)))
                row[label] = float(np.mean(errs))
            res["runs"][f"{mode}_s{seed}"] = row
            print(mode, seed, row, flush=True)
            write_json(Path(args.out), res)
    print("\n| position_norm | seed | RelMSE as rendered | RelMSE rescaled |\n|---|---|---|---|")
    for k, r in res["runs"].items():
        m, s = k.rsplit("_s", 1)
        print(f"| {m} | {s} | {r['as rendered']:.4f} | {r['rescaled']:.4f} |")


if __name__ == "__main__":
    main()
