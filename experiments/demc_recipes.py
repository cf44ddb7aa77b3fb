"""DEMC training recipes measured at an equal budget on this machine (issue 33): Eq. 3's two readings
from scratch, and the loss's per-pixel scale as a fine-tune of the shipped weights.

    python experiments/demc_recipes.py eq3 --steps 250 --seeds 0,1 --lr 5e-4 --out runs/demc_eq3
    python experiments/demc_recipes.py finetune --loss-scale output --steps 700 --out runs/demc_scale
    python experiments/demc_recipes.py finetune --level-weight 4 --steps 700 --out runs/demc_level

Both train on ``--data`` (default ``runs/demc_rates_data``: the scene library's training scenes and
40 procedural ``mixed`` scenes at 1/4/16/64 spp, jaxdenoise/weights/demc/README.md) and validate on
the library's ``val`` split every ``--validate-every`` steps, keeping ``best/`` by the geometric mean
of the validation RelMSE (`jaxdenoise.train`). ``eq3`` trains ``skip_init`` "decoder" ([I, 0, 0]) and
"all" ([I, I, I]) from a random init, one run per seed, the same crops for both readings (the seed
draws the crops) at Adam ``--lr`` (5e-4: the rate of the first from-scratch DEMC run,
docs/methods/demc.md); ``finetune`` starts from ``--init`` with the config's ``loss_scale`` and
``level_weight`` replaced, at the method's own rate (1e-4).
Each run resumes from its checkpoint when started again; every run's summary goes to
``OUT/summary.json``. Score the folders with ``experiments/demc_ablation.py --weights OUT``.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import get  # noqa: E402
from jaxdenoise.train import TrainConfig, load_data, train  # noqa: E402

SPPS = (1, 4, 16, 64)


def _run(method, data, out: Path, args, **fields) -> dict:
    run = TrainConfig.for_method(method, steps=args.steps, resume=True, val_data=args.val_data,
                                 validate_every=args.validate_every, select="geomean", progress=False, **fields)
    t = time.perf_counter()
    s = train(method, data, out, run)
    rec = {"steps": s["steps_done"], "seconds": time.perf_counter() - t, "final_loss": s["final_loss"],
           "best_step": s["best"]["step"], "best_geomean": s["best"]["relmse_geomean"],
           "config": {f: getattr(method.config, f) for f in ("skip_init", "loss_scale", "level_weight", "exposure")}}
    print(out.name, rec, flush=True)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("eq3", "finetune"))
    ap.add_argument("--data", default="runs/demc_rates_data")
    ap.add_argument("--val-data", default="data/library_val")
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--validate-every", type=int, default=50)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--lr", type=float, default=5e-4, help="eq3: Adam's step size (constant)")
    ap.add_argument("--init", default="jaxdenoise/weights/demc")
    ap.add_argument("--loss-scale", default="reference", choices=("reference", "output"))
    ap.add_argument("--level-weight", type=float, default=0.0)
    args = ap.parse_args()
    out = Path(args.out)
    base = get("demc", train_spps=SPPS)
    data = load_data(base, args.data, progress=False)
    summary: dict = {"what": args.what, "data": args.data, "val_data": args.val_data, "steps": args.steps, "runs": {}}
    if args.what == "eq3":
        for seed in (int(s) for s in args.seeds.split(",")):
            for reading in ("decoder", "all"):
                name = f"{reading}_s{seed}"
                summary["runs"][name] = _run(base.with_config(skip_init=reading), data, out / name, args, seed=seed,
                                             learning_rate=args.lr)
                write_json(out / "summary.json", summary)
    else:
        name = f"scale_{args.loss_scale}" + (f"_level{args.level_weight:g}" if args.level_weight else "")
        summary["runs"][name] = _run(base.with_config(loss_scale=args.loss_scale, level_weight=args.level_weight),
                                     data, out / name, args, init_from=args.init)
        write_json(out / "summary.json", summary)


if __name__ == "__main__":
    main()
