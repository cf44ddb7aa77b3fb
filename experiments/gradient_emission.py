"""Directly seen emission kept out of the gradients, against the gradients that hold it (issue 37,
item 4; `data_gen.gradient.render_gradients`' ``direct_emission``, docs/methods/gradient_domain.md).

Kettunen et al. 2015's tracer keeps what a light seen directly gives a pixel out of dx, dy and adds it
back after the reconstruction; data_gen did not before 0.7.0 (``included``), and the light's edges then
carried gradient noise as large as the image's. For every scene and rate, one frame is rendered with
each setting from the same seed (the same base image, features and base paths: only dx, dy and the
``emission`` layer differ) and reconstructed by ``poisson-l2``, ``poisson-l1`` and ``gradnet`` (its
shipped weights were trained on ``included`` gradients); RelMSE against an independent reference.

Scenes: the five of ``experiments/bench_gradient_cost.py`` (``docs/results/data_gen_gradient.md``;
``demo-glossy`` is the demo's scene), held-out draws of the procedural families (``mixed``, seeds
100000+, as ``data/heldout``) and the scene library's evaluation split, all ``--width`` pixels wide.

    python experiments/gradient_emission.py [--procedural 8] [--library 4] [--width 128] \
        [--spps 4,16,64] [--ref-spp 2048]

Writes docs/results/gradient_emission/gradient_emission.{json,md}.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from common import all_measured, heldout_scenes, num, write_study

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "gradient_emission"
METHODS = ("poisson-l2", "poisson-l1", "gradnet")
MODES = ("included", "separate")


def _scenes(n_proc: int, n_lib: int, width: int) -> list[tuple]:
    from bench_gradient_cost import scenes

    out = [(name, d, None, None, 1000 + k, "bench") for k, (name, d) in enumerate(scenes(width).items())]
    for label, scene, w, h, seed in heldout_scenes(n_proc, n_lib, width):
        out.append((label, scene, w, h, seed, "library-eval" if label.startswith("library:") else "heldout"))
    return out


def run(args) -> dict:
    import warnings

    import jaxdenoise
    from data_gen.integrator import PathSettings, derive_seed
    from data_gen.mitsuba_setup import setup_mitsuba
    from data_gen.render import render_reference
    from data_gen.scenes import load_scene
    from data_gen.shot import render_frame
    from jaxdenoise.metrics import relmse

    warnings.filterwarnings("ignore", message=".*outside its trained rates.*")
    variant = setup_mitsuba("llvm_ad_rgb")
    settings = PathSettings()
    dn = {m: jaxdenoise.load(m) for m in METHODS}
    spps = [int(s) for s in args.spps.split(",")]
    rows = []
    t_start = time.perf_counter()
    for label, scene, w, h, seed, group in _scenes(args.procedural, args.library, args.width):
        loaded = load_scene(scene, width=w, height=h)
        ref, noise = render_reference(loaded, spp=args.ref_spp, seed=derive_seed(seed, "reference"), settings=settings)
        ref = np.asarray(ref, np.float64)
        for s in spps:
            row = {"scene": label, "group": group, "spp": s, "size": list(ref.shape[:2][::-1]),
                   "ref_relmse_halves": noise}
            for mode in MODES:
                b = render_frame(loaded, spp=s, methods=["gradnet", "poisson-l2"], seed=seed, gradient_emission=mode)
                rec = {"input": float(relmse(b.color, ref))}
                for m, fn in dn.items():
                    rec[m] = float(relmse(np.asarray(fn(b)), ref))
                if b.emission is not None:
                    e = np.asarray(b.emission)
                    rec["emission_pixels"] = float(np.mean(e.max(-1) > 0))
                    rec["emission_share"] = float(e.sum() / max(float(np.asarray(b.color).sum()), 1e-30))
                row[mode] = rec
            rows.append(row)
            print({k: row[k] for k in ("scene", "spp")}, {m: {k: round(v, 5) for k, v in row[m].items()} for m in MODES},
                  flush=True)
    return {"command": "python experiments/gradient_emission.py " + " ".join(
                f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out"),
            "config": {k: v for k, v in vars(args).items() if k != "out"}, "variant": variant,
            "seconds": time.perf_counter() - t_start, "cpu_count": os.cpu_count(), "machine": platform.machine(),
            "load_average": list(os.getloadavg()), "methods": list(METHODS), "modes": list(MODES), "rows": rows}


def group_means(res: dict) -> list[dict]:
    """Per group of scenes, rate and setting: mean RelMSE of the input and of each method, the input's
    mean over each method's (the ratio of means), and the frames each method leaves below the input."""
    out = []
    groups = sorted({r["group"] for r in res["rows"]}, key=["bench", "heldout", "library-eval"].index)
    for g in groups:
        for s in sorted({r["spp"] for r in res["rows"]}):
            rows = [r for r in res["rows"] if r["group"] == g and r["spp"] == s]
            for mode in res["modes"]:
                mean = {k: float(np.mean([r[mode][k] for r in rows])) for k in ["input", *res["methods"]]}
                below = {m: sum(r[mode][m] < r[mode]["input"] for r in rows) for m in res["methods"]}
                out.append({"group": g, "spp": s, "mode": mode, "frames": len(rows), "mean": mean,
                            "ratio": {m: mean["input"] / mean[m] for m in res["methods"]}, "below_input": below})
    return out


