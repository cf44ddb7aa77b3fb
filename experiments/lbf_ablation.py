"""LBF claims (c) network size (Fig. 11: hidden 10 vs 20 vs (10, 10)) and (d) which secondary-
feature category matters most (Sec. 6: each Sec. 3.3 category removed in turn; the paper finds the
feature statistics matter most).

Reduced protocol (2 shared CPU cores, stated in docs/results/lbf.md): every variant is trained
from the same seed, on the same precomputed training set, for the same number of RPROP steps, with
a 15x15 filter window (radius 7) instead of 55x55; each is scored by the mean RelMSE and SSIM
(after spike removal) on held-out frames. "Removing" a category feeds its inputs as the constant 0
(the training mean after normalization), which is equivalent to deleting those inputs.

    python experiments/lbf_ablation.py --train data/train_rooms --scenes 0:6 \
        --test runs/lbf_eval_data --steps 60 --out docs/results

Writes ``lbf_ablation.json`` and ``lbf_ablation.md``.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise import checkpoint, metrics  # noqa: E402
from jaxdenoise.fsutil import write_json, write_text  # noqa: E402
from jaxdenoise.io import read_buffers, read_image  # noqa: E402
from jaxdenoise.methods import get, lbf  # noqa: E402
from jaxdenoise.methods.lbf_features import CATEGORIES  # noqa: E402
from jaxdenoise.train import TrainConfig, load_data, train  # noqa: E402
from common import num  # noqa: E402
from lbf_eval import frames  # noqa: E402
from lbf_train import link_scenes  # noqa: E402


def variants(base: lbf.Config, seeds: int = 1) -> list[tuple[str, str, lbf.Config, int]]:
    """(group, label, config, seed) of every variant; seeds 1.. of the paper's network measure the
    run-to-run spread that the other differences must exceed."""
    out = [("size", "hidden (10,) [paper]", base, 0),
           ("size", "hidden (20,)", dataclasses.replace(base, hidden=(20,)), 0),
           ("size", "hidden (10, 10)", dataclasses.replace(base, hidden=(10, 10)), 0)]
    for c in CATEGORIES:
        out.append(("features", f"without {c}", dataclasses.replace(base, drop_categories=(c,)), 0))
    for s in range(1, seeds):
        out.append(("seed", f"hidden (10,) [paper] seed {s}", base, s))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", default="data/train_rooms")
    ap.add_argument("--scenes", default="0:6")
    ap.add_argument("--test", required=True)
    ap.add_argument("--test-spp", default="4,16,64")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--radius", type=int, default=7)
    ap.add_argument("--runs", default="runs/lbf_ablation")
    ap.add_argument("--out", default="docs/results")
    ap.add_argument("--only", default=None, help="comma list of variant labels to run (default all)")
    ap.add_argument("--seeds", type=int, default=1,
                    help="train the paper's network with this many seeds (0 .. N-1) to measure the spread")
    ap.add_argument("--resume", action="store_true",
                    help="continue (or reuse, when finished) the variants' runs under --runs")
    args = ap.parse_args()
    t0 = time.time()
    runs = Path(args.runs)
    base = lbf.Config(radius=args.radius)
    names = link_scenes(Path(args.train), args.scenes, runs / "data")
    dataset = load_data(get("lbf", base), runs / "data")
    trained = []
    for group, label, cfg, seed in variants(base, args.seeds):
        if args.only and label not in args.only.split(","):
            continue
        run = runs / label.replace(" ", "_").replace(",", "").replace("(", "").replace(")", "").replace("[", "").replace("]", "")
        method = get("lbf", cfg)
        s = train(method, dataset, run, TrainConfig.for_method(method, steps=args.steps, progress=False,
                                                               checkpoint_every=args.steps, seed=seed,
                                                               resume=args.resume))
        trained.append((group, label, cfg, seed, run, s))
        print(f"trained {label}: loss {s['final_loss']:.4g} ({time.time() - t0:.0f} s)", flush=True)
    # Held-out frames are read after training (they may still be rendering when this starts).
    test_spp = {int(s) for s in args.test_spp.split(",")}
    tests = []
    prep_fn = jax.jit(lambda b: lbf.prepare(b, base))
    for shot, spp, path, refp in frames(Path(args.test)):
        if spp in test_spp:
            b, _ = read_buffers(path)
            b = b.only(lbf.needs(base))
            tests.append((shot, spp, prep_fn(b), read_image(refp)[..., :3], np.asarray(b.color)))
    results = []
    for group, label, cfg, seed, run, s in trained:
        params, _ = checkpoint.load(run / "weights")
        fn = jax.jit(lambda p, prep, cfg=cfg: lbf.postprocess(lbf.filter_with(lbf.filter_params(p, prep["x"], cfg), prep, cfg), cfg))
        rel, ss = [], []
        for shot, spp, prep, ref, _ in tests:
            img = np.asarray(fn(params, prep))
            rel.append(float(metrics.relmse(img, ref)))
            ss.append(float(metrics.ssim(img, ref)))
        spps = [spp for _, spp, _, _, _ in tests]
        by_spp = {str(k): float(np.mean([r for r, q in zip(rel, spps) if q == k])) for k in sorted(set(spps))}
        results.append({"group": group, "variant": label, "train_loss": s["final_loss"], "steps": s["steps_done"],
                        "test_relmse": float(np.mean(rel)), "test_ssim": float(np.mean(ss)),
                        "test_relmse_by_spp": by_spp, "test_relmse_per_frame": rel,
                        "seed": seed, "steps_this_run": s["steps_this_run"], "seconds_this_run": s["seconds"]})
        print(f"{label}: train loss {s['final_loss']:.4g}, test RelMSE {np.mean(rel):.4g}, SSIM {np.mean(ss):.4f} "
              f"({time.time() - t0:.0f} s)", flush=True)
    inp = float(np.mean([float(metrics.relmse(c, r)) for _, _, _, r, c in tests]))
    result = {"command": "python " + " ".join(sys.argv), "train_scenes": names, "test": args.test,
              "test_spp": sorted(test_spp), "test_frames": len(tests), "steps": args.steps,
              "radius": args.radius, "input_relmse": inp, "results": results, "seconds": time.time() - t0}
    write_json(Path(args.out) / "lbf_ablation.json", result)
    write_text(Path(args.out) / "lbf_ablation.md", page(result))
    print(f"lbf_ablation: {len(results)} variants in {time.time() - t0:.0f} s")


def page(res: dict) -> str:
    """``lbf_ablation.md`` from ``lbf_ablation.json`` alone: every variant's held-out scores, then
    the protocol and the run-to-run spread of the paper's network over its seeds."""
    spps = [str(k) for k in res["test_spp"]]
    rows = [f"| {r['group']} | {r['variant']} | {num(r['train_loss'])} | {num(r['test_relmse'])} | "
            + " | ".join(num(r["test_relmse_by_spp"][k]) for k in spps) + f" | {num(r['test_ssim'], '.4f')} |"
            for r in res["results"]]
    window = 2 * res["radius"] + 1
    names = res["train_scenes"]
    lines = ["# LBF claims (c) network size and (d) secondary-feature categories", "",
             "| group | variant | train loss (Eq. 8, last 10 steps) | held-out RelMSE | "
             + " | ".join(f"RelMSE {k} spp" for k in spps) + " | held-out SSIM |",
             "|---|---|---|---|" + "---|" * len(spps) + "---|", *rows, "",
             f"Reduced protocol: {res['steps']} RPROP steps per variant, filter window {window}x{window}, "
             f"training scenes {names[0]}..{names[-1]}, {res['test_frames']} held-out frames at spp "
             f"{res['test_spp']} (input RelMSE {num(res['input_relmse'])}).  ",
             f"Command: `{res['command']}`"]
    paper = [r for r in res["results"] if r["variant"].startswith("hidden (10,) [paper]")]
    if len(paper) > 1:
        rels, sss = [r["test_relmse"] for r in paper], [r["test_ssim"] for r in paper]
        lines += ["", f"Run-to-run spread of the paper's network over {len(paper)} seeds: held-out RelMSE "
                  f"{num(min(rels))}-{num(max(rels))}, SSIM {num(min(sss), '.4f')}-{num(max(sss), '.4f')}. "
                  "A variant's difference from the paper's network means something only where it leaves this range."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
