"""GradNet's per-channel colour level (issue 15, thirteenth session): does the network keep its input's
brightness in each colour channel, and does its own loss want it to?

1. **Level**: for each weights folder and each frame, the network's output without the post-process
   of Eq. 13 over its input base image, both box-filtered over 15 x 15 pixels, median over the frame,
   per colour channel (1.0 = the output keeps the base's level; the base is an unbiased estimate of
   the reference, so a ratio away from 1 on most of a frame is a colour cast the network adds).
2. **Loss**: on whole training renders, the module's own loss terms (Eq. 8, 9, 10 with lambda = 2)
   of the network's output with one colour channel multiplied by each ``--factors`` value: if a
   factor below or above 1 lowers every term, the cast is not what the loss asks for but where the
   optimizer stopped.

    python experiments/gradnet_colour_level.py --out docs/results/gradnet_colour_level.json
    python experiments/gradnet_colour_level.py --weights shipped,runs/gradnet_ema/best --out ...
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdenoise.fsutil import write_json  # noqa: E402
from common import box_mean  # noqa: E402

BOX = 15


def levels(weights: str | None, folder: str, spp: int, count: int) -> list[list[float]]:
    """Per frame, per channel: median over the frame of box(output) / box(base), no post-process."""
    from jaxdenoise.api import resolve
    from jaxdenoise.inference import inference_fn, prepare
    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.io import read_buffers
    from jaxdenoise.methods import Method

    gn, gp = resolve("gradnet", weights)
    m = Method(name="gradnet", module=gn.module, config=dataclasses.replace(gn.config, postprocess=False))
    fn = inference_fn(m)
    out = []
    for shot in list(discover(folder))[:count]:
        renders = renders_by_spp(shot, {spp}).get(spp)
        if not renders:
            raise SystemExit(f"error: {shot.path}: no render at {spp} spp")
        b, _ = read_buffers(renders[0].path)
        y = np.asarray(fn(gp, prepare(m, b)), np.float64)
        base = np.maximum(np.nan_to_num(np.asarray(b.color, np.float64)[..., :3]), 0.0)
        r = box_mean(y, BOX) / np.maximum(box_mean(base, BOX), 1e-6)
        e = BOX // 2
        out.append([float(v) for v in np.median(r[e:-e, e:-e], axis=(0, 1))])
    return out


def loss_under_rescale(weights: str | None, folder: str, spp: int, count: int, factors, lam: float) -> dict:
    """Mean loss terms over ``count`` whole renders with the output's channel c scaled by each factor."""
    import jax.numpy as jnp

    from jaxdenoise.api import resolve
    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.io import read_buffers
    from jaxdenoise.methods import gradnet as g

    gn, p = resolve("gradnet", weights)
    cfg = gn.config
    sums: dict[str, list[float]] = {}
    shots = list(discover(folder))[:count]
    for shot in shots:
        b, _ = read_buffers(renders_by_spp(shot, {spp})[spp][0].path)
        batch = {k: np.asarray(getattr(b, k))[None] for k in ("color", "dx", "dy", *g.FEATURES)}
        y, G, x = g.predict(p, batch, cfg)
        hdr = g.to_hdr(y, cfg)
        for c in range(3):
            for f in factors:
                t = g.output_terms(g.compress(hdr * jnp.ones(3).at[c].set(f), cfg), G, x, cfg)
                sums.setdefault(f"{'rgb'[c]} x{f:g}", []).append([float(t[k]) for k in ("data", "grad", "first")])
    out = {}
    for k, v in sums.items():
        d, gr, fo = np.mean(np.asarray(v), axis=0)
        out[k] = {"data": float(d), "grad": float(gr), "first": float(fo), "L_all": float(d + gr + lam * fo)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="shipped", help="comma list of weights folders ('shipped': the package's)")
    ap.add_argument("--frames", default="data/gradnet_train:64:16,data/gradnet_val:256:8,data/gradnet_test:256:10",
                    help="comma list of FOLDER:SPP:COUNT scored for the level")
    ap.add_argument("--loss-frames", default="data/gradnet_train:64:16", help="FOLDER:SPP:COUNT for the loss part")
    ap.add_argument("--factors", default="0.95,1,1.05")
    ap.add_argument("--lam", type=float, default=2.0, help="lambda of L_1st in L_all (Eq. 14's cap)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    factors = [float(f) for f in args.factors.split(",")]
    result = {"command": "python experiments/gradnet_colour_level.py " + " ".join(argv or sys.argv[1:]),
              "box": BOX, "weights": {}}
    for wname in args.weights.split(","):
        weights = None if wname == "shipped" else wname
        rec = {"level": {}}
        for spec in args.frames.split(","):
            folder, spp, count = spec.rsplit(":", 2)
            per = levels(weights, folder, int(spp), int(count))
            a = np.asarray(per)
            rec["level"][f"{folder}@{spp}"] = {"frames": per, "median": np.median(a, 0).tolist(),
                                                "min": a.min(0).tolist(), "max": a.max(0).tolist()}
            print(f"{wname} {folder} {spp} spp: median level r/g/b " +
                  " ".join(f"{v:.3f}" for v in np.median(a, 0)) +
                  "  (range over frames " + ", ".join(f"{lo:.3f}-{hi:.3f}" for lo, hi in zip(a.min(0), a.max(0))) + ")",
                  flush=True)
        folder, spp, count = args.loss_frames.rsplit(":", 2)
        rec["loss"] = loss_under_rescale(weights, folder, int(spp), int(count), factors, args.lam)
        for k, v in rec["loss"].items():
            print(f"  {k}: data {v['data']:.5f} grad {v['grad']:.5f} first {v['first']:.5f} L_all {v['L_all']:.5f}")
        result["weights"][wname] = rec
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
