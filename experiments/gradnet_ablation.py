"""GradNet ablations at an equal, short budget. ``--study loss`` (issue 15, item 6): the full loss
L_all against L_data + L_grad (Fig. 12), and the mu-law (mu = 16) against log(1 + |I|) compression
(Fig. 17, convergence curves); ``--study converged``: the first pair at the full schedule (two
58-minute runs; the "L_all" one is the shipped weights' run: its folder can be copied in to resume
it as finished). ``--study decoder``: the decoder as first built (three deconvolutions,
the last one giving the output) against the input-skip decoder the shipped network uses, each at the
paper's learning rate (1e-4) and at ours (1e-3, gradient norm clipped to 1) (docs/methods/gradnet.md).
``--study readings`` (issue 35 item 2): the residual block with an LReLU after the sum (ours) against
Fig. 4's one LReLU per block, and Eq. 10's w_ij on the compressed base against w_ij on I_b in HDR
(the equation writes no T there); ``--seeds`` repeats every variant. ``--study pixels`` (issue 35
item 4): the pixels a step sees against the learning rate, at equal wall time (``--seconds`` per
variant, compile and validations included): our 8 crops of 64x64 at 1e-3 with clipping; 4x the
pixels per step as 8 crops of 128x128, at 1e-3 with clipping and at the paper's 1e-4; and 4x as 32
crops of 64x64 at the paper's 1e-4 (Sec. 5.2: 32 patches of 256x256 at 1e-4).
Every variant trains with the same code, data, seed and steps or seconds (`jaxdenoise.train.train`), validated
on the same frames every ``--validate-every`` steps; the schedule is compressed to the budget (an
epoch of ``--epoch-patches`` patches, so that Eq. 14's lambda is on for most of the run). Writes the
curves and the final scores as JSON and a plot.

    python experiments/gradnet_ablation.py --study loss --data data/gradnet_train --train-primal base --val data/gradnet_val \
        --steps 1000 --validate-every 200 --out docs/results/gradnet_ablation
    python experiments/gradnet_ablation.py --study converged --data data/gradnet_train --train-primal base --val data/gradnet_val \
        --epoch-patches 2560 --steps 32000 --validate-every 1000 --val-spps 64 --out docs/results/gradnet_ablation_converged
    python experiments/gradnet_ablation.py --study decoder --data data/gradnet_train --train-primal base --val data/gradnet_val \
        --steps 1000 --validate-every 200 --out docs/results/gradnet_decoder
    python experiments/gradnet_ablation.py --study readings --data data/gradnet_train_gpt --val data/gradnet_val_gpt \
        --steps 3000 --epoch-patches 256 --validate-every 500 --seeds 0,1 --out docs/results/gradnet_readings
    python experiments/gradnet_ablation.py --study pixels --data data/gradnet_train_gpt --val data/gradnet_val_gpt1k \
        --val-spps 16,64,256 --seconds 480 --steps 100000 --epoch-patches 512 --validate-every 0 \
        --runs runs/gradnet_pixels --out docs/results/gradnet_pixels
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdenoise.buffers import PRIMALS  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import get, gradnet  # noqa: E402
from jaxdenoise.train import TrainConfig, load_data, train  # noqa: E402

PAPER_LR = {"learning_rate": 1e-4, "clip_norm": None}  # Sec. 5.2 (the trainer's other defaults: gradnet.TRAIN)
# study -> variant -> (method config overrides, trainer overrides)
STUDIES = {
    "converged": {  # Fig. 12 at the full schedule (--epoch-patches 2560 --steps 32000): L_all is the shipped run
        "L_all (mu-law)": ({}, {}),
        "L_data + L_grad (mu-law)": ({"first_order": False}, {}),
    },
    "loss": {
        "L_all (mu-law)": ({}, {}),
        "L_data + L_grad (mu-law)": ({"first_order": False}, {}),
        "L_all (log)": ({"compression": "log"}, {}),
    },
    "readings": {  # issue 35 item 2: two open readings of the paper, each against the shipped reading
        "block LReLU after the sum, w_ij on T(I_b)": ({}, {}),
        "one LReLU per block (Fig. 4), w_ij on T(I_b)": ({"res_act_after_sum": False}, {}),
        "block LReLU after the sum, w_ij on I_b (Eq. 10 literal)": ({"weights_domain": "hdr"}, {}),
    },
    "pixels": {  # issue 35 item 4, at equal wall time (--seconds)
        "8 x 64^2 a step, lr 1e-3 + clip (ours)": ({}, {}),
        "8 x 128^2 a step, lr 1e-3 + clip": ({"train_crop": 128}, {}),
        "8 x 128^2 a step, lr 1e-4 (the paper's)": ({"train_crop": 128}, PAPER_LR),
        "32 x 64^2 a step, lr 1e-4 (the paper's)": ({"train_batch": 32}, PAPER_LR),
    },
    "decoder": {
        # L_data + L_grad only: the question is how fast each decoder leaves the base image
        "first decoder, lr 1e-4": ({"input_skip": False, "first_order": False}, PAPER_LR),
        "first decoder, lr 1e-3 + clip": ({"input_skip": False, "first_order": False}, {}),
        "input skip, lr 1e-4": ({"first_order": False}, PAPER_LR),
        "input skip, lr 1e-3 + clip": ({"first_order": False}, {}),
    },
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", choices=sorted(STUDIES), default="loss")
    ap.add_argument("--data", required=True)
    ap.add_argument("--val", required=True)
    ap.add_argument("--val-spps", default="64")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--epoch-patches", type=int, default=128)
    ap.add_argument("--validate-every", type=int, default=250)
    ap.add_argument("--seconds", type=float, help="wall-time budget of every variant (TrainConfig.time_limit)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", help="comma-separated seeds, every variant trained once per seed (default: --seed)")
    ap.add_argument("--runs", default="runs/gradnet_ablation")
    ap.add_argument("--train-primal", default="gpt", choices=PRIMALS,
                    help="what I_b of the training renders is (gradnet.Config.train_primal; base: data/gradnet_train)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    base = dataclasses.replace(gradnet.Config(), epoch_patches=args.epoch_patches, train_primal=args.train_primal)
    dataset = load_data(get("gradnet", base), args.data)
    seeds = [int(v) for v in args.seeds.split(",")] if args.seeds else [args.seed]
    results = {}
    for seed in seeds:
        for variant, (over, train_over) in STUDIES[args.study].items():
            name = variant if len(seeds) == 1 else f"{variant}, seed {seed}"
            cfg = dataclasses.replace(base, **over)
            slug = "".join(c if c.isalnum() or c in "-." else "_" for c in name.replace("+", "plus"))
            folder = Path(args.runs) / args.study / slug
            t0 = time.perf_counter()
            method = get("gradnet", cfg)
            s = train(method, dataset, folder, TrainConfig.for_method(
                method, steps=args.steps, seed=seed, val_data=args.val,
                val_spps=[int(v) for v in args.val_spps.split(",")], validate_every=args.validate_every, resume=True,
                progress=False, time_limit=args.seconds, **train_over))
            cfg_m = method.config
            results[name] = {"variant": variant, "seed": seed, "config": over, "train": train_over,
                             "validation": s["validation"], "best": s["best"], "steps": s["steps_done"],
                             "pixels_per_step": cfg_m.train_batch * cfg_m.train_crop ** 2,
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
