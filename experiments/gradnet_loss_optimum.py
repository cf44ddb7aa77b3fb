"""Where does GradNet's unsupervised loss have its minimum? (diagnostic for issue 15.)

Minimizes L_grad + alpha L_data (Guo 2019 Eq. 7 without the first-order term, exactly as
`jaxdenoise.methods.gradnet.loss_terms` computes them) directly over the mu-law image of each frame,
with Adam, no network, and scores the minimizer against the reference beside the noisy input and
`poisson-l1`. If the per-image optimum is no better than the input, no amount of training of the
network on this loss can beat the classical solver. ``--lambdas`` adds lambda L_1st (Eq. 10) with
the per-pixel G of the shipped network's G-branch held fixed (as the autoencoder's step holds it):
the whole of L_all at the lambda the schedule ends with (2).

    python experiments/gradnet_loss_optimum.py --data data/gradnet_val --spp 64 --steps 1500 --out docs/results/gradnet_loss_optimum.json
    python experiments/gradnet_loss_optimum.py --data data/gradnet_test --spp 256 --steps 1500 --alphas 1.0 --lambdas 0,2 --out docs/results/gradnet_loss_optimum_test256.json
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdenoise import metrics  # noqa: E402
from jaxdenoise.api import resolve  # noqa: E402
from jaxdenoise.inference import inference_fn, prepare  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import gradnet as G  # noqa: E402
from jaxdenoise.solvers.optim import adam  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--lr", type=float, default=1e-2)
    ap.add_argument("--alphas", default="1.0,0.2")
    ap.add_argument("--lambdas", default="0", help="weights of L_1st (G from the shipped G-branch)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.io import read_buffers, read_image

    l1m, l1p = resolve("poisson-l1")
    l1 = inference_fn(l1m)
    lambdas = [float(v) for v in args.lambdas.split(",")]
    gparams = resolve("gradnet")[1] if any(lambdas) else None
    rows = []
    for shot in discover(args.data):
        b, _ = read_buffers(renders_by_spp(shot, {args.spp})[args.spp][0].path)
        ref = np.asarray(read_image(shot.reference), np.float32)[..., :3]
        row = {"shot": shot.name, "input": float(metrics.relmse(b.color, ref)),
               "poisson-l1": float(metrics.relmse(np.asarray(l1(l1p, prepare(l1m, b))), ref))}
        for alpha, lam in ((float(a), lam) for a in args.alphas.split(",") for lam in lambdas):
            cfg = dataclasses.replace(G.Config(), alpha=alpha)
            x = G.inputs(b, cfg)
            if lam:
                g = G.predict(gparams, b, cfg)[1]
                w = G.first_order_weights(x["tb"], cfg)

            def loss(y):
                v = G.grad_loss(G.decompress(y, cfg), x, cfg) + cfg.alpha * jnp.abs(y - x["tb"]).sum(-1).mean()
                return v + lam * G.first_order_loss(y, g, x["feat"], w) if lam else v

            init, update = adam(args.lr, b1=0.9, b2=0.999)
            y = x["tb"]
            state = init(y)

            @jax.jit
            def step(y, s):
                v, g = jax.value_and_grad(loss)(y)
                y2, s2 = update(g, s, y)
                return y2, s2, v

            first = float(loss(y))
            for _ in range(args.steps):
                y, state, v = step(y, state)
            img = np.maximum(np.asarray(G.decompress(y, cfg)), 0.0)
            tag = f"alpha{alpha:g}" + (f"_lambda{lam:g}" if lam else "")
            row[f"optimum_{tag}"] = float(metrics.relmse(img, ref))
            row[f"loss_{tag}"] = {"at_input": first, "at_optimum": float(v)}
        rows.append(row)
        print(row, flush=True)
    keys = [k for k in rows[0] if k not in ("shot",) and not k.startswith("loss_")]
    summary = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    write_json(args.out, {"rows": rows, "mean": summary, "spp": args.spp, "steps": args.steps, "lr": args.lr,
                          "lambdas": lambdas,
                          "command": "python experiments/gradnet_loss_optimum.py " + " ".join(argv or sys.argv[1:])})
    print("mean", summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
