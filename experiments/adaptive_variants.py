"""Adaptive sampling's settings against each other at equal samples (issue 40; docs/methods/adaptive.md
"Choices measured"): the pilot's share, the floor and cap, the map's box and the number of passes,
each with the classic map and with OIDN's half-buffer map; the RelMSE of demc, lbf and oidn after
each, against uniform sampling, on held-out procedural scenes (``mixed``, seeds 100010+, not those of
`experiments/adaptive.py`) with 2048-spp references, two independent renders per scene.

    python experiments/adaptive_variants.py [--scenes 6] [--width 96] [--spp 16] [--renders 2] [--variants 0,1,...]

``map_spp=pilot``: the map reads the whole pilot and every pass has a fixed weight (0.9.6's pooling).

Writes docs/results/adaptive/variants.json and variants.md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from common import num, write_study

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "adaptive"
METHODS = ("demc", "lbf", "oidn")
VARIANTS = ({"spec": "relvar"}, {"spec": "oidn:halves"},
            {"spec": "relvar", "initial": "half"}, {"spec": "oidn:halves", "initial": "half"},
            {"spec": "relvar", "floor_fraction": 0.3, "cap": 4.0}, {"spec": "oidn:halves", "floor_fraction": 0.3, "cap": 4.0},
            {"spec": "relvar", "smooth": 9}, {"spec": "oidn:halves", "smooth": 9},
            {"spec": "relvar", "passes": 2}, {"spec": "oidn:halves", "passes": 2},
            {"spec": "relvar", "map_spp": "pilot"}, {"spec": "oidn:halves", "map_spp": "pilot"})


POOLING = "the map reads half the pilot (fixed weight), the rest of the pilot and the last pass pooled by count"
POOLING_096 = "every pass at a fixed weight (0.9.6's pooling)"


def label(v: dict) -> str:
    rest = ", ".join(f"{k}={val}" for k, val in v.items() if k != "spec")
    return f"{v['spec']} ({rest or 'defaults'})"


def run(args) -> dict:
    import warnings

    import jaxdenoise
    from data_gen.adaptive import plan, render_adaptive
    from data_gen.integrator import PathSettings, derive_seed
    from data_gen.mitsuba_setup import setup_mitsuba
    from data_gen.render import camera_matrices, render_buffers, render_reference
    from data_gen.scenes import build_scene, load_scene
    from jaxdenoise.buffers import Buffers
    from jaxdenoise.metrics import relmse

    warnings.filterwarnings("ignore", message=".*outside its trained rates.*")
    setup_mitsuba("llvm_ad_rgb")
    st = PathSettings(max_depth=8, rr_depth=5)
    dn = {m: jaxdenoise.load(m) for m in METHODS}
    record = ["albedo", "albedo2", "normal", "position", "visibility", "depth", "roughness"]
    chosen = [VARIANTS[int(i)] for i in args.variants.split(",")] if args.variants else list(VARIANTS)
    rows = {"uniform": [], **{label(v): [] for v in chosen}}
    for k in range(args.scenes):
        scene = load_scene(build_scene("mixed", 100010 + k, width=args.width, height=args.width))
        ref = render_reference(scene, spp=args.ref_spp, seed=derive_seed(100010 + k, "reference"), settings=st)[0]
        cam = {a: b for a, b in camera_matrices(scene).items() if b is not None}

        def score(fields, smap=None):
            b = Buffers(**fields, spp=float(args.spp), **cam)
            if smap is not None:
                b = b.replace(spp_map=smap)
            return {m: float(relmse(np.asarray(dn[m](b)), ref)) for m in METHODS} | {
                "input": float(relmse(b.color, ref))}

        for r in range(args.renders):
            rows["uniform"].append(score(render_buffers(scene, spp=args.spp, seed=derive_seed(k, r), settings=st,
                                                        record=record)))
            for v in chosen:
                kw = {a: b for a, b in v.items() if a != "spec"}
                if kw.get("initial") == "half":
                    kw["initial"] = args.spp // 2
                if kw.get("map_spp") == "pilot":
                    kw["map_spp"] = plan(args.spp, kw.get("passes", 1), kw.get("initial"), 1)[0]
                method = v["spec"].split(":")[0]
                fields, _ = render_adaptive(scene, spp=args.spp, adaptive=v["spec"], seed=derive_seed(k, r, 9),
                                            settings=st, record=record, camera=cam, denoise=dn.get(method), **kw)
                smap = fields.pop("spp_map")
                rows[label(v)].append(score(fields, smap))
    summary = {name: {m: float(np.mean([x[m] for x in xs])) for m in ("input",) + METHODS} for name, xs in rows.items()}
    per = {name: {m: [x[m] for x in xs] for m in ("input",) + METHODS} for name, xs in rows.items()}
    return {"scenes": args.scenes, "width": args.width, "spp": args.spp, "ref_spp": args.ref_spp,
            "renders": args.renders, "summary": summary, "per_render": per,
            "pooling": POOLING, "command": "python experiments/adaptive_variants.py " + " ".join(args.argv)}


def page(res: dict) -> str:
    lines = ["# Adaptive sampling: settings at equal samples", "",
             f"Generated by `{res['command']}`: {res['scenes']} held-out `mixed` scenes at {res['width']}x{res['width']}, "
             f"{res['spp']} spp, {res['ref_spp']}-spp references, {res['renders']} independent renders per scene; "
             "mean RelMSE over them. Defaults: pilot a quarter of the budget, floor 0.1 and cap 8 times the pass's "
             f"mean, a 5x5 box over the map, one adaptive pass; {res.get('pooling', POOLING_096)} "
             "(docs/methods/adaptive.md).", ""]
    per = res.get("per_render")
    if per:
        lines += ["*geo ratio*: the geometric mean over the renders of the render's RelMSE over uniform "
                  "sampling's (same scene and render index; below 1: better than uniform), less swayed by one "
                  "scene's fireflies than the mean.", ""]
    head = ["input", "demc", "lbf", "oidn"]
    lines += ["| sampling | " + " | ".join(head) + (" | " + " | ".join(f"{m} geo ratio" for m in head) if per else "")
              + " |", "|---|" + "---:|" * (len(head) * (2 if per else 1))]
    for name, s in res["summary"].items():
        geo = []
        if per:
            for m in head:
                r = np.log(np.asarray(per[name][m]) / np.asarray(per["uniform"][m]))
                geo.append(num(float(np.exp(r.mean())), ".3f"))
        lines.append(f"| {name} | " + " | ".join(num(s[m]) for m in head) + (" | " + " | ".join(geo) if per else "")
                     + " |")
    lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--renders", type=int, default=2, help="independent renders per scene")
    ap.add_argument("--variants", default=None, help="comma list of indices into VARIANTS (default: all)")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    res = run(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_study(out, "variants.json", "variants.md", res, page)
    print(page(res))


if __name__ == "__main__":
    main()
