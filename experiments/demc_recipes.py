"""DEMC training recipes measured at an equal budget on this machine (issue 33): Eq. 3's two readings
from scratch, and the loss's per-pixel scale as a fine-tune of the shipped weights.

    python experiments/demc_recipes.py eq3 --steps 250 --seeds 0,1 --lr 5e-4 --out runs/demc_eq3
    python experiments/demc_recipes.py finetune --loss-scale output --steps 700 --out runs/demc_scale
    python experiments/demc_recipes.py finetune --level-weight 4 --steps 700 --out runs/demc_level
    python experiments/demc_recipes.py finetune --level-weight 4 --level-pool 8 --level-scale output \
        --steps 400 --validate-every 50 --out runs/demc_level3
    python experiments/demc_recipes.py finetune --level-weight 4 --seeds 3 --steps 3000 --validate-every 100 \
        --out runs/demc_stage3

Both train on ``--data`` (default ``runs/demc_rates_data``: the scene library's training scenes and
40 procedural ``mixed`` scenes at 1/4/16/64 spp, jaxdenoise/weights/demc/README.md) and validate on
the library's ``val`` split every ``--validate-every`` steps, keeping ``best/`` by the geometric mean
of the validation RelMSE (`jaxdenoise.train`). ``eq3`` trains ``skip_init`` "decoder" ([I, 0, 0]) and
"all" ([I, I, I]) from a random init, one run per seed, the same crops for both readings (the seed
draws the crops) at Adam ``--lr`` (5e-4: the rate of the first from-scratch DEMC run,
docs/methods/demc.md); ``finetune`` starts from ``--init`` with the config's ``loss_scale`` and
``level_weight`` replaced, at the method's own rate (1e-4), one run per seed (a seed other than the
earlier stages' 0 draws crops they did not see).
Each run resumes from its checkpoint when started again; every run's summary goes to
``OUT/summary.json``.

    python experiments/demc_recipes.py report --runs runs/demc_eq3,runs/demc_scale,runs/demc_level \
        --data data/library_eval4k,data/heldout --out docs/results/demc_rates

``report`` scores every run's shipped choice (``best/``, or ``weights/`` where ``best/`` kept the
starting weights) and the current ``demc`` with `demc_levels.measure` (colour level, RelMSE, SSIM
at 1/4/16/64 spp on each ``--data`` folder) and writes ``recipes.json`` and ``recipes.md`` into
``--out`` with each run's budget and validation curve.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "experiments"))

from common import all_measured, num, write_study  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import get  # noqa: E402
from jaxdenoise.train import TrainConfig, load_data, train  # noqa: E402

SPPS = (1, 4, 16, 64)


def _shipped(run_dir: Path) -> tuple[Path, int]:
    """A run's choice: ``best/``, or ``weights/`` (its last step) where ``best/`` is the starting weights."""
    curve = json.loads((run_dir / "best" / "selection.json").read_text())
    if curve["selected_step"] == 0:
        return run_dir / "weights", int(curve["validation"][-1]["step"])
    return run_dir / "best", int(curve["selected_step"])


def report(args) -> None:
    from demc_levels import measure

    runs, entries = {}, ["demc"]
    for group in args.runs.split(","):
        summary = json.loads((Path(group) / "summary.json").read_text())
        for name, rec in summary["runs"].items():
            folder, step = _shipped(Path(group) / name)
            curve = json.loads((Path(group) / name / "best" / "selection.json").read_text())
            train_cfg = json.loads((Path(group) / name / "train_config.json").read_text())
            runs[name] = {**rec, "what": summary["what"], "scored": str(folder), "scored_step": step,
                          "crops": rec["steps"] * int(train_cfg["config"]["train_batch"]),
                          "crop": int(train_cfg["config"]["train_crop"]),
                          "learning_rate": train_cfg["train"]["learning_rate"],
                          "init_from": train_cfg["init_from"],
                          "validation": [{k: v[k] for k in ("step", "relmse_geomean", "per_spp")}
                                         for v in curve["validation"]]}
            entries.append(f"{name}={folder}")
    res = {"runs": runs, "spps": list(SPPS), "scores": measure(entries, args.data.split(","), list(SPPS))}
    res["command"] = "python experiments/demc_recipes.py " + " ".join(sys.argv[1:])
    print(write_study(Path(args.out), "recipes.json", "recipes.md", res, page))


