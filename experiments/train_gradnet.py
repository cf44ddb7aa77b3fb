"""GradNet (Guo et al. 2019) at the paper's patch size and batch, sized to one short GPU lease, with
the data moved as two compact exports (issue 15: the 256-spp check needs more training than 2 CPU
cores give; docs/results/gradnet.md).

1. ``prepare`` (here, with OpenImageIO): `gradnet.make_dataset` on the training folder (64-spp G-PT
   renders; illegal renders dropped and counted), then the kept renders exported whole **without the
   reference** (GradNet's losses never read it; `pipeline.Cache.export(leave_out=...)`), as many as
   fit in ``--train-mib``; and the validation frames at ``--val-spps`` whole, with their references,
   in ``--val-mib``. ``exports.json`` records counts, sizes and the drop count.
2. ``run`` (anywhere JAX runs; needs neither OpenImageIO, Mitsuba nor jaxopt): one training run from
   scratch with the module's optimizer (`gradnet.TRAIN`) on ``--crop`` x ``--crop`` crops in batches of
   ``--batch`` (the paper: 256 x 256 and 32; our renders are 128 x 128, so 128 is the largest crop),
   an epoch of ``--epoch-patches`` patches (the paper's 11,785) so that Eq. 14's lambda and the
   learning-rate decay (x0.95 every other epoch, counted in each group's updates) follow the paper's
   epochs, stopped by ``--seconds`` or ``--steps``; validated every ``--validate-every`` steps, the
   best step kept in ``RUNS/best``. It resumes from its checkpoint when started again. Results go to
   ``--out``: ``best.tar`` and ``last.tar`` (weights only: a device machine sends back files of at
   most 16 MiB, and the checkpoint with Adam's state is 4x that) and ``summary.json``. ``--init`` fine-tunes
   given weights instead (lambda held at its cap), ``--train-spps`` trains on other rates.

    python experiments/train_gradnet.py prepare --train data/gradnet_train --train-primal base --val data/gradnet_val
    python experiments/train_gradnet.py run --train-primal base --out OUT --runs /tmp/gradnet_gpu --seconds 420

Unpack ``best.tar`` here and score it with ``experiments/gradnet_eval.py --weights``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import tar_folders  # noqa: E402
from jaxdenoise.buffers import PRIMALS  # noqa: E402

PAPER_EPOCH_PATCHES = 11_785  # Sec. 5.1: 13,500 patches of 256 x 256, 846 illegal, 869 held out for testing


def prepare(args) -> None:
    from jaxdenoise.methods import gradnet
    from jaxdenoise.pipeline import open_training_data

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    cfg = gradnet.Config(train_primal=args.train_primal)
    ds = gradnet.make_dataset(args.train, cfg)
    out = {"train": ds.export(work / "gradnet_train.npz", n=10**9, whole=True, spps=cfg.train_spps,
                              leave_out=("reference",), max_mib=args.train_mib)}
    out["train"].update(ds.dropped, kept=len(ds), folder=args.train)
    spps = [int(s) for s in args.val_spps.split(",")]
    val = open_training_data(args.val, ("dx", "dy", *gradnet.FEATURES), spps=spps, progress=True)
    out["val"] = val.export(work / "gradnet_val.npz", n=10**9, whole=True, spps=spps, max_mib=args.val_mib)
    out["val"]["folder"] = args.val
    for part, s in out.items():
        print(part, json.dumps(s))
    tmp = work / ".exports.json.tmp"
    tmp.write_text(json.dumps(out, indent=1))
    tmp.rename(work / "exports.json")


def run(args) -> None:
    import jax

    from jaxdenoise import train
    from jaxdenoise.methods import get, gradnet

    out, runs = Path(args.out), Path(args.runs)
    out.mkdir(parents=True, exist_ok=True)
    cfg = dataclasses.replace(gradnet.Config(), train_crop=args.crop, train_batch=args.batch,
                              epoch_patches=args.epoch_patches, train_primal=args.train_primal)
    if args.train_spps:
        cfg = dataclasses.replace(cfg, train_spps=tuple(int(v) for v in args.train_spps.split(",")))
    if args.init:  # the weights went through Eq. 14's ramp: hold lambda at its cap from the first step
        cfg = dataclasses.replace(cfg, lambda_epochs=0, lambda_start=cfg.lambda_max)
    # x0.95 every other epoch (Sec. 5.2), counted in updates of each group (gradnet.TRAIN's convention)
    every = max(1, round(2 * args.epoch_patches / args.batch))
    over = {"schedule_every": every}
    if args.lr is not None:
        over["learning_rate"] = args.lr
    t = time.perf_counter()
    method = get("gradnet", cfg)
    s = train.train(method, args.train, runs, train.TrainConfig.for_method(
        method, resume=True, steps=args.steps, seed=args.seed, progress=False, val_data=args.val,
        val_spps=[int(v) for v in args.val_spps.split(",")], validate_every=args.validate_every,
        checkpoint_every=args.validate_every, time_limit=args.seconds, init_from=args.init, **over))
    rec = {"command": " ".join(sys.argv), "device": str(jax.devices()[0]), "seconds": time.perf_counter() - t,
           "steps": s["steps_done"], "steps_this_run": s["steps_this_run"], "final_loss": s["final_loss"],
           "crops_seen": s["steps_done"] // 2 * args.batch, "crop": args.crop, "batch": args.batch,
           "epoch_patches": args.epoch_patches, "schedule_every": every, "best": s.get("best"),
           "validation": s.get("validation", []), "line": s["line"]}
    tmp = out / ".summary.json.tmp"
    tmp.write_text(json.dumps(rec, indent=1, default=str))
    tmp.rename(out / "summary.json")
    tar_folders(out, "best.tar", {"best": runs / "best"})
    tar_folders(out, "last.tar", {"weights": runs / "weights"})
    print(s["line"], flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--train", default="data/gradnet_train")
    p.add_argument("--val", default="data/gradnet_val")
    p.add_argument("--val-spps", default="64,256")
    p.add_argument("--train-mib", type=float, default=34.0,
                   help="the training export's size cap, uncompressed (the file is about 2/3 of it)")
    p.add_argument("--val-mib", type=float, default=9.0)
    p.add_argument("--work", default="runs/gradnet_data")
    r = sub.add_parser("run")
    r.add_argument("--train", default="runs/gradnet_data/gradnet_train.npz")
    r.add_argument("--val", default="runs/gradnet_data/gradnet_val.npz")
    r.add_argument("--val-spps", default="64,256")
    r.add_argument("--runs", default="runs/gradnet_gpu")
    r.add_argument("--out", default="runs/gradnet_gpu_out")
    r.add_argument("--crop", type=int, default=128)
    r.add_argument("--batch", type=int, default=32)
    r.add_argument("--epoch-patches", type=int, default=PAPER_EPOCH_PATCHES)
    r.add_argument("--steps", type=int, default=2 * 50 * PAPER_EPOCH_PATCHES // 32,
                   help="trainer steps (two per autoencoder update: the G-branch alternates); default the "
                        "paper's 50 epochs at batch 32")
    r.add_argument("--seconds", type=float, default=None, help="time limit of this run")
    r.add_argument("--validate-every", type=int, default=1000)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--lr", type=float, default=None, help="Adam's base rate (default: gradnet.TRAIN's)")
    r.add_argument("--train-spps", default=None, help="comma list of training rates (default: gradnet.Config's 64)")
    r.add_argument("--init", default=None, help="fine-tune these weights (a folder); Eq. 14's lambda is then "
                                                "held at its cap from step 0")
    for q in (p, r):
        q.add_argument("--train-primal", default="gpt", choices=PRIMALS,
                       help="what I_b of the training renders is (gradnet.Config.train_primal; base: data/gradnet_train)")
    args = ap.parse_args()
    {"prepare": prepare, "run": run}[args.cmd](args)


if __name__ == "__main__":
    main()
