"""Denoiser-guided adaptive sampling against uniform sampling, at equal samples and at equal total time
(issue 40; `data_gen.adaptive`, `jaxdenoise.adaptive`, docs/methods/adaptive.md).

For every scene: a reference, uniform renders at 2..128 spp (the error-against-time curve of each
denoiser), and adaptive renders at the budgets (4, 16, 64 spp on average) with each map estimator;
every frame denoised by ``input``, ``demc``, ``lbf`` and ``oidn``. Total time = render (Dr.Jit
compilation excluded) + map (half buffers, denoising, estimate, allocation; adaptive only) +
denoise (the method's median of 3 warm calls on the scene's 16-spp frame, the same for every frame of
that size; XLA compilation excluded). Equal time: the uniform curve's RelMSE at the adaptive run's
total time, interpolated in log-log between the uniform rates that bracket it.

Scenes: held-out draws of the procedural families (``mixed``, seeds 100000+, as ``data/heldout``)
and the scene library's evaluation split, ``--width`` pixels wide (default 256), with independent
4096-spp references.

    python experiments/adaptive.py [--procedural 4] [--library 4] [--width 256] [--budgets 4,16,64] [--no-cost-aware]
                                   [--map-spp N|pilot] [--specs relvar,oidn-fast:halves/2,...] [--renders R]
                                   [--ref-cache DIR]

Writes docs/results/adaptive/adaptive.json, adaptive.md and error_vs_time.png.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from common import heldout_scenes, num, write_study

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "adaptive"
METHODS = ("input", "demc", "lbf", "oidn")
SPECS = ("relvar", "oidn:halves", "demc:halves", "demc:relvar")
UNIFORM = (2, 4, 8, 16, 32, 64, 128)
COST = {True: "cost-aware maps (a pixel's share divided by its pilot samples' mean path length)",
        False: "maps by error alone (not cost-aware)"}


def _denoisers():
    import jaxdenoise

    return {m: (None if m == "input" else jaxdenoise.load(m)) for m in METHODS}


def _time_call(fn, b, repeats=3) -> float:
    fn(b)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.asarray(fn(b))
        ts.append(time.perf_counter() - t0)
    return float(statistics.median(ts))


def run(args) -> dict:
    import warnings

    from data_gen.adaptive import map_split, parse_spec, plan, render_adaptive
    from data_gen.integrator import PathSettings, derive_seed
    from data_gen.mitsuba_setup import RenderTimer, setup_mitsuba
    from data_gen.render import camera_matrices, render_buffers, render_reference
    from data_gen.scenes import load_scene
    import jaxdenoise
    from jaxdenoise.buffers import Buffers
    from jaxdenoise.methods import get
    from jaxdenoise.metrics import relmse

    warnings.filterwarnings("ignore", message=".*outside its trained rates.*")
    variant = setup_mitsuba("llvm_ad_rgb")
    settings = PathSettings(max_depth=8, rr_depth=5)
    dn = _denoisers()
    record = sorted({f for m in METHODS for f in get(m).needs() if not f.endswith("_var") and f not in
                     ("color", "spp", "world_to_camera", "world_to_ndc")})
    budgets = [int(b) for b in args.budgets.split(",")]
    pilots = {b: plan(b, args.passes, None, 1)[0] for b in budgets}
    map_spp = {b: (pilots[b] if args.map_spp == "pilot" else map_split(pilots[b], None if args.map_spp is None
                                                                         else int(args.map_spp))) for b in budgets}
    specs = args.specs.split(",")
    dn_maps = {}
    scenes = []
    for label, scene, w, h, seed in heldout_scenes(args.procedural, args.library, args.width):
        t_scene = time.perf_counter()
        loaded = load_scene(scene, width=w, height=h)
        camera = {k: v for k, v in camera_matrices(loaded).items() if v is not None}
        ref, ref_noise = _reference(args.ref_cache, f"{label}_{w}x{h}_{args.ref_spp}_{seed}",
                                    lambda: render_reference(loaded, spp=args.ref_spp,
                                                             seed=derive_seed(seed, "reference"), settings=settings))
        rec = {"scene": label, "size": list(np.shape(ref)[:2][::-1]), "ref_spp": args.ref_spp,
               "ref_relmse_halves": ref_noise, "uniform": {}, "adaptive": {}, "denoise_seconds": {}}

        def score(fields, spp, spp_map=None):
            b = Buffers(**fields, spp=float(spp), **camera)
            if spp_map is not None:
                b = b.replace(spp_map=spp_map)
            out = {}
            for m in METHODS:
                x = b.color if m == "input" else dn[m](b)
                out[m] = float(relmse(np.asarray(x), ref))
            return out, b

        for s in UNIFORM:
            runs = []
            for r in range(args.renders):
                with RenderTimer() as t:
                    f = render_buffers(loaded, spp=s, seed=derive_seed(seed, "noisy", s, r), settings=settings,
                                       record=record)
                err, b = score(f, s)
                runs.append({"render_seconds": t.seconds, "relmse": err})
                if s == 16 and r == 0:
                    rec["denoise_seconds"] = {m: (0.0 if m == "input" else _time_call(dn[m], b)) for m in METHODS}
            rec["uniform"][str(s)] = _mean_runs(runs)
        for spec in specs:
            sp = parse_spec(spec)
            if sp.method is not None and sp.method not in dn and sp.method not in dn_maps:
                dn_maps[sp.method] = jaxdenoise.load(sp.method)   # a map's denoiser beside METHODS
            mapper = None if sp.method is None else dn.get(sp.method) or dn_maps[sp.method]
            # warm-up (not recorded): the map's XLA programs compile once per frame size
            render_adaptive(loaded, spp=budgets[0], adaptive=sp, passes=args.passes, map_spp=map_spp[budgets[0]],
                            seed=1, settings=settings, record=record, camera=camera, denoise=mapper,
                            cost_aware=args.cost_aware)
            for bud in budgets:
                runs = []
                for r in range(args.renders):
                    # render 0's seed is the one a single-render run used
                    key = (seed, "adaptive", spec, bud) + ((r,) if r else ())
                    fields, info = render_adaptive(loaded, spp=bud, adaptive=sp, passes=args.passes,
                                                   map_spp=map_spp[bud], seed=derive_seed(*key), settings=settings,
                                                   record=record, camera=camera, denoise=mapper,
                                                   cost_aware=args.cost_aware)
                    smap = fields.pop("spp_map")
                    err, _ = score(fields, bud, smap)
                    runs.append({"render_seconds": info["render_seconds"], "map_seconds": info["map_seconds"],
                                 "relmse": err, "pass_counts": info["pass_counts"]})
                rec["adaptive"][f"{spec}@{bud}"] = {"spec": spec, "spp": bud, "pilot_spp": info["pilot_spp"],
                                                    "map_spp": info["map_spp"], **_mean_runs(runs)}
        rec["wall_seconds"] = time.perf_counter() - t_scene
        print(f"{label}: {rec['wall_seconds']:.0f} s", flush=True)
        scenes.append(rec)
    res = {"scenes": scenes, "methods": list(METHODS), "specs": specs, "budgets": budgets, "uniform_spp": list(UNIFORM),
           "passes": args.passes, "renders": args.renders, "map_spp": {str(b): v for b, v in map_spp.items()},
           "ref_spp": args.ref_spp, "width": args.width, "cost_aware": args.cost_aware,
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "variant": variant,
                       "load_start": args.load_start, "load_end": os.getloadavg()[0]},
           "command": "python experiments/adaptive.py " + " ".join(args.argv)}
    res["summary"] = summarize(res)
    return res


def _reference(cache, key: str, render):
    """``render()``'s (reference, RelMSE of its halves), kept in ``cache`` (a folder) under ``key``
    when one is given (written to a temporary name, then renamed)."""
    if cache is None:
        return render()
    path = Path(cache) / (key.replace(":", "-").replace("/", "-") + ".npz")
    if path.exists():
        with np.load(path) as z:
            return z["ref"], float(z["noise"])
    from jaxdenoise.fsutil import atomic_path

    ref, noise = render()
    with atomic_path(path) as tmp:
        np.savez(tmp, ref=ref, noise=noise)
    return ref, noise


def _mean_runs(runs: list[dict]) -> dict:
    """One entry from ``runs`` independent renders: the mean seconds and RelMSE per method, each
    render's RelMSE under ``relmse_renders`` (with more than one); ``pass_counts`` of the first."""
    out = {k: float(np.mean([r[k] for r in runs])) for k in runs[0] if k.endswith("_seconds")}
    out["relmse"] = {m: float(np.mean([r["relmse"][m] for r in runs])) for m in runs[0]["relmse"]}
    if len(runs) > 1:
        out["relmse_renders"] = {m: [r["relmse"][m] for r in runs] for m in runs[0]["relmse"]}
    if "pass_counts" in runs[0]:
        out["pass_counts"] = runs[0]["pass_counts"]
    return out


