"""Cost and quality of the gradient-domain buffers, replay vs reconnection shift (issue 16, item 4).

For each scene and shift (`data_gen.gradient.render_gradients`, ``shift="replay"`` / ``"reconnect"``):

- time per sample relative to the plain colour render `data_gen.render.render_buffers` at the same
  spp and resolution (medians of ``--runs`` runs after one warm-up each, same process);
- the fractions of offset paths that reconnected, went through a half-vector copy, and failed
  (reconnect only);
- the variance of dx, dy against that of the difference of two independent renders: the aggregate
  ratio sum(dx_var) / sum(var_a[x] + var_b[x+1]) and the median of the per-pixel ratio;
- the RelMSE against a ``--ref-spp`` reference (independent seed) of the input (base image),
  ``poisson-l2`` and ``poisson-l1`` at ``--spps`` samples per pixel, and of plain path tracing at
  equal render time (``round(spp * time ratio)`` samples of the plain renderer). The solvers' own
  time is reported beside (it is not part of "render time").

    python experiments/bench_gradient_cost.py --size 128 --spp 16 --runs 5 --spps 4,16,64 \
        --ref-spp 2048 --out docs/results/data_gen_gradient.md

Writes ``--out`` (the page; `page`: the page from the JSON alone) and the JSON beside it.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from data_gen import gradient  # noqa: E402
from data_gen.gpt import trace_gpt  # noqa: E402
from data_gen.gradient import SHIFTS, render_gradients  # noqa: E402
from data_gen.integrator import FEATURES, PathSettings  # noqa: E402
from data_gen.mitsuba_setup import setup_mitsuba  # noqa: E402
from data_gen.render import render_buffers  # noqa: E402
from data_gen.scenes import build_scene, default_scene, load_scene  # noqa: E402
from jaxdenoise.metrics import relmse  # noqa: E402
from common import all_measured, write_study  # noqa: E402


def scenes(size: int) -> dict:
    """Mitsuba's Cornell box (ceiling light in view), the demo scene (a rough-gold sphere: glossy),
    a textured room lit indirectly (procedural ``rooms``), an outdoor scene under an environment
    map seen through a thin lens (procedural ``envmap`` with the camera made a thin lens), and an
    object set with plastic, rough conductor and glass (procedural ``objects``)."""
    import mitsuba as mi

    out = {}
    box = mi.cornell_box()
    box["sensor"]["film"].update({"width": size, "height": size, "rfilter": {"type": "box"}})
    out["cornell-box"] = box
    out["demo-glossy"] = default_scene(width=size, height=size)
    out["textured-room"] = build_scene("rooms", 3, width=size, height=size)
    outdoor = build_scene("envmap", 5, width=size, height=size)
    outdoor["sensor"].update(type="thinlens", aperture_radius=0.08, focus_distance=4.0)
    out["outdoor-dof"] = outdoor
    out["objects-specular"] = build_scene("objects", 11, width=size, height=size)
    for d in out.values():
        d.pop("__family__", None)
    return out


def interleaved_times(fns: dict, runs: int) -> dict:
    """``{name: (median seconds, the runs)}`` of each callable: one warm-up each (kernel compilation),
    then ``runs`` rounds that call every one once, in turn, so a drift of the machine's speed during
    the measurement reaches every ratio alike."""
    for fn in fns.values():
        fn()
    ts = {k: [] for k in fns}
    for _ in range(runs):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t0)
    return {k: (statistics.median(v), v) for k, v in ts.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16, help="spp of the timing and variance runs")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--spps", default="4,16,64", help="spp of the reconstruction comparison")
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--scenes", default=None, help="comma list (default: all)")
    ap.add_argument("--out", default="docs/results/data_gen_gradient.md")
    args = ap.parse_args(argv)

    variant = setup_mitsuba()
    from jaxdenoise import methods
    from jaxdenoise.buffers import Buffers

    solvers = {n: methods.get(n) for n in ("poisson-l2", "poisson-l1")}
    params = {n: m.init(None) for n, m in solvers.items()}
    settings = PathSettings()
    spps = [int(s) for s in args.spps.split(",")]
    rows = []
    t_start = time.perf_counter()
    todo = scenes(args.size)
    if args.scenes:
        todo = {k: v for k, v in todo.items() if k in args.scenes.split(",")}
    for name, d in todo.items():
        scene = load_scene(d)
        ref = render_buffers(scene, spp=args.ref_spp, seed=987654, settings=settings)["color"].astype(np.float64)
        # The frame a dataset writes: every feature with the colour (issue 37 item 3's measure). For the
        # reconnection shift also the tracer before 0.9.3, one trace of every offset state run by every lane
        # (same outputs, bit for bit); data_gen.gradient calls trace_gpt by that name, so it is swapped here.
        single = functools.partial(trace_gpt, branch_states=False)

        def single_trace_frame():
            with mock.patch.object(gradient, "trace_gpt", single):
                return render_gradients(scene, spp=args.spp, seed=1, shift="reconnect", record=FEATURES)

        fns = {"plain": lambda: render_buffers(scene, spp=args.spp, seed=1, settings=settings),
               "buffers": lambda: render_buffers(scene, spp=args.spp, seed=1, settings=settings, record=FEATURES)}
        for shift in SHIFTS:
            fns[f"gradient_{shift}"] = functools.partial(render_gradients, scene, spp=args.spp, seed=1, shift=shift)
            fns[f"frame_{shift}"] = functools.partial(render_gradients, scene, spp=args.spp, seed=1, shift=shift,
                                                      record=FEATURES)
        fns["single_trace_frame_reconnect"] = single_trace_frame
        times = interleaved_times(fns, args.runs)
        t_plain, ts_plain = times["plain"]
        t_buf, ts_buf = times["buffers"]
        for shift in SHIFTS:
            t_grad, ts_grad = times[f"gradient_{shift}"]
            t_frame, ts_frame = times[f"frame_{shift}"]
            t_single, ts_single = times.get(f"single_trace_frame_{shift}", (None, None))
            ratio = t_grad / t_plain
            # the variance of gradients of the whole image (the directly seen emission included), which is
            # what the difference of two independent renders estimates
            a = render_gradients(scene, spp=args.spp, seed=2, shift=shift, direct_emission="included")
            b = render_gradients(scene, spp=args.spp, seed=3, shift=shift, direct_emission="included")
            ix = a["primal_var"][:, :-1] + b["primal_var"][:, 1:]
            iy = a["primal_var"][:-1] + b["primal_var"][1:]
            vx, vy = a["dx_var"][:, :-1], a["dy_var"][:-1]
            mx, my = ix > 0, iy > 0
            row = {
                "scene": name, "shift": shift, "size": args.size, "spp": args.spp,
                "plain_s": t_plain, "gradient_s": t_grad, "time_ratio": ratio,
                "plain_runs_s": ts_plain, "gradient_runs_s": ts_grad,
                "buffers_s": t_buf, "frame_s": t_frame, "buffers_runs_s": ts_buf, "frame_runs_s": ts_frame,
                "frame_ratio": t_frame / t_buf, "two_pass_ratio": (t_buf + t_grad) / t_buf,
                "single_trace_frame_s": t_single, "single_trace_frame_runs_s": ts_single,
                "single_trace_frame_ratio": None if t_single is None else t_single / t_buf,
                "var_ratio_dx": float(vx.sum() / ix.sum()), "var_ratio_dy": float(vy.sum() / iy.sum()),
                "median_pixel_var_ratio_dx": float(np.median(vx[mx] / ix[mx])),
                "median_pixel_var_ratio_dy": float(np.median(vy[my] / iy[my])),
                "shift_stats": a.get("shift_stats"), "n_invalid": int(a["n_invalid"]), "quality": [],
            }
            for s in spps:
                g = render_gradients(scene, spp=s, seed=100 + s, shift=shift)
                buf = Buffers(color=g["primal"], dx=g["dx"], dy=g["dy"], emission=g["emission"], spp=s)
                q = {"spp": s, "input": float(relmse(g["primal"], ref))}
                for n, m in solvers.items():
                    np.asarray(m.apply(params[n], buf))  # warm-up (compilation)
                    t0 = time.perf_counter()
                    rec = np.asarray(m.apply(params[n], buf))
                    q[f"{n}_solve_s"] = time.perf_counter() - t0
                    q[n] = float(relmse(rec, ref))
                eq = max(1, int(round(s * ratio)))
                q["equal_time_spp"] = eq
                q["plain_equal_time"] = float(relmse(render_buffers(scene, spp=eq, seed=200 + s, settings=settings)["color"], ref))
                row["quality"].append(q)
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if not k.endswith("runs_s")}), flush=True)

    cmd = "python experiments/bench_gradient_cost.py " + " ".join(
        f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if v is not None)
    res = {"config": vars(args), "command": cmd, "seconds": time.perf_counter() - t_start, "variant": variant,
           "cpu_count": os.cpu_count(), "machine": platform.machine(), "load_average": os.getloadavg(), "rows": rows}
    out = Path(args.out)
    write_study(out.parent, out.with_suffix(".json").name, out.name, res, page)
    print(f"bench_gradient_cost: {len(rows)} rows, wrote {out}")
    return 0


def page(res: dict) -> str:
    """``data_gen_gradient.md`` from ``data_gen_gradient.json`` alone (a missing value raises, never
    prints a hole)."""
    all_measured(res, "data_gen_gradient.json")
    cfg, rows, load = res["config"], res["rows"], res["load_average"]
    lines = [
        "# Gradient-domain buffers: replay vs reconnection shift, cost, variance, reconstruction",
        "",
        "| scene | shift | frame ratio (one pass) | one trace of every state (before 0.9.3) | frame ratio (two passes) "
        "| time ratio | var ratio dx / dy | median px ratio dx / dy | reconnected | half-vector | failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["shift"] == "replay" and r["shift_stats"] is None:
            fr = "- | - | -"  # replay has no reconnection
        else:
            st = r["shift_stats"]
            fr = f"{st['reconnected']:.3f} | {st['half_vector']:.3f} | {st['failed']:.3f}"
        single = "-" if r["single_trace_frame_ratio"] is None else f"{r['single_trace_frame_ratio']:.2f}"
        lines.append(
            f"| {r['scene']:s} | {r['shift']:s} | {r['frame_ratio']:.2f} | {single} | {r['two_pass_ratio']:.2f} | "
            f"{r['time_ratio']:.2f} | {r['var_ratio_dx']:.3f} / {r['var_ratio_dy']:.3f} | "
            f"{r['median_pixel_var_ratio_dx']:.4f} / {r['median_pixel_var_ratio_dy']:.4f} | {fr} |")
    lines += [
        "",
        "Frame ratios (issue 37's measure): the time of a whole gradient frame (colour, every feature of "
        "`data_gen.integrator.FEATURES`, dx, dy) over that of the same frame's buffers without gradients "
        "(`render_buffers` with every feature), at equal spp. One pass: `render_gradients(record=FEATURES)`, "
        "whose base paths record the colour and the features (bit-identical to `render_buffers`'; the API "
        "since 0.8.1, data_gen's shots since 0.8.2); two passes: `render_buffers` then `render_gradients` "
        "(what data_gen's shots rendered before 0.8.2), "
        "and the one pass with the tracer of 0.9.2 and before (`trace_gpt(branch_states=False)`: one trace of "
        "every offset state run by every lane; same outputs bit for bit), "
        "measured in the same run. Time ratio = `render_gradients` (no features; replay: base + 2 replayed "
        "paths per sample; reconnect: base + 4 offset paths) / `render_buffers` (colour only) at equal spp.",
        "Variance ratio = sum(dx_var) / sum(var_a[x] + var_b[x+1]) (two independent plain renders; dx, dy "
        "here hold the directly seen emission, `direct_emission=\"included\"`, the quantity such a difference "
        "estimates); "
        "median = the median over pixels of the per-pixel ratio. Fractions are of all offset paths "
        "(4 per sample; an offset whose base path sees only the sky never reconnects).",
        "",
        f"RelMSE against a {cfg['ref_spp']:d}-spp reference (independent seed). `input` = the base image at that "
        "spp; dx, dy leave the directly seen emission out and the solvers add the `emission` layer back "
        "(data_gen's default since 0.7.0; before and after: gradient_emission/); "
        "`plain @ equal time` = plain path tracing with `round(spp x time ratio)` samples (the spp "
        "in brackets), i.e. the same render time as the gradient render; solver seconds (after compilation) "
        "are not counted in render time. **Bold**: poisson-l2 below the input at equal spp / poisson-l1 "
        "below plain path tracing at equal time.",
        "",
        "| scene | shift | spp | input | poisson-l2 | poisson-l1 | plain @ equal time | l2 / l1 solve s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for q in r["quality"]:
            l2 = f"{q['poisson-l2']:.4g}"
            l1 = f"{q['poisson-l1']:.4g}"
            if q["poisson-l2"] < q["input"]:
                l2 = f"**{l2}**"
            if q["poisson-l1"] < q["plain_equal_time"]:
                l1 = f"**{l1}**"
            lines.append(f"| {r['scene']:s} | {r['shift']:s} | {q['spp']:d} | {q['input']:.4g} | {l2} | {l1} | "
                         f"{q['plain_equal_time']:.4g} ({q['equal_time_spp']:d}) | "
                         f"{q['poisson-l2_solve_s']:.2f} / {q['poisson-l1_solve_s']:.2f} |")
    lines += [
        "",
        "## Run",
        "",
        f"Reproduce: `{res['command']:s}` ({res['seconds']:.0f} s).",
        "",
        f"Mitsuba variant `{res['variant']:s}`, {res['cpu_count']:d} CPU cores, {res['machine']:s}, load average at the end "
        f"{load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1/5/15 min); times are medians of {cfg['runs']:d} runs after a "
        f"warm-up, in one process, at {cfg['size']:d}x{cfg['size']:d} and {cfg['spp']:d} spp, interleaved (each round "
        "renders every timed variant once, in turn).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
