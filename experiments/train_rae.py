"""RAE (Chaitanya et al. 2017): the main training run and the Sec. 5 ablations, sized to one short
GPU lease (or this CPU), with the data moved as two compact exports.

Steps (docs/results/rae.md has the commands as run and what they gave):

1. ``prepare`` (here, with OpenImageIO): export the training fly-throughs (``data/rae_train``, 1 spp)
   as whole videos keeping ``--instances`` noise instances per frame (camera stops need them), and
   the validation fly-throughs (``data/rae_val``, 1 spp, one instance) as whole videos
   (`jaxdenoise.pipeline.Cache.export(whole=True)`, at most 60 MiB each).
2. ``run`` (anywhere JAX runs; needs neither OpenImageIO nor Mitsuba): the main run first, alone on
   the device for ``--main-seconds`` (``--main-crop`` crops), then the ablations side by side, one
   process each, for ``--ablation-seconds``: the combined loss against the spatial term alone
   (Sec. 4.4: paper SSIM 0.9335 -> 0.9417) and all auxiliary inputs against none and against the
   first rungs of Fig. 3's ladder (+normals, +normals +depth), each with seeds 0 and 1. Runs
   started together on one device share it unevenly, so the ablations are compared at the steps
   every run of the study reached (validation every ``--validate-every`` steps: RelMSE and SSIM);
   ``summary.json`` keeps each run's whole curve. Results go to ``--out``: the main run's best and
   last weights (one tar each) and ``summary.json``; the ablations' weights stay in ``--runs`` (a
   device machine sends back 64 MiB at most). Each run resumes from its checkpoint when started
   again.
3. ``one`` is what ``run`` starts per run (a separate process, so that runs overlap on the device);
   run by hand it also continues a run's weights elsewhere (``--init-from``, ``--lr``), e.g. on this
   CPU from the EXR folders (``--train data/rae_train --val data/rae_val``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from common import tar_folders

ROOT = Path(__file__).resolve().parent.parent

# name -> Config overrides of the ablation variants (Sec. 4.4 loss; Sec. 3.2 / Fig. 3 inputs)
VARIANTS = {
    "full": {},
    "spatial": {"loss_weights": (1.0, 0.0, 0.0)},
    "noaux": {"aux": ()},
    "normal": {"aux": ("normal",)},
    "normal_depth": {"aux": ("normal", "depth")},
}


def prepare(args) -> None:
    from jaxdenoise.methods import rae

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    cfg = rae.Config()
    out = {}
    for part, src, inst in (("train", args.train, args.instances), ("val", args.val, 1)):
        cache = rae.make_dataset(src, cfg, progress=True)
        out[part] = cache.export(work / f"rae_{part}.npz", n=10**9, whole=True, spps=(1,), instances=inst)
        out[part]["videos"] = len(cache.videos)
        print(part, json.dumps(out[part]))
    (work / "exports.json").write_text(json.dumps(out, indent=1))


def one(args) -> None:
    from jaxdenoise import train
    from jaxdenoise.methods import get, rae

    cfg = dataclasses.replace(rae.Config(train_crop=args.crop), **VARIANTS[args.variant])
    method = get("rae", cfg)
    t = time.perf_counter()
    lr = {} if args.lr is None else {"learning_rate": args.lr}
    s = train.train(method, args.train, Path(args.runs) / args.name, train.TrainConfig.for_method(
        method, resume=True, steps=args.max_steps, seed=args.seed, progress=False, val_data=args.val, val_spps=[1],
        validate_every=args.validate_every, checkpoint_every=args.validate_every, time_limit=args.seconds,
        init_from=args.init_from, **lr))
    rec = {"variant": args.variant, "seed": args.seed, "steps": s["steps_done"], "seconds": time.perf_counter() - t,
           "final_loss": s["final_loss"], "best": s.get("best"), "crop": args.crop, "params": rae.num_params(cfg),
           "crops_seen": s["steps_done"] * cfg.train_batch,
           "validation": [{k: v[k] for k in ("step", "relmse", "ssim")} for v in s.get("validation", [])]}
    tmp = Path(args.runs) / f".{args.name}.json.tmp"
    tmp.write_text(json.dumps(rec, indent=1, default=str))
    tmp.rename(Path(args.runs) / f"{args.name}.json")
    print(args.name, json.dumps({k: rec[k] for k in ("steps", "seconds", "final_loss")}), flush=True)


def _launch(args, name, variant, seed, crop, seconds, validate_every, log):
    cmd = [sys.executable, str(Path(__file__).resolve()), "one", "--name", name, "--variant", variant,
           "--seed", str(seed), "--crop", str(crop), "--seconds", str(seconds), "--steps", str(args.max_steps),
           "--validate-every", str(validate_every), "--train", args.train, "--val", args.val, "--runs", args.runs]
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONUNBUFFERED="1")
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)


def _common(curves: list[list[dict]]) -> dict:
    """The validation of each run at the last step that every run of a study reached."""
    steps = set.intersection(*({v["step"] for v in c} for c in curves)) if curves else set()
    if not steps:
        return {"step": None, "scores": []}
    s = max(steps)
    return {"step": s, "scores": [next(v for v in c if v["step"] == s) for c in curves]}


def run(args) -> None:
    out, runs = Path(args.out), Path(args.runs)
    out.mkdir(parents=True, exist_ok=True)
    runs.mkdir(parents=True, exist_ok=True)
    summary = {"started": time.time(), "runs": {}}

    def save():
        for f in sorted(runs.glob("*.json")):
            summary["runs"][f.stem] = json.loads(f.read_text())
        tmp = out / ".summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=1, default=str))
        tmp.rename(out / "summary.json")

    with open(out / "log.txt", "a") as log:
        if args.main_seconds > 0:
            p = _launch(args, args.main_name, "full", 0, args.main_crop, args.main_seconds, args.validate_every, log)
            p.wait()
            summary["main_rc"] = p.returncode
            save()
            # one tar each: a device machine sends back files of at most 16 MiB
            tar_folders(out, f"{args.main_name}_best.tar", {"best": runs / args.main_name / "best"})
            tar_folders(out, f"{args.main_name}_last.tar", {"weights": runs / args.main_name / "weights"})
        if args.ablation_seconds > 0:
            names = [(f"abl_{v}_s{s}", v, s) for v in args.variants.split(",") for s in (0, 1)]
            procs = [_launch(args, n, v, s, args.ablation_crop, args.ablation_seconds, args.ablation_validate_every, log)
                     for n, v, s in names]
            summary["ablation_rc"] = {n: p.wait() for (n, _, _), p in zip(names, procs)}
            save()
            by = lambda vs: [summary["runs"].get(n, {}).get("validation", []) for n, v, _ in names if v in vs]
            summary["studies"] = {"loss": _common(by({"full", "spatial"})),
                                  "aux": _common(by(set(VARIANTS) - {"spatial"}))}
    summary["finished"] = time.time()
    save()
    failed = {k: v for k, v in [("main", summary.get("main_rc", 0)), *summary.get("ablation_rc", {}).items()] if v}
    if failed:
        sys.exit(f"runs failed (exit codes {failed}): see {out / 'log.txt'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--train", default="data/rae_train")
    p.add_argument("--val", default="data/rae_val")
    p.add_argument("--instances", type=int, default=2, help="noise instances per training frame exported")
    p.add_argument("--work", default="runs/rae_data")
    for name in ("run", "one"):
        r = sub.add_parser(name)
        r.add_argument("--train", default="runs/rae_data/rae_train.npz")
        r.add_argument("--val", default="runs/rae_data/rae_val.npz")
        r.add_argument("--runs", default="runs/rae_gpu")
        r.add_argument("--validate-every", type=int, default=500)
        r.add_argument("--max-steps", "--steps", dest="max_steps", type=int, default=10**6,
                       help="a run's step cap (its time limit ends it first)")
    r = sub.choices["run"]
    r.add_argument("--out", default="runs/rae_out")
    r.add_argument("--main-seconds", type=float, default=300.0)
    r.add_argument("--main-crop", type=int, default=128)
    r.add_argument("--main-name", default="main")
    r.add_argument("--ablation-seconds", type=float, default=170.0)
    r.add_argument("--ablation-crop", type=int, default=64)
    r.add_argument("--ablation-validate-every", type=int, default=250)
    r.add_argument("--variants", default="full,spatial,noaux", help=f"comma list of {sorted(VARIANTS)}")
    o = sub.choices["one"]
    o.add_argument("--name", required=True)
    o.add_argument("--variant", choices=sorted(VARIANTS), default="full")
    o.add_argument("--seed", type=int, default=0)
    o.add_argument("--crop", type=int, default=64)
    o.add_argument("--seconds", type=float, default=None)
    o.add_argument("--init-from", default=None, help="weights folder to continue from (fine-tuning)")
    o.add_argument("--lr", type=float, default=None, help="Adam's base rate (default: the module's TRAIN)")
    args = ap.parse_args()
    {"prepare": prepare, "run": run, "one": one}[args.cmd](args)


if __name__ == "__main__":
    main()
