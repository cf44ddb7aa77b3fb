"""Benchmark of data_gen (issue 3): writes docs/results/data_gen.json and docs/results/data_gen.md (`page`:
the page from the JSON alone).

Measures, on the same machine in one run (medians of ``--repeats`` runs after a warm-up, interleaved
so that load from other processes hits every contender alike):

1. samples per second of the buffer integrator (all buffers, and radiance only) against Mitsuba's own
   ``path`` integrator at equal spp, resolution and max depth (goal: buffers cost <= 2x);
2. radiance agreement: RelMSE(ours, path) against RelMSE(path, path') at high spp;
3. time saved by leaving out buffers a method does not need (per registered method's ``needs()``);
4. the cost of gradient-domain buffers (``data_gen.gradient.render_gradients``) when that module exists;
5. time and size of the standard training set, read from its manifest (``--train-dir``).

Usage: python experiments/bench_data_gen.py [--res 128] [--spp 16] [--repeats 5]
       python experiments/bench_data_gen.py --train-set-only   # refresh the training-set section only
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import data_gen  # noqa: E402
from data_gen import render, scenes  # noqa: E402
from data_gen.dataset import dataset_size_bytes  # noqa: E402
from jaxdenoise.metrics import relmse  # noqa: E402
from common import all_measured, write_study  # noqa: E402


def _time(fn, repeats):
    fn()  # warm-up (kernel compilation)
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def _train_set(train_dir: str) -> dict:
    """Size, render time, spp and reference noise of a data_gen dataset folder, from its manifest."""
    mpath = Path(train_dir) / "manifest.json"
    if not mpath.exists():
        return {}
    m = json.loads(mpath.read_text())
    sc = m.get("scenes", {})
    refs = [r.get("reference") or {} for r in sc.values()]
    runs = m.get("runs", [])
    return {"dir": str(Path(train_dir).relative_to(ROOT)) if Path(train_dir).resolve().is_relative_to(ROOT) else train_dir,
            "scenes": len(sc), "size_mib": dataset_size_bytes(train_dir) / 2**20,
            "render_seconds": float(sum(r.get("render_seconds", 0.0) for r in sc.values())),
            "reference_seconds": float(sum(x.get("seconds", 0.0) for x in refs)),
            "ref_spp": sorted({x.get("spp") for x in refs if x}),
            "median_ref_relmse_halves": float(np.median([x["relmse_halves"] for x in refs if x])) if refs else None,
            "spp": sorted({tuple(r["spp"]) for r in sc.values()}),
            "commands": [r.get("command") for r in runs],
            "run_wall_seconds": [r.get("wall_seconds") for r in runs],
            "run_status": [r.get("status", "done") for r in runs]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--agree-spp", type=int, default=1024)
    ap.add_argument("--train-dir", default=str(ROOT / "data" / "train_rooms"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "results"))
    ap.add_argument("--from-json", default=None, help="only rewrite the markdown from a saved data_gen.json")
    ap.add_argument("--train-set-only", action="store_true",
                    help="re-read only the training set's manifest into the saved data_gen.json, keep the timings")
    ap.add_argument("--train-note", default=None, help="a remark printed under the training-set section")
    a = ap.parse_args(argv)
    if a.train_set_only:
        res = json.loads((Path(a.out) / "data_gen.json").read_text())
        res["train_set"] = _train_set(a.train_dir)
        if a.train_note:
            res["train_set"]["note"] = a.train_note
        write_study(Path(a.out), "data_gen.json", "data_gen.md", res, page)
        return 0
    if a.from_json:
        from jaxdenoise.fsutil import write_text

        write_text(Path(a.out) / "data_gen.md", page(json.loads(Path(a.from_json).read_text())))
        return 0

    import drjit as dr
    import mitsuba as mi

    variant = data_gen.setup_mitsuba()
    st = data_gen.PathSettings(max_depth=a.max_depth)
    cases = {"default": data_gen.default_scene(width=a.res, height=a.res)}
    for fam, seed in (("objects", 1), ("rooms", 0), ("envmap", 5)):
        cases[f"{fam}:{seed}"] = data_gen.build_scene(fam, seed, width=a.res, height=a.res)
    npix = a.res * a.res
    speed_rows, agree_rows, leave_rows, grad_rows = [], [], [], []
    registry = importlib.import_module("jaxdenoise.methods")
    for name, d in cases.items():
        d = dict(d)
        d["integrator"] = {"type": "path", "max_depth": a.max_depth}
        s = scenes.load_scene(d)
        desc = scenes.describe(s)
        all_fields, _ = data_gen.plan_buffers(desc, st, None, a.spp)
        all_feats = [f for f in data_gen.FEATURES if f in all_fields]

        def path():
            img = mi.render(s, spp=a.spp, seed=0)
            dr.eval(img)
            np.asarray(img)

        def ours_color():
            render.render_buffers(s, spp=a.spp, seed=0, settings=st, record=())

        def ours_all():
            render.render_buffers(s, spp=a.spp, seed=0, settings=st, record=all_feats)

        # Feature sets the registered methods need (one contender per distinct set).
        method_feats: dict[str, tuple] = {}
        method_err: dict[str, str] = {}
        method_grad: dict[str, bool] = {}
        for mname in registry.names():
            try:
                need = registry.get(mname).needs()
            except Exception as exc:  # noqa: BLE001 - a method module another worker has not finished
                method_err[mname] = f"{type(exc).__name__}: {exc}"
                continue
            method_feats[mname] = tuple(f for f in data_gen.FEATURES if f in need or f + "_var" in need)
            method_grad[mname] = bool({"dx", "dy"} & set(need))

        def subset(feats):
            return lambda: render.render_buffers(s, spp=a.spp, seed=0, settings=st, record=feats)

        contenders = {"path": path, "ours_color": ours_color, "ours_all": ours_all}
        for feats in sorted(set(method_feats.values())):
            if feats and tuple(feats) != tuple(all_feats):
                contenders["feats:" + ",".join(feats)] = subset(feats)
        for fn in contenders.values():
            fn()
        times = {k: [] for k in contenders}
        for _ in range(a.repeats):  # interleaved: load from other jobs hits every contender alike
            for k, fn in contenders.items():
                t = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t)
        med = {k: statistics.median(v) for k, v in times.items()}
        speed_rows.append({"scene": name, "res": a.res, "spp": a.spp,
                           **{f"{k}_s": med[k] for k in ("path", "ours_color", "ours_all")},
                           **{f"{k}_msamples_per_s": npix * a.spp / med[k] / 1e6 for k in ("path", "ours_color", "ours_all")},
                           "all_over_path": med["ours_all"] / med["path"],
                           "color_over_path": med["ours_color"] / med["path"], "buffers": all_feats})

        # Leaving out: per registered method, only what it needs, against all buffers (same loop).
        for mname in registry.names():
            if mname in method_err:
                leave_rows.append({"scene": name, "method": mname, "error": method_err[mname]})
                continue
            feats = method_feats[mname]
            key = "ours_color" if not feats else ("ours_all" if tuple(feats) == tuple(all_feats) else "feats:" + ",".join(feats))
            leave_rows.append({"scene": name, "method": mname, "features": list(feats), "seconds": med[key],
                               "gradients": method_grad[mname], "all_seconds": med["ours_all"],
                               "saved_fraction": 1 - med[key] / med["ours_all"]})

        # Gradient buffers (other worker's integrator), when present.
        try:
            gradient = importlib.import_module("data_gen.gradient")
        except ImportError as exc:
            grad_rows.append({"scene": name, "error": f"data_gen.gradient not available: {exc}"})
        else:
            try:
                ts = _time(lambda: gradient.render_gradients(s, spp=a.spp, seed=0, max_depth=a.max_depth), a.repeats)
                grad_rows.append({"scene": name, "seconds": statistics.median(ts), "color_seconds": med["ours_color"],
                                  "over_color": statistics.median(ts) / med["ours_color"]})
            except Exception as exc:  # noqa: BLE001
                grad_rows.append({"scene": name, "error": f"{type(exc).__name__}: {exc}"})

        # Agreement at high spp (smaller image: this is about the estimator, not speed).
        d_small = dict(d)
        s_small = scenes.load_scene(d_small, width=32, height=32)
        ours = render.render_buffers(s_small, spp=a.agree_spp, seed=1, settings=st)["color"]
        pa = np.asarray(mi.render(s_small, spp=a.agree_spp, seed=2))
        pb = np.asarray(mi.render(s_small, spp=a.agree_spp, seed=3))
        # Pixels next to directly seen bright emitters: Mitsuba's film splats with a discretized
        # (interpolated) box filter, slightly wider than our exact one-pixel box, which shows at
        # high-contrast edges only. Report the ratio with and without those pixels.
        bright = pa.max(-1) > 2.0
        near = bright.copy()
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                near |= np.roll(np.roll(bright, dy, 0), dx, 1)
        keep = ~near
        e_o, e_p = float(relmse(ours, pa)), float(relmse(pb, pa))
        e_o2, e_p2 = float(relmse(ours[keep][None], pa[keep][None])), float(relmse(pb[keep][None], pa[keep][None]))
        agree_rows.append({"scene": name, "spp": a.agree_spp, "relmse_ours_vs_path": e_o,
                           "relmse_path_vs_path": e_p, "ratio": e_o / max(e_p, 1e-30),
                           "excluded_pixels": int(near.sum()), "ratio_without_light_edges": e_o2 / max(e_p2, 1e-30),
                           "mean_ratio": float(ours.mean() / pa.mean())})
        print(f"{name}: path {med['path']:.2f}s ours(all) {med['ours_all']:.2f}s ratio {med['ours_all'] / med['path']:.2f}",
              file=sys.stderr)

    train = _train_set(a.train_dir)

    res = {"variant": variant, "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
           "res": a.res, "spp": a.spp,
           "repeats": a.repeats, "max_depth": a.max_depth, "speed": speed_rows, "agreement": agree_rows,
           "leave_out": leave_rows, "gradients": grad_rows, "train_set": train,
           "command": "python experiments/bench_data_gen.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    out = Path(a.out)
    write_study(out, "data_gen.json", "data_gen.md", res, page)
    print(f"bench_data_gen: {len(speed_rows)} scenes -> {out / 'data_gen.md'}")
    return 0


def page(r: dict) -> str:
    """``data_gen.md`` from ``data_gen.json`` alone (a missing value raises, never prints a hole)."""
    all_measured(r, "data_gen.json")
    cmd = f"{r['command']:s}".strip()
    L = ["# data_gen benchmarks", "",
         "## Buffer integrator against Mitsuba's `path` (equal spp, resolution, depth)", "",
         "| scene | path s | ours, radiance only s | ours, all buffers s | all / path | Msamples/s path | Msamples/s all buffers | buffers |",
         "|---|---|---|---|---|---|---|---|"]
    for x in r["speed"]:
        L.append(f"| {x['scene']:s} | {x['path_s']:.3f} | {x['ours_color_s']:.3f} | {x['ours_all_s']:.3f} | "
                 f"**{x['all_over_path']:.2f}x** | {x['path_msamples_per_s']:.2f} | {x['ours_all_msamples_per_s']:.2f} | "
                 f"{', '.join(x['buffers'])} |")
    ratios = [x["all_over_path"] for x in r["speed"]]
    if not ratios:
        raise ValueError("data_gen.json: no speed rows")
    feat_cost = [1 - x["ours_color_s"] / x["ours_all_s"] for x in r["speed"]]
    L += ["", f"Median cost of all buffers relative to `path`: **{statistics.median(ratios):.2f}x** (goal <= 2x). "
          f"Recording every feature instead of radiance only takes {100 * statistics.median(feat_cost):.0f} % of the "
          "all-buffer time (median over scenes): that is the most that leaving buffers out can save, and the "
          "differences between feature subsets below are of the order of the timing noise on this shared machine."]
    L += ["", "## Radiance agrees with `path`", "",
          "RelMSE between our radiance and a `path` render, against RelMSE between two independent `path` "
          "renders (32x32). A ratio near 1 means the difference is the renders' own noise.", "",
          "The last columns leave out pixels within one pixel of a directly seen emitter (path render > 2): "
          "Mitsuba's film splats samples with a discretized, interpolated box filter that reaches slightly "
          "into the neighbouring pixels, while ours assigns each sample to exactly its pixel (needed for "
          "an i.i.d. variance of the mean); the difference shows only at such high-contrast edges.", "",
          "| scene | spp | RelMSE(ours, path) | RelMSE(path, path') | ratio | image-mean ratio | pixels left out | ratio without light edges |",
          "|---|---|---|---|---|---|---|---|"]
    for x in r["agreement"]:
        L.append(f"| {x['scene']:s} | {x['spp']:d} | {x['relmse_ours_vs_path']:.3e} | {x['relmse_path_vs_path']:.3e} | "
                 f"{x['ratio']:.2f} | {x['mean_ratio']:.4f} | {x['excluded_pixels']:d} | {x['ratio_without_light_edges']:.2f} |")
    L += ["", "## Leaving out what a method does not need", "",
          "Render time with only the features a method's `needs()` lists, against all buffers the scene can vary "
          "(medians from the same interleaved loop as above).", "",
          "| scene | method | features rendered | seconds | all buffers s | time saved |", "|---|---|---|---|---|---|"]
    for x in r["leave_out"]:
        if "error" in x:  # a method that could not be loaded in that run: nothing was measured for it
            L.append(f"| {x['scene']:s} | {x['method']:s} | (could not load: {x['error'][:80]}) | - | - | - |")
        else:
            feats = (', '.join(x['features']) or '(radiance only)') + (' + dx, dy (gradient integrator, timed below)' if x['gradients'] else '')
            L.append(f"| {x['scene']:s} | {x['method']:s} | {feats} | "
                     f"{x['seconds']:.3f} | {x['all_seconds']:.3f} | {100 * x['saved_fraction']:.0f} % |")
    L += ["", "## Gradient-domain buffers (`data_gen.gradient`)", ""]
    if r["gradients"] and all("error" not in x for x in r["gradients"]):
        L += ["| scene | gradients s | radiance only s | ratio |", "|---|---|---|---|"]
        for x in r["gradients"]:
            L.append(f"| {x['scene']:s} | {x['seconds']:.3f} | {x['color_seconds']:.3f} | {x['over_color']:.2f}x |")
    else:
        errs = sorted({x.get("error", "") for x in r["gradients"]})
        L.append("Not measured in this run: " + "; ".join(errs))
    L += ["", "## Standard training set", ""]
    t = r["train_set"]
    if t == {}:
        L.append("No training set manifest found.")
    else:
        L += [f"`{t['dir']:s}`: {t['scenes']:d} scenes, {t['size_mib']:.0f} MiB on disk, "
              f"{t['render_seconds'] / 60:.1f} min of rendering in total ({t['reference_seconds'] / 60:.1f} min of it references), "
              f"spp lists {', '.join('(' + ', '.join(map(str, s)) + ')' for s in t['spp'])}, reference spp "
              f"{', '.join(map(str, t['ref_spp']))}, median reference RelMSE between halves "
              f"{t['median_ref_relmse_halves']:.2e}."]
        if t["ref_spp"] and max(t["ref_spp"]) < 4096:
            r_spp = max(t["ref_spp"])
            proj = t["reference_seconds"] * 4096 / r_spp + (t["render_seconds"] - t["reference_seconds"])
            L += ["", f"These references have {r_spp} spp. Scaling their time linearly, the same set with 4096-spp "
                  f"references takes about {proj / 3600:.1f} h of rendering on this machine (references: "
                  f"{t['reference_seconds'] * 4096 / r_spp / 3600:.1f} h); re-running the generator with "
                  "`--ref-spp 4096` re-renders only the references."]
        L += ["", "Generator commands (wall time of each run; the second re-renders only the references, "
              "keeping the noisy files):", ""]
        if not len(t["commands"]) == len(t["run_wall_seconds"]) == len(t["run_status"]):
            raise ValueError("data_gen.json: train_set's commands, run_wall_seconds and run_status differ in length")
        for c, wall, st in zip(t["commands"], t["run_wall_seconds"], t["run_status"]):
            if c is None:
                raise KeyError("data_gen.json: a train_set run without its command")
            if st == "running":
                when = "# interrupted before it finished; the identical command below resumed it"
            elif wall is None:
                raise KeyError(f"data_gen.json: the train_set run {c!r} ({st}) has no wall time")
            else:
                when = f"# wall {wall / 60:.1f} min"
            L += [f"    {c:s}", f"    {when}", ""]
        if "note" in t:
            L += [f"{t['note']:s}"]
    L += ["", "## Run", "",
          f"Generated by `{cmd}` (variant `{r['variant']:s}`, "
          f"{r['res']:d}x{r['res']:d}, {r['spp']:d} spp, max_depth {r['max_depth']:d}, median of {r['repeats']:d} "
          "interleaved runs after a warm-up). "
          f"The machine is {r['cpu_count']:d} CPU cores ({r['machine']:s}) shared with other jobs, so absolute times "
          "are noisy; the ratios compare contenders measured in the same loop."]
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    sys.exit(main())
