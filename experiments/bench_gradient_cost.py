"""Cost and quality of the gradient-domain buffers (issue 3, item 2 benchmark).

For each scene: the time of `data_gen.gradient.render_gradients` (base + two replayed shifted paths
per sample) against the plain colour render `data_gen.render.render_buffers` at the same spp and
resolution (median of ``--runs`` runs after one warm-up each, same process, same scene object), and
the variance of the replayed differences against that of the difference of two independent renders:
the aggregate ratio sum(dx_var) / sum(var_a[x] + var_b[x+1]) and the median of the per-pixel ratio.

    python experiments/bench_gradient_cost.py --size 128 --spp 16 --runs 5 \
        --out docs/results/data_gen_gradient.md
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_gen.gradient import render_gradients  # noqa: E402
from data_gen.integrator import PathSettings  # noqa: E402
from data_gen.mitsuba_setup import setup_mitsuba  # noqa: E402
from data_gen.render import render_buffers  # noqa: E402
from jaxdenoise.fsutil import write_json, write_text  # noqa: E402


def scenes(size: int) -> dict:
    """Mitsuba's built-in Cornell box, with its light seen directly, and the same box with the light
    hidden from the camera by a crop of the view (only the lower 3/4 of the box is framed)."""
    import mitsuba as mi

    out = {}
    box = mi.cornell_box()
    box["sensor"]["film"]["width"] = size
    box["sensor"]["film"]["height"] = size
    box["sensor"]["film"]["rfilter"] = {"type": "box"}
    out["cornell-box"] = box
    low = mi.cornell_box()
    low["sensor"]["film"].update({"width": size, "height": size, "rfilter": {"type": "box"}})
    # Look down a little and narrow the field of view so the ceiling light leaves the frame.
    low["sensor"]["to_world"] = mi.ScalarTransform4f().look_at(origin=[0, 0, 3.9], target=[0, -0.35, 0], up=[0, 1, 0])
    low["sensor"]["fov"] = 28.0
    out["cornell-box-no-light-in-view"] = low
    return out


def median_time(fn, runs: int) -> tuple[float, list[float]]:
    fn()  # warm-up: kernel compilation
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), ts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--out", default="docs/results/data_gen_gradient.md")
    args = ap.parse_args(argv)

    variant = setup_mitsuba()
    import mitsuba as mi

    settings = PathSettings()
    rows = []
    for name, d in scenes(args.size).items():
        scene = mi.load_dict(d)
        t_plain, ts_plain = median_time(lambda: render_buffers(scene, spp=args.spp, seed=1, settings=settings), args.runs)
        t_grad, ts_grad = median_time(lambda: render_gradients(scene, spp=args.spp, seed=1), args.runs)
        a = render_gradients(scene, spp=args.spp, seed=2)
        b = render_gradients(scene, spp=args.spp, seed=3)
        ix = a["primal_var"][:, :-1] + b["primal_var"][:, 1:]
        iy = a["primal_var"][:-1] + b["primal_var"][1:]
        vx, vy = a["dx_var"][:, :-1], a["dy_var"][:-1]
        mx, my = ix > 0, iy > 0
        rows.append({
            "scene": name, "size": args.size, "spp": args.spp,
            "plain_s": t_plain, "gradient_s": t_grad, "ratio": t_grad / t_plain,
            "plain_runs_s": ts_plain, "gradient_runs_s": ts_grad,
            "var_ratio_dx": float(vx.sum() / ix.sum()), "var_ratio_dy": float(vy.sum() / iy.sum()),
            "median_pixel_var_ratio_dx": float(np.median(vx[mx] / ix[mx])),
            "median_pixel_var_ratio_dy": float(np.median(vy[my] / iy[my])),
            "n_invalid": int(a["n_invalid"]),
        })
        print(json.dumps({k: v for k, v in rows[-1].items() if not k.endswith("runs_s")}), flush=True)

    cmd = "python experiments/bench_gradient_cost.py " + " ".join(
        f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items())
    lines = [
        "## Gradient-domain buffers: cost and variance",
        "",
        f"Reproduce: `{cmd}`",
        "",
        f"Mitsuba variant `{variant}`, {os.cpu_count()} CPU cores (shared with other jobs), "
        f"{platform.machine()}; times are medians of {args.runs} runs after a warm-up, in one process.",
        "`plain` = `data_gen.render.render_buffers` (colour only); `gradient` = "
        "`data_gen.gradient.render_gradients` (base + 2 replayed shifted paths per sample, same spp).",
        "Variance ratio = sum(dx_var) / sum(var_a[x] + var_b[x+1]) (two independent renders); "
        "median ratio = the median over pixels of the same ratio per pixel.",
        "",
        "| scene | size | spp | plain s | gradient s | time ratio | var ratio dx | var ratio dy | median px ratio dx | median px ratio dy |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['size']} | {r['spp']} | {r['plain_s']:.3f} | {r['gradient_s']:.3f} | "
            f"{r['ratio']:.2f} | {r['var_ratio_dx']:.3f} | {r['var_ratio_dy']:.3f} | "
            f"{r['median_pixel_var_ratio_dx']:.4f} | {r['median_pixel_var_ratio_dy']:.4f} |")
    lines.append("")
    out = Path(args.out)
    write_text(out, "\n".join(lines))
    write_json(out.with_suffix(".json"), {"config": vars(args), "variant": variant, "rows": rows})
    print(f"bench_gradient_cost: {len(rows)} scenes, wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
