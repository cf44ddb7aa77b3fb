"""DEMC (Yang et al. 2019): the main training run and the Sec. 4.4 ablations, sized to one short
GPU lease (or this CPU), with the data moved as two compact exports.

Steps (docs/results/demc.md has the commands as run and what they gave):

1. ``prepare`` (here, with OpenImageIO): link the training shots (4-spp renders of
   ``data/train_rooms`` scenes 0-39, first noise instance, and every scene of ``data/train_demc``)
   and the validation shots (``data/train_rooms`` scenes 40-47, both instances) into ``--work``, and
   export both as whole 128x128 frames (`jaxdenoise.pipeline.Cache.export`, at most 60 MiB each).
2. ``run`` (anywhere JAX runs; needs neither OpenImageIO nor Mitsuba): the ablations first, DEMC,
   SEMC and DEMC-noSN with 2 seeds each, at an equal number of steps (set by DEMC's measured rate
   and ``--ablation-seconds``), then the main DEMC run for ``--main-seconds``; every run validates on
   the validation export and keeps its best weights; results go to ``--out`` as tar files of weight
   folders plus ``summary.json``. Each run resumes from its checkpoint when started again.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

from common import tar_folders

ROOT = Path(__file__).resolve().parent.parent


def _link_shot(src: Path, dst: Path, renders: list[str]) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for name in ["reference.exr", "shot.json", *renders]:
        if (src / name).exists() and not (dst / name).exists():
            os.symlink((src / name).resolve(), dst / name)


def prepare(args) -> None:
    from jaxdenoise import pipeline
    from jaxdenoise.methods import demc

    work = Path(args.work)
    rooms, extra = Path(args.rooms), Path(args.extra)
    for i in range(40):
        _link_shot(rooms / f"scene_{i:04d}", work / "train" / f"rooms_{i:04d}", ["spp0004_00.exr"])
    for sd in sorted(extra.glob("scene_*")):
        _link_shot(sd, work / "train" / f"extra_{sd.name}", ["spp0004_00.exr"])
    for i in range(40, 48):
        _link_shot(rooms / f"scene_{i:04d}", work / "val" / f"rooms_{i:04d}", ["spp0004_00.exr", "spp0004_01.exr"])
    out = {}
    for part in ("train", "val"):
        cache = pipeline.build_cache(work / part, demc.FEATURES, work / "cache", spps=(4,), progress=True,
                                     stats=demc.frame_stats(demc.Config()))  # whole-frame position moments
        n = len(cache.frames)
        out[part] = cache.export(work / f"demc_{part}.npz", n=n, whole=True, spps=(4,))
        out[part]["frames_available"] = n
        print(part, json.dumps(out[part]))
    (work / "exports.json").write_text(json.dumps(out, indent=1))


def run(args) -> None:
    import jax

    from jaxdenoise import train
    from jaxdenoise.methods import demc, get

    out, work = Path(args.out), Path(args.runs)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    summary = {"devices": [str(d) for d in jax.devices()], "runs": {}, "started": time.time()}

    def save_summary():
        tmp = out / ".summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=1, default=str))
        tmp.rename(out / "summary.json")

    dataset = None
    base = demc.Config(train_batch=args.batch, train_crop=args.crop)

    def one(name, cfg, seed, steps, time_limit, lr_every, init_from=None):
        nonlocal dataset
        method = get("demc", cfg)
        if dataset is None:
            dataset = train.load_data(method, args.train, progress=False)
        t = time.perf_counter()
        s = train.train(method, dataset, work / name, train.TrainConfig.for_method(
            method, resume=True, steps=steps, seed=seed, progress=False, val_data=args.val, learning_rate=args.lr,
            schedule="exponential", schedule_every=max(1, lr_every), schedule_factor=0.5,
            validate_every=args.validate_every, checkpoint_every=args.validate_every, time_limit=time_limit,
            init_from=init_from))
        rec = {"variant": cfg.variant, "seed": seed, "steps": s["steps_done"], "seconds": time.perf_counter() - t,
               "final_loss": s["final_loss"], "best": s.get("best"), "params": demc.num_params(cfg),
               "crops_seen": s["steps_done"] * cfg.train_batch, "crop": cfg.train_crop,
               "validation": [{"step": v["step"], "relmse": v["relmse"]} for v in s.get("validation", [])]}
        summary["runs"][name] = rec
        save_summary()
        print(name, json.dumps({k: rec[k] for k in ("steps", "seconds", "final_loss")}),
              "best", rec["best"] and round(rec["best"]["relmse"], 5), flush=True)
        return rec

    if args.ablation_seconds > 0:
        # DEMC seed 0 sets the common step count: as many steps as it makes in the time given
        # (its first step's compilation included).
        first = one("abl_demc_s0", base, 0, 10**7, args.ablation_seconds, 10**7)
        n = first["steps"]
        summary["ablation_steps"] = n
        for name, variant, seed in [("abl_demc_s1", "demc", 1), ("abl_nosn_s0", "nosn", 0),
                                    ("abl_nosn_s1", "nosn", 1), ("abl_semc_s0", "semc", 0),
                                    ("abl_semc_s1", "semc", 1)]:
            one(name, dataclasses.replace(base, variant=variant), seed, n, 3 * args.ablation_seconds, 10**7)
        for variant in ("demc", "nosn", "semc"):
            tar_folders(out, f"ablation_{variant}.tar", {f"{variant}_s{s}": work / f"abl_{variant}_s{s}" / "best"
                                                  for s in (0, 1)})
    if args.main_seconds > 0:
        # DEMC seed 1 ran with its step already compiled: its rate sizes the main run's schedule.
        rate = summary["runs"].get("abl_demc_s1", {})
        steps = int(rate["steps"] / max(rate["seconds"], 1e-9) * args.main_seconds) if rate else args.main_steps
        summary["main_planned_steps"] = steps
        one(args.main_name, base, 0, steps, 1.15 * args.main_seconds, max(1, steps // 3), args.init_from)
        tar_folders(out, f"{args.main_name}.tar", {"best": work / args.main_name / "best",
                                            "weights": work / args.main_name / "weights"})
    summary["finished"] = time.time()
    save_summary()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--rooms", default="data/train_rooms")
    p.add_argument("--extra", default="data/train_demc")
    p.add_argument("--work", default="runs/demc_data")
    r = sub.add_parser("run")
    r.add_argument("--train", default="runs/demc_data/demc_train.npz")
    r.add_argument("--val", default="runs/demc_data/demc_val.npz")
    r.add_argument("--runs", default="runs/demc")
    r.add_argument("--out", default="runs/demc_out")
    r.add_argument("--batch", type=int, default=32)
    r.add_argument("--crop", type=int, default=96)
    r.add_argument("--lr", type=float, default=5e-4)
    r.add_argument("--validate-every", type=int, default=250)
    r.add_argument("--ablation-seconds", type=float, default=35.0)
    r.add_argument("--main-seconds", type=float, default=200.0)
    r.add_argument("--main-steps", type=int, default=2000, help="when no ablation ran to measure the rate")
    r.add_argument("--main-name", default="main")
    r.add_argument("--init-from", default=None, help="weights folder to start the main run from (fine-tuning)")
    args = ap.parse_args()
    prepare(args) if args.cmd == "prepare" else run(args)


if __name__ == "__main__":
    main()