def _equal_time(curve: list[tuple[float, float]], t: float) -> tuple[float, str]:
    """RelMSE of the uniform curve (time, error) at time ``t``, log-log interpolated; outside the
    measured range the nearest end (and a note)."""
    pts = sorted(curve)
    if t <= pts[0][0]:
        return pts[0][1], "below"
    if t >= pts[-1][0]:
        return pts[-1][1], "above"
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if t0 <= t <= t1:
            a = (math.log(t) - math.log(t0)) / max(math.log(t1) - math.log(t0), 1e-12)
            return math.exp((1 - a) * math.log(e0) + a * math.log(e1)), ""
    return pts[-1][1], "above"


def summarize(res: dict) -> list[dict]:
    rows = []
    for spec in res["specs"]:
        for bud in res["budgets"]:
            for m in res["methods"]:
                ad, un, eq, t_ad, outside = [], [], [], [], 0
                for sc in res["scenes"]:
                    a = sc["adaptive"][f"{spec}@{bud}"]
                    d = sc["denoise_seconds"][m]
                    total = a["render_seconds"] + a["map_seconds"] + d
                    curve = [(u["render_seconds"] + d, u["relmse"][m]) for u in sc["uniform"].values()]
                    e_eq, note = _equal_time(curve, total)
                    outside += bool(note)
                    ad.append(a["relmse"][m])
                    un.append(sc["uniform"][str(bud)]["relmse"][m])
                    eq.append(e_eq)
                    t_ad.append(total)
                mean = lambda v: float(np.mean(v))
                geo = lambda u: float(np.exp(np.mean(np.log(np.asarray(u) / np.asarray(ad)))))  # noqa: E731
                rows.append({"spec": spec, "spp": bud, "method": m, "adaptive": mean(ad), "uniform_equal_spp": mean(un),
                             "geo_gain_equal_spp": geo(un), "geo_gain_equal_time": geo(eq),
                             "uniform_equal_time": mean(eq), "adaptive_seconds": mean(t_ad),
                             "gain_equal_spp": mean(un) / mean(ad), "gain_equal_time": mean(eq) / mean(ad),
                             "wins_equal_time": int(sum(e > x for e, x in zip(eq, ad))),
                             "scenes": len(ad), "outside_uniform_range": outside})
    return rows