def _medians(rec: dict, folder: str, spp: str) -> tuple[list, list]:
    import numpy as np

    return (np.median(np.asarray(rec["levels"][folder][spp]), 0).tolist(),
            np.mean(np.asarray(rec["scores"][folder][spp]), 0).tolist())


def page(res: dict) -> str:
    """``recipes.md`` from ``recipes.json`` alone."""
    import numpy as np

    all_measured(res, "recipes.json")
    runs, sc = res["runs"], res["scores"]
    folders = sc["folders"]
    lines = ["# DEMC training recipes at an equal budget (issue 33)", "",
             "Runs of `experiments/demc_recipes.py` on this CPU (2 cores): crops of 96x96 from the scene "
             "library's training scenes and 40 procedural `mixed` scenes at 1/4/16/64 spp, validated on the "
             "library's `val` split (geometric mean of RelMSE over 8 frames). Scored here: each run's choice "
             "(`best/`, or its last step where `best/` kept the starting weights) on the folders below, never "
             "trained or selected on. Level = median over frames of the 15x15 box-mean ratio output / reference "
             "per channel (`experiments/demc_levels.py`" + ("; surface pixels only, emitters left out"
                                                          if sc.get("masks") == "scene" else "")
             + "); RelMSE and SSIM are means over frames.", "",
             "## Runs", "", "| run | recipe | start | steps | crops | Adam lr | scored step | validation geomean there | seconds |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for name, r in runs.items():
        at = [v for v in r["validation"] if v["step"] == r["scored_step"]]
        cfg = r["config"]
        recipe = (f"Eq. 3 `{cfg['skip_init']}`" if r["what"] == "eq3" else
                  f"loss scale `{cfg['loss_scale']}`, level weight {num(float(cfg.get('level_weight', 0.0)), 'g')}"
                  + (f" on {cfg['level_pool']}x{cfg['level_pool']} blocks scaled by the `{cfg['level_scale']}`"
                     if "level_scale" in cfg else ""))
        lines.append(f"| {name} | {recipe} | {'random' if r['init_from'] is None else '`' + Path(r['init_from']).name + '`'} | "
                     f"{r['steps']} | {r['crops']} | {num(float(r['learning_rate']), 'g')} | {r['scored_step']} | "
                     f"{num(at[0]['relmse_geomean'], '.4f') if at else '-'} | {num(r['seconds'], '.0f')} |")
    for folder in folders:
        lines += ["", f"## `{folder}`", "", "| model | " + " | ".join(f"{s} spp RelMSE" for s in res["spps"])
                  + " | 4 spp SSIM | " + " | ".join(f"{s} spp level R/G/B" for s in res["spps"]) + " |",
                  "|---|" + "---:|" * (2 * len(res["spps"]) + 1)]
        for name, rec in sc["methods"].items():
            cells, levels, ssim4 = [], [], None
            for s in res["spps"]:
                lv, (rel, ssim) = _medians(rec, folder, str(s))
                cells.append(num(rel, ".4f"))
                levels.append("/".join(num(v, ".3f") for v in lv))
                if s == 4:
                    ssim4 = num(ssim, ".3f")
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {ssim4} | " + " | ".join(levels) + " |")
    eq3 = {name: r for name, r in runs.items() if r["what"] == "eq3"}
    if eq3:
        lines += ["", "## Eq. 3: the two readings, mean over seeds", "", "| reading | folder | "
                  + " | ".join(f"{s} spp RelMSE" for s in res["spps"]) + " | geometric mean |", "|---|---|" + "---:|" * (len(res["spps"]) + 1)]
        for reading in sorted({r["config"]["skip_init"] for r in eq3.values()}):
            names = [n for n, r in eq3.items() if r["config"]["skip_init"] == reading]
            for folder in folders:
                per = [[_medians(sc["methods"][n], folder, str(s))[1][0] for s in res["spps"]] for n in names]
                mean = np.mean(per, 0)
                geo = float(np.exp(np.mean(np.log(np.asarray(per)))))
                lines.append(f"| `{reading}` ({len(names)} seeds) | `{folder}` | " + " | ".join(num(float(v), ".4f") for v in mean)
                             + f" | {num(geo, '.4f')} |")
    lines += ["", f"Command: `{res['command']}`", ""]
    return "\n".join(lines)


def _run(method, data, out: Path, args, **fields) -> dict:
    run = TrainConfig.for_method(method, steps=args.steps, resume=True, val_data=args.val_data,
                                 validate_every=args.validate_every, select="geomean", progress=False, **fields)
    t = time.perf_counter()
    s = train(method, data, out, run)
    rec = {"steps": s["steps_done"], "seed": run.seed, "seconds": time.perf_counter() - t,
           "final_loss": s["final_loss"],
           "best_step": s["best"]["step"], "best_geomean": s["best"]["relmse_geomean"],
           "config": {f: getattr(method.config, f) for f in ("skip_init", "loss_scale", "level_weight", "level_pool",
                                                             "level_scale", "exposure")}}
    print(out.name, rec, flush=True)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("eq3", "finetune", "report"))
    ap.add_argument("--runs", default="runs/demc_eq3,runs/demc_scale,runs/demc_level", help="report: run groups")
    ap.add_argument("--data", default=None, help="training data (default runs/demc_rates_data); report: "
                    "comma-separated folders to score (default data/library_eval4k,data/heldout)")
    ap.add_argument("--val-data", default="data/library_val")
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--validate-every", type=int, default=50)
    ap.add_argument("--seeds", default=None, help="comma-separated seeds (the init and the crop order), one run "
                    "each (default: 0,1 for eq3, 0 for finetune; a finetune's run name gains _sN for a seed N > 0)")
    ap.add_argument("--lr", type=float, default=None, help="Adam's step size (default: 5e-4 for eq3, the method's "
                    "own 1e-4 for finetune; a finetune given --lr is named _lrX)")
    ap.add_argument("--init", default="jaxdenoise/weights/demc")
    ap.add_argument("--loss-scale", default="reference", choices=("reference", "output"))
    ap.add_argument("--level-weight", type=float, default=0.0)
    ap.add_argument("--level-pool", type=int, default=8, help="finetune: the level term's block size")
    ap.add_argument("--level-scale", default="reference", choices=("reference", "output"),
                    help="finetune: the level term's denominator (Config.level_scale)")
    args = ap.parse_args()
    if args.what == "report":
        args.data = args.data or "data/library_eval4k,data/heldout"
        return report(args)
    args.data = args.data or "runs/demc_rates_data"
    out = Path(args.out)
    base = get("demc", train_spps=SPPS)
    data = load_data(base, args.data, progress=False)
    summary: dict = {"what": args.what, "data": args.data, "val_data": args.val_data, "steps": args.steps, "runs": {}}
    if (out / "summary.json").exists():  # fine-tunes of one group run one after another into one folder
        summary["runs"] = json.loads((out / "summary.json").read_text())["runs"]
    seeds = [int(s) for s in (args.seeds or ("0,1" if args.what == "eq3" else "0")).split(",")]
    if args.what == "eq3":
        for seed in seeds:
            for reading in ("decoder", "all"):
                name = f"{reading}_s{seed}"
                summary["runs"][name] = _run(base.with_config(skip_init=reading), data, out / name, args, seed=seed,
                                             learning_rate=5e-4 if args.lr is None else args.lr)
                write_json(out / "summary.json", summary)
    else:
        stem = f"scale_{args.loss_scale}" + (f"_level{args.level_weight:g}" if args.level_weight else "")
        if args.level_weight and (args.level_pool, args.level_scale) != (8, "reference"):
            stem += f"_pool{args.level_pool}_{args.level_scale}"
        for seed in seeds:
            name = stem + (f"_lr{args.lr:g}" if args.lr is not None else "") + (f"_s{seed}" if seed else "")
            summary["runs"][name] = _run(base.with_config(loss_scale=args.loss_scale, level_weight=args.level_weight,
                                                          level_pool=args.level_pool, level_scale=args.level_scale),
                                         data, out / name, args, init_from=args.init, seed=seed,
                                         **({} if args.lr is None else {"learning_rate": args.lr}))
            write_json(out / "summary.json", summary)


if __name__ == "__main__":
    main()
