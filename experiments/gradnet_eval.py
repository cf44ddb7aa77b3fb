"""GradNet against the classical screened-Poisson solvers on frames it never trained on (issue 15,
item 6): mean RelMSE and SSIM per sampling rate of the input (base image), ``poisson-l2``,
``poisson-l1``, ``gradnet`` and ``gradnet`` without the post-process of Eq. 13, with GradNet's
ratio to each solver. Every output is scored as the user gets it (`inference.nonnegative`: negative
samples set to 0, as `jaxdenoise bench` does; each row counts the pixels changed).

    python experiments/gradnet_eval.py --data data/gradnet_test --out docs/results/gradnet_eval.json

``--weights`` evaluates another weights folder (a run's ``best/``) instead of the shipped ones.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdenoise import metrics  # noqa: E402
from jaxdenoise.api import resolve  # noqa: E402
from jaxdenoise.inference import inference_fn, nonnegative, prepare  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import Method  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--weights", default=None, help="GradNet weights folder (default: the shipped ones)")
    ap.add_argument("--spps", default=None, help="comma list (default: every rate in the folder)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.io import read_buffers, read_image

    gn, gp = resolve("gradnet", args.weights)
    variants = {
        "input": resolve("input"),
        "poisson-l2": resolve("poisson-l2"),
        "poisson-l1": resolve("poisson-l1"),
        "gradnet": (gn, gp),
        "gradnet-no-postprocess": (Method(name="gradnet", module=gn.module,
                                          config=dataclasses.replace(gn.config, postprocess=False)), gp),
    }
    fns = {k: (m, p, inference_fn(m)) for k, (m, p) in variants.items()}
    wanted = None if args.spps is None else {int(s) for s in args.spps.split(",")}
    rows = []
    t0 = time.perf_counter()
    for shot in discover(args.data):
        ref = np.asarray(read_image(shot.reference), np.float32)[..., :3]
        for spp, renders in sorted(renders_by_spp(shot, wanted).items()):
            b, _ = read_buffers(renders[0].path)
            row = {"shot": shot.name, "spp": spp}
            for k, (m, p, fn) in fns.items():
                out, clamped = nonnegative(fn(p, prepare(m, b)))
                row[k] = {"relmse": float(metrics.relmse(out, ref)), "ssim": float(metrics.ssim(out, ref)),
                          "negative_clamped": clamped}
            rows.append(row)
            print(row["shot"], spp, {k: round(v["relmse"], 5) for k, v in row.items() if isinstance(v, dict)},
                  flush=True)
    summary = {}
    for spp in sorted({r["spp"] for r in rows}):
        rs = [r for r in rows if r["spp"] == spp]
        s = {k: {"relmse": float(np.mean([r[k]["relmse"] for r in rs])), "ssim": float(np.mean([r[k]["ssim"] for r in rs]))}
             for k in variants}
        s["frames"] = len(rs)
        s["l2_over_gradnet"] = s["poisson-l2"]["relmse"] / s["gradnet"]["relmse"]
        s["l1_over_gradnet"] = s["poisson-l1"]["relmse"] / s["gradnet"]["relmse"]
        s["gradnet_wins_per_frame_l1"] = int(sum(r["gradnet"]["relmse"] < r["poisson-l1"]["relmse"] for r in rs))
        s["gradnet_wins_per_frame_l2"] = int(sum(r["gradnet"]["relmse"] < r["poisson-l2"]["relmse"] for r in rs))
        summary[str(spp)] = s
    write_json(args.out, {"data": args.data, "weights": args.weights or "shipped", "rows": rows, "summary": summary,
                          "seconds": time.perf_counter() - t0, "load_average": os.getloadavg(),
                          "command": "python experiments/gradnet_eval.py " + " ".join(argv or sys.argv[1:])})
    for spp, s in summary.items():
        print(f"{spp} spp ({s['frames']} frames): " + ", ".join(f"{k} {s[k]['relmse']:.4g}/{s[k]['ssim']:.3f}"
                                                               for k in variants)
              + f"; L2/GradNet {s['l2_over_gradnet']:.2f}x, L1/GradNet {s['l1_over_gradnet']:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
