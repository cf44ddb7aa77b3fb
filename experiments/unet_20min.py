"""The convolutional-networks issue's end-to-end check: a small U-Net built from `jaxdenoise.nn`,
trained for a fixed wall-clock budget (20 minutes) on real data_gen crops with the project's Adam and
pipeline, validated on frames it never trained on against the Gaussian filter's RelMSE.

    python experiments/unet_20min.py --train runs/demc_data/demc_train.npz --val runs/demc_data/val \\
        --minutes 20 --out docs/results/unet_20min.json

- network: U-Net with stages of 16 / 32 / 64 channels (two 3x3 convs + leaky ReLU 0.1 each), 2x2
  max pooling, nearest up-sampling, skip concatenation, linear 3-channel output (304k parameters);
- input: ``log1p`` of the 4-spp colour, albedo and shading normal (9 channels); output
  ``expm1(y)`` (a first run clamped ``y`` at 0 and its output died: every pixel 0 after the first
  steps, no gradient left); loss: RelMSE ``(y - r)^2 / (r^2 + 0.01)`` (the metric);
- data: 8 augmented 64x64 crops per step from the training export (`pipeline.open_training_data`),
  drawn by (seed, step); Adam 1e-3, constant;
- validation: every ``--validate-seconds``, the whole 128x128 frames of ``--val`` (EXR folder or
  export; scenes disjoint from training), mean RelMSE (docs/metrics.md), beside the Gaussian filter
  (the registered ``gaussian``) and the raw input on the same frames.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise import metrics, nn, train  # noqa: E402
from jaxdenoise.api import denoise  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import get  # noqa: E402
from jaxdenoise.pipeline import open_training_data  # noqa: E402
from jaxdenoise.solvers import optim  # noqa: E402
from common import unet  # noqa: E402

WIDTHS = (16, 32, 64)
FIELDS = ("albedo", "normal")


def features(b):
    get_ = (lambda f: getattr(b, f)) if not isinstance(b, dict) else (lambda f: b[f])
    color = jnp.maximum(jnp.asarray(get_("color")), 0.0)
    return jnp.concatenate([jnp.log1p(color)] + [jnp.asarray(get_(f)) for f in FIELDS], -1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", default="runs/demc_data/demc_train.npz")
    ap.add_argument("--val", default="runs/demc_data/val")
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--validate-seconds", type=float, default=120.0)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="docs/results/unet_20min.json")
    args = ap.parse_args()

    data = open_training_data(args.train, FIELDS, spps=(4,))
    val = train.load_validation(get("bilateral"), args.val, spps=(4,))  # colour, albedo, normal, ...
    refs = [v["reference"] for v in val]
    gauss = float(np.mean([metrics.relmse(denoise(v["buffers"], "gaussian"), r) for v, r in zip(val, refs)]))
    raw = float(np.mean([metrics.relmse(v["buffers"].color, r) for v, r in zip(val, refs)]))
    init, apply = unet(WIDTHS)
    _, params = init(jax.random.PRNGKey(args.seed), (-1, args.crop, args.crop, 3 + 3 * len(FIELDS)))
    n_params = int(sum(np.prod(a.shape) for a in jax.tree_util.tree_leaves(params)))
    opt_init, opt_update = optim.adam(1e-3)
    state = opt_init(params)

    def predict(p, b):
        x, size = nn.pad_to_multiple(features(b), 2 ** len(WIDTHS))
        return jnp.expm1(nn.crop_to(apply(p, x), size))

    @jax.jit
    def step(p, s, b):
        def loss(q):
            y = predict(q, b)
            return jnp.mean(jnp.square(y - b["reference"]) / (jnp.square(b["reference"]) + 0.01))
        value, g = jax.value_and_grad(loss)(p)
        p, s = opt_update(g, s, p)
        return p, s, value

    pred = jax.jit(predict)
    curve, losses = [], []
    t0 = time.perf_counter()
    train_s, next_val, k = 0.0, 0.0, 0
    while True:
        elapsed = time.perf_counter() - t0
        if elapsed >= next_val or train_s >= args.minutes * 60:
            score = float(np.mean([metrics.relmse(pred(params, v["buffers"]), r) for v, r in zip(val, refs)]))
            curve.append({"step": k, "train_seconds": train_s, "val_relmse": score,
                          "train_loss": float(np.mean(losses[-50:])) if losses else None})
            print(curve[-1], flush=True)
            next_val = elapsed + args.validate_seconds
            if train_s >= args.minutes * 60:
                break
        t = time.perf_counter()
        b = data.crops(args.batch, args.crop, np.random.default_rng([args.seed, k]), spps=(4,))
        params, state, value = step(params, state, {k_: b[k_] for k_ in ("color", *FIELDS, "reference")})
        losses.append(float(value))
        train_s += time.perf_counter() - t
        k += 1
    res = {"params": n_params, "widths": WIDTHS, "steps": k, "crops_seen": k * args.batch, "crop": args.crop,
           "train_minutes": train_s / 60, "wall_minutes": (time.perf_counter() - t0) / 60,
           "val_frames": len(val), "val": args.val, "train": args.train, "gaussian_relmse": gauss,
           "input_relmse": raw, "curve": curve, "final_below_gaussian": curve[-1]["val_relmse"] < gauss}
    write_json(Path(args.out), res)
    print(f"U-Net {n_params} params, {k} steps ({k * args.batch} crops) in {train_s / 60:.1f} min of training: "
          f"validation RelMSE {curve[0]['val_relmse']:.4f} -> {curve[-1]['val_relmse']:.4f}; Gaussian {gauss:.4f}, "
          f"input {raw:.4f}")


if __name__ == "__main__":
    main()