def _pooling(res: dict) -> str:
    if "map_spp" not in res:                   # 0.9.6 and before: every pass at a fixed weight
        return "every pass at a fixed weight (its share of the budget)"
    said = ", ".join(f"{v} of {b}" for b, v in res["map_spp"].items())
    return (f"the map reads {said} spp (the pilot's first samples; fixed weight), the rest of the pilot and the "
            "last pass pooled by count")


def _renders(res: dict) -> str:
    n = res.get("renders", 1)
    return ("one render per scene, rate and map" if n == 1 else
            f"{n} independent renders per scene, rate and map (RelMSE averaged over them per scene)")


def page(res: dict) -> str:
    lines = ["# Denoiser-guided adaptive sampling: uniform against adaptive, at equal samples and equal time", "",
             f"Generated by `{res['command']}`. {len(res['scenes'])} scenes "
             f"({', '.join(s['scene'] for s in res['scenes'])}), {res['width']} pixels wide, "
             f"{res['ref_spp']}-spp references; {_renders(res)}; one pilot (a quarter of the budget, at least "
             f"2 spp) and {res['passes']} adaptive pass(es); {_pooling(res)}; {COST[res['cost_aware']]}. "
             f"Machine: {res['machine']['cpus']} cores, load average "
             f"{num(res['machine']['load_start'], '.2f')} at the start, {num(res['machine']['load_end'], '.2f')} at "
             "the end.", "",
             "RelMSE is the mean over the scenes. *gain* = uniform / adaptive RelMSE (above 1: adaptive wins). "
             "Equal time: the uniform curve (2-128 spp, render + denoise) at the adaptive run's total time "
             "(render + map + denoise), interpolated in log-log per scene; *wins* counts the scenes where "
             "adaptive is below it; *outside* the scenes whose adaptive time fell outside the uniform range "
             "(the nearest end is used). *geo*: the geometric mean over the scenes of the per-scene gain, which one "
             "scene's fireflies sway less than the ratio of the means.", ""]
    for spec in res["specs"]:
        lines += [f"## Map: `{spec}`", "",
                  "| spp | method | adaptive | uniform, equal spp | gain | geo | uniform, equal time | gain | geo | "
                  "wins | outside | adaptive s |",
                  "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in res["summary"]:
            if r["spec"] != spec:
                continue
            geo = lambda k: num(r[k], ".3f") if k in r else "-"  # noqa: E731
            lines.append(f"| {r['spp']} | {r['method']} | {num(r['adaptive'])} | {num(r['uniform_equal_spp'])} | "
                         f"{num(r['gain_equal_spp'], '.3f')} | {geo('geo_gain_equal_spp')} | "
                         f"{num(r['uniform_equal_time'])} | "
                         f"{num(r['gain_equal_time'], '.3f')} | {geo('geo_gain_equal_time')} | "
                         f"{r['wins_equal_time']}/{r['scenes']} | "
                         f"{r['outside_uniform_range']} | {num(r['adaptive_seconds'], '.3f')} |")
        lines.append("")
    lines += _by_scene_set(res)
    lines += ["## Per scene: render and denoise seconds", "",
              "| scene | size | uniform 16 spp render s | " + " | ".join(f"{m} s" for m in res["methods"][1:])
              + " | reference RelMSE (halves) |", "|---|---|---:|" + "---:|" * (len(res["methods"]) - 1) + "---:|"]
    for sc in res["scenes"]:
        lines.append(f"| {sc['scene']} | {sc['size'][0]}x{sc['size'][1]} | {num(sc['uniform']['16']['render_seconds'], '.3f')} | "
                     + " | ".join(num(sc["denoise_seconds"][m], ".3f") for m in res["methods"][1:])
                     + f" | {num(sc['ref_relmse_halves'], '.2e')} |")
    lines.append("")
    return "\n".join(lines)


def _by_scene_set(res: dict) -> list[str]:
    """The equal-time gains (mean, geo, wins) over the library's scenes (hand-written, built unlike
    the procedural families) and over the procedural draws apart."""
    sets = {"library": [s for s in res["scenes"] if s["scene"].startswith("library:")],
            "procedural": [s for s in res["scenes"] if not s["scene"].startswith("library:")]}
    if not all(sets.values()):
        return []
    rows = {name: {(r["spec"], r["spp"], r["method"]): r for r in summarize(dict(res, scenes=sc))}
            for name, sc in sets.items()}
    lines = ["## Equal time by scene set", "",
             "The equal-time gain (mean; geo; wins) over the library's scenes and over the procedural draws apart.", "",
             "| map | spp | method | library | procedural |", "|---|---:|---|---|---|"]
    def cell(r):
        return (f"{num(r['gain_equal_time'], '.3f')}; {num(r['geo_gain_equal_time'], '.3f')}; "
                f"{r['wins_equal_time']}/{r['scenes']}")

    for spec in res["specs"]:
        for bud in res["budgets"]:
            for m in res["methods"]:
                if m == "input":
                    continue
                lines.append(f"| `{spec}` | {bud} | {m} | {cell(rows['library'][(spec, bud, m)])} | "
                             f"{cell(rows['procedural'][(spec, bud, m)])} |")
    return lines + [""]


def plot_adaptive(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ms = [m for m in res["methods"]]
    fig, axes = plt.subplots(1, len(ms), figsize=(4 * len(ms), 3.6))
    for ax, m in zip(axes, ms):
        us = res["uniform_spp"]
        t = [np.mean([sc["uniform"][str(s)]["render_seconds"] + sc["denoise_seconds"][m] for sc in res["scenes"]]) for s in us]
        e = [np.mean([sc["uniform"][str(s)]["relmse"][m] for sc in res["scenes"]]) for s in us]
        ax.loglog(t, e, "k.-", label="uniform")
        for spec in res["specs"]:
            pts = [r for r in res["summary"] if r["spec"] == spec and r["method"] == m]
            ax.loglog([r["adaptive_seconds"] for r in pts], [r["adaptive"] for r in pts], "o--", label=spec)
        ax.set_title(m)
        ax.set_xlabel("total seconds (render + map + denoise)")
        ax.set_ylabel("RelMSE (mean over scenes)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)


def main(argv=None) -> None:
    import sys

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--procedural", type=int, default=4)
    ap.add_argument("--library", type=int, default=4)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--budgets", default="4,16,64")
    ap.add_argument("--specs", default=",".join(SPECS))
    ap.add_argument("--passes", type=int, default=1)
    ap.add_argument("--ref-cache", default=None,
                    help="folder keeping the references between runs (a scene's label, size, spp and seed name "
                         "its file); default: none")
    ap.add_argument("--renders", type=int, default=1,
                    help="independent renders per scene, rate and map (RelMSE and seconds averaged over them)")
    ap.add_argument("--no-cost-aware", dest="cost_aware", action="store_false",
                    help="allocate by error alone, not error per path length")
    ap.add_argument("--map-spp", default=None,
                    help="the pilot's spp the map reads (default: half the pilot); 'pilot': all of it, every pass at "
                         "a fixed weight (0.9.6's frames)")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    if args.renders < 1:
        ap.error(f"--renders: expected a positive integer, got {args.renders}")
    args.argv = list(sys.argv[1:] if argv is None else argv)
    args.load_start = os.getloadavg()[0]
    res = run(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_study(out, "adaptive.json", "adaptive.md", res, page)
    plot_adaptive(res, out / "error_vs_time.png")
    print(page(res))


if __name__ == "__main__":
    main()
