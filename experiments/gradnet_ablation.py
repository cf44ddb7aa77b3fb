"""GradNet's loss and compression ablations at an equal, short budget (issue 15, item 6): the full
loss L_all against L_data + L_grad (Fig. 12), and the mu-law (mu = 16) against log(1 + |I|)
compression (Fig. 17, convergence curves). Every variant trains with the same code, data, seed and
steps (`jaxdenoise.train.train`), validated on the same frames every ``--validate-every`` steps; the
schedule is compressed to the budget (an epoch of ``--epoch-patches`` patches, so that Eq. 14's
lambda is on for most of the run). Writes the curves and the final scores as JSON and a plot.

    python experiments/gradnet_ablation.py --data data/gradnet_train --val data/gradnet_val \
        --steps 1500 --out docs/results/gradnet_ablation
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import gradnet  # noqa: E402
from jaxdenoise.train import train  # noqa: E402

VARIANTS = {
    "L_all (mu-law)": {},
    "L_data + L_grad (mu-law)": {"first_order": False},
    "L_all (log)": {"compression": "log"},
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--val", required=True)
    ap.add_argument("--val-spps", default="64")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--epoch-patches", type=int, default=128)
    ap.add_argument("--validate-every", type=int, default=250)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", default="runs/gradnet_ablation")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    base = dataclasses.replace(gradnet.Config(), epoch_patches=args.epoch_patches)
    dataset = gradnet.make_dataset(args.data, base)
    results = {}
    for name, over in VARIANTS.items():
        cfg = dataclasses.replace(base, **over)
        folder = Path(args.runs) / name.replace(" ", "_").replace("(", "").replace(")", "").replace("+", "plus")
        t0 = time.perf_counter()
        s = train("gradnet", args.data, folder, steps=args.steps, seed=args.seed, config=cfg, dataset=dataset,
                  val_data=args.val, val_spps=[int(v) for v in args.val_spps.split(",")],
                  validate_every=args.validate_every, resume=True, progress=False)
        results[name] = {"config": over, "validation": s["validation"], "best": s["best"],
                         "seconds": time.perf_counter() - t0, "folder": str(folder)}
        print(name, s["line"], flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ablation.json", {"command": "python experiments/gradnet_ablation.py " + " ".join(argv or sys.argv[1:]),
                                       "results": results, "method_config": dataclasses.asdict(base)})
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for name, r in results.items():
        v = [x for x in r["validation"] if x["step"] > 0]
        ax.plot([x["step"] for x in v], [x["relmse"] for x in v], marker="o", label=name)
    ax.set_yscale("log")
    ax.set_xlabel("training step")
    ax.set_ylabel(f"validation RelMSE ({args.val_spps} spp)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.savefig(out / "convergence.png", bbox_inches="tight")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
