"""Train the shipped LBF weights (`lbf`, `lbf-nlm`) on a fixed subset of data_gen's procedural
training scenes, under a wall-clock limit, and record how in jaxdenoise/weights/<name>/README.md.

    python experiments/lbf_train.py --method lbf --data data/train_rooms --scenes 0:20 \
        --out runs/lbf --minutes 20 [--resume]
    python experiments/lbf_train.py --method lbf --out runs/lbf --ship [--note TEXT]   # copy weights + README

With ``--val-scenes lo:hi`` (scenes of the same folder, disjoint from ``--scenes``) the run scores
itself on those scenes every ``--validate-every`` steps (`jaxdenoise.train`, "Validation") and
``--ship`` copies the best-scoring params instead of the last ones.

The scene subset is linked into ``<out>/data`` so the run (and a resume) sees exactly those scenes;
the remaining scenes of the folder stay unseen and can serve as held-out frames.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxdenoise import checkpoint  # noqa: E402
from jaxdenoise.fsutil import write_text  # noqa: E402
from jaxdenoise.methods import WEIGHTS_DIR  # noqa: E402


def select_scenes(data: Path, spec: str) -> list[Path]:
    """Scenes ``lo`` .. ``hi - 1`` of ``data``: the folders holding a ``reference.exr`` whose name
    ends in that index (data_gen's ``scene_XXXX``), so a partly rendered dataset selects the same
    scenes as a complete one; folders without an index in their name are sliced in sorted order."""
    try:
        lo, hi = (int(x) for x in spec.split(":"))
    except ValueError:
        raise SystemExit(f"--scenes {spec!r}: expected lo:hi, two integers (e.g. 0:32)") from None
    shots = sorted(p for p in data.iterdir() if p.is_dir() and (p / "reference.exr").is_file())
    index = [re.search(r"_(\d+)$", p.name) for p in shots]
    if shots and all(index):
        return [p for p, m in zip(shots, index) if lo <= int(m.group(1)) < hi]
    return shots[lo:hi]


def link_scenes(data: Path, spec: str, dest: Path) -> list[str]:
    scenes = select_scenes(data, spec)
    dest.mkdir(parents=True, exist_ok=True)
    for p in scenes:
        link = dest / p.name
        if not link.exists():
            link.symlink_to(p.resolve())
    return [p.name for p in scenes]


def ship(method: str, out: Path, note: str = "") -> Path:
    """Copy the run's weights (its ``best/`` when it was validated) into jaxdenoise/weights/<method>
    with a README saying how they were trained; the old folder is replaced only once the new one
    is complete."""
    resolved = json.loads((out / "train_config.json").read_text())
    ckpt_meta = json.loads((out / "checkpoint" / "config.json").read_text())
    hist = ckpt_meta.get("history", [])
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").is_file() else None
    if summary is not None and summary["steps_done"] == ckpt_meta["step"]:
        params, meta = checkpoint.load(out / "weights")
    else:  # the run (or its last resumed part) was stopped: its last checkpoint (every checkpoint_every steps)
        state, _ = checkpoint.load(out / "checkpoint")
        params = state["params"]
        elapsed = (out / "checkpoint" / "config.json").stat().st_mtime - (out / "train_config.json").stat().st_mtime
        summary = {"steps_done": ckpt_meta["step"], "final_loss": sum(hist[-10:]) / max(1, len(hist[-10:])),
                   "seconds": elapsed}
        meta = {"config": ckpt_meta["config"], "method": method, "steps": ckpt_meta["step"],
                "data": resolved["data"], "seed": resolved["seed"], "final_loss": summary["final_loss"],
                "note": "run stopped by hand at the session's time limit; last checkpoint shipped"}
    selection = ""
    if (out / "best" / checkpoint.PARAMS_FILE).is_file():
        params, meta = checkpoint.load(out / "best")
        val = meta["validation"]
        scores = ckpt_meta.get("validation", [])
        every = resolved["train"].get("validate_every")
        per = ", ".join(f"{v:.4g} at {k} spp" for k, v in sorted(val["per_spp"].items(), key=lambda kv: int(kv[0])))
        selection = f"""- selection: these are the params of step {val['step']} of the {summary['steps_done']}, the
  lowest mean validation RelMSE ({val['relmse']:.5g}: {per}) of the {len(scores)} validations
  (every {every} steps) on `{resolved['val_data']}` (scenes never used in training); the last
  validation, at step {scores[-1]['step'] if scores else '?'}, scored {scores[-1]['relmse'] if scores else float('nan'):.5g}.
"""
    dest = WEIGHTS_DIR / method
    tmp = dest.with_name(dest.name + ".new")
    if tmp.exists():
        shutil.rmtree(tmp)
    checkpoint.save(tmp, params, None, extra={k: v for k, v in meta.items()})
    scenes = json.loads((out / "scenes.json").read_text())
    text = f"""# Weights `{method}` (Kalantari, Bako, Sen 2015)

Trained with the generic loop `jaxdenoise.train.train` through:

```
{scenes['command']}
```

- data: `{scenes['data']}` (data_gen procedural `mixed`/rooms family, 128x128), scenes
  {', '.join(scenes['scenes'])} ({len(scenes['scenes'])} scenes; every other scene of that folder was
  never seen in training); spp {resolved['config']['train_spps']}, both noise instances.
- optimizer: {resolved['train']['optimizer']} (initial step {resolved['train']['learning_rate']}),
  {summary['steps_done']} steps of {resolved['config']['train_scenes_per_step']} scenes x
  {len(resolved['config']['train_spps'])} spp crops of {resolved['config']['train_crop']}x{resolved['config']['train_crop']},
  seed {resolved['seed']}, filter window {2 * resolved['config']['radius'] + 1}x{2 * resolved['config']['radius'] + 1}.
- started from: {('`' + resolved['init_from'] + '` (fine-tuned)') if resolved.get('init_from') else 'random weights (Sec. 3.1)'}.
- time: {summary['seconds'] / 60:.1f} min wall{'' if summary.get('line') else ' since the last start of the run'} (2 CPU cores shared with other jobs).
- final loss (Eq. 8, mean of the last 10 mini-batches): {summary['final_loss']:.5g};
  first 10 mini-batches: {sum(hist[:10]) / max(1, len(hist[:10])):.5g}.
{selection}
Files: `params.npz` (MLP weights `net`, input normalization `norm`), `config.json` (the method
config the weights were trained with, restored by `jaxdenoise.load`).
"""
    if note:
        text += "\n" + note.strip() + "\n"
    write_text(tmp / "README.md", text)
    old = dest.with_name(dest.name + ".old")
    if old.exists():
        shutil.rmtree(old)
    if dest.exists():
        dest.rename(old)
    tmp.rename(dest)
    if old.exists():
        shutil.rmtree(old)
    return dest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", default="lbf", choices=["lbf", "lbf-nlm"])
    ap.add_argument("--data", default="data/train_rooms")
    ap.add_argument("--scenes", default="0:20", help="slice of the sorted scene folders, lo:hi")
    ap.add_argument("--out", required=True)
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--crop", type=int, default=None, help="training crop size (Config.train_crop)")
    ap.add_argument("--scenes-per-step", type=int, default=None, help="Config.train_scenes_per_step")
    ap.add_argument("--optimizer", default=None, choices=["rprop", "adam"],
                    help="default: the method's (RPROP, Sec. 4.2)")
    ap.add_argument("--lr", type=float, default=None,
                    help="Adam step size, or RPROP's initial step size (default: the method's)")
    ap.add_argument("--val-scenes", default=None,
                    help="lo:hi slice of --data scored during training (must not overlap --scenes); "
                         "the best params are kept in <out>/best and shipped")
    ap.add_argument("--val-spps", default="4,16,64", help="sampling rates of the validation scenes")
    ap.add_argument("--validate-every", type=int, default=100)
    ap.add_argument("--init", default=None, help="weights folder to fine-tune (e.g. jaxdenoise/weights/lbf)")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--ship", action="store_true", help="copy the run's weights into jaxdenoise/weights/")
    ap.add_argument("--note", default="", help="with --ship: a paragraph appended to the weights' README")
    args = ap.parse_args()
    out = Path(args.out)
    if args.ship:
        print(f"shipped to {ship(args.method, out, args.note)}")
        return
    import dataclasses

    from jaxdenoise.fsutil import write_json
    from jaxdenoise.methods import get
    from jaxdenoise.train import TrainConfig, train

    config = get(args.method).config
    if args.crop is not None:
        config = dataclasses.replace(config, train_crop=args.crop)
    if args.scenes_per_step is not None:
        config = dataclasses.replace(config, train_scenes_per_step=args.scenes_per_step)

    names = link_scenes(Path(args.data), args.scenes, out / "data")
    val_names = link_scenes(Path(args.data), args.val_scenes, out / "val") if args.val_scenes else []
    if set(names) & set(val_names):
        raise SystemExit(f"--val-scenes {args.val_scenes} overlaps --scenes {args.scenes}: "
                         f"{sorted(set(names) & set(val_names))[:3]}")
    write_json(out / "scenes.json", {"data": args.data, "scenes": names, "val_scenes": val_names,
                                     "command": "python " + " ".join(sys.argv)})
    t0 = time.time()
    overrides = {k: v for k, v in (("optimizer", args.optimizer), ("learning_rate", args.lr)) if v is not None}
    val = {}
    if val_names:
        val = {"val_data": out / "val", "val_spps": [int(x) for x in args.val_spps.split(",")],
               "validate_every": args.validate_every}
    method = get(args.method, config)
    summary = train(method, out / "data", out, TrainConfig.for_method(
        method, resume=args.resume, steps=args.steps, seed=args.seed, progress=True, time_limit=args.minutes * 60,
        init_from=args.init, **overrides, **val))
    print(summary["line"], f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