def page(res: dict) -> str:
    methods, modes = res["methods"], res["modes"]
    lines = ["# Directly seen emission out of the gradients (Kettunen's tracer) against in them", "",
             "Every frame rendered twice from one seed: `included` (dx, dy hold what a light seen directly gives a "
             "pixel, data_gen before 0.7.0) and `separate` (they leave it out, the `emission` layer holds it and "
             "every reconstruction adds it back: data_gen's default now). Same base image, features and base "
             "paths in both; RelMSE against an independent "
             f"{res['config']['ref_spp']}-spp reference. `gradnet`'s shipped weights were trained on `included` "
             "gradients.", "",
             "## Mean over the frames of each group", "",
             "Ratio = mean input RelMSE / mean method RelMSE; below = frames where the method is below its input.", "",
             "| scenes | spp | gradients | frames | input | " + " | ".join(methods) + " | "
             + " | ".join(f"{m} ratio" for m in methods) + " | " + " | ".join(f"{m} below" for m in methods) + " |",
             "|---|---:|---|---:|---:|" + "---:|" * (3 * len(methods))]
    for r in group_means(res):
        lines.append(f"| {r['group']} | {r['spp']} | {r['mode']} | {r['frames']} | {num(r['mean']['input'])} | "
                     + " | ".join(num(r["mean"][m]) for m in methods) + " | "
                     + " | ".join(num(r["ratio"][m], ".2f") for m in methods) + " | "
                     + " | ".join(f"{r['below_input'][m]}/{r['frames']}" for m in methods) + " |")
    lines += ["", "## Every frame", "",
              "| scene | spp | input | " + " | ".join(f"{m} {mode}" for m in methods for mode in modes)
              + " | emission pixels | emission share |",
              "|---|---:|---:|" + "---:|" * (len(methods) * len(modes) + 2)]
    for r in res["rows"]:
        sep = r["separate"]
        lines.append(f"| {r['scene']} | {r['spp']} | {num(r['included']['input'])} | "
                     + " | ".join(num(r[mode][m]) for m in methods for mode in modes)
                     + f" | {num(sep.get('emission_pixels', 0.0), '.3f')} | {num(sep.get('emission_share', 0.0), '.3f')} |")
    lines += ["", "Emission pixels: the fraction of pixels a light seen directly covers (any of its samples); share: "
              "the emission layer's sum over the colour's.", "", "## Run", "",
              f"Reproduce: `{res['command']}` ({res['seconds']:.0f} s).", "",
              f"Mitsuba variant `{res['variant']}`, {res['cpu_count']} CPU cores, {res['machine']}, load average at the "
              f"end {' / '.join(f'{v:.2f}' for v in res['load_average'])} (1/5/15 min).", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--procedural", type=int, default=8, help="held-out mixed draws (seeds 100000+)")
    ap.add_argument("--library", type=int, default=4, help="scenes of the library's evaluation split")
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--spps", default="4,16,64")
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    res = run(args)
    all_measured(res, "gradient_emission.json")
    out = Path(args.out)
    print(f"gradient_emission: wrote {write_study(out, 'gradient_emission.json', 'gradient_emission.md', res, page)}")


if __name__ == "__main__":
    main()
