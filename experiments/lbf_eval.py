"""LBF claims (a) and (b) of Kalantari, Bako, Sen 2015 on frames never used in training.

(a) LBF beats the best single global setting of the same cross-bilateral filter, and beats no
    filtering, in RelMSE and SSIM, at 4-64 spp (Sec. 5, Fig. 8-9).
(b) its error keeps falling above 64 spp, the highest rate it was trained on (Fig. 9).

"Best single global setting": the same pipeline as `lbf` (prefilter, cross-bilateral with beta = 7,
55x55 window, spike removal) with one constant spatial lambda and one constant lambda shared by the
five features, picked from a grid *per sampling rate* as the one with the lowest mean RelMSE on
these very test frames (an oracle choice: the strongest possible global setting, which no real
user gets). ``lbf-nlm`` is listed beside them.

    python experiments/lbf_eval.py --data runs/lbf_eval_data --out docs/results \
        [--weights-lbf runs/lbf/weights] [--weights-nlm runs/lbf-nlm/weights]

Writes ``lbf_eval.json`` (every frame x method) and ``lbf_eval.md`` (tables).
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise import api, metrics  # noqa: E402
from jaxdenoise.inference import inference_fn  # noqa: E402
from jaxdenoise.data import discover, renders_by_spp  # noqa: E402
from jaxdenoise.fsutil import write_json, write_text  # noqa: E402
from jaxdenoise.io import read_buffers, read_image  # noqa: E402
from jaxdenoise.methods import lbf  # noqa: E402
from common import num  # noqa: E402
from lbf_train import select_scenes  # noqa: E402

THETA_S = (2.0, 5.0, 12.0, 30.0)  # global spatial std (pixels)
THETA_F = (1.0, 4.0, 16.0, float("inf"))  # global feature std (noise-std units, Eq. 12); inf: off


def frames(data: Path, instance: int = 0, scenes: str | None = None):
    """(shot name, spp, path, reference path) for the ``instance``-th render (name order) of every
    sampling rate of every shot (`jaxdenoise.data`, spp from the EXR header); ``scenes`` ``"lo:hi"``
    keeps those scenes (as `lbf_train` selects them)."""
    keep = {p.name for p in select_scenes(data, scenes)} if scenes else None
    for shot in discover(data):
        if keep is not None and shot.name not in keep:
            continue
        for spp, renders in sorted(renders_by_spp(shot).items()):
            if instance < len(renders):
                yield shot.name, spp, renders[instance].path, shot.reference


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", default="docs/results")
    ap.add_argument("--weights-lbf", default=None)
    ap.add_argument("--weights-nlm", default=None)
    ap.add_argument("--no-grid", action="store_true")
    ap.add_argument("--scenes", default=None, help="lo:hi slice of the sorted shot folders (e.g. validation scenes)")
    ap.add_argument("--spp", default="4,16,64,128,256", help="sampling rates evaluated")
    ap.add_argument("--global-spp", default="4,16,64", help="sampling rates of the global-setting grid")
    ap.add_argument("--parts", default="input,lbf,lbf-nlm,global",
                    help="what to compute now; results already in --out/lbf_eval.json are kept (merge)")
    args = ap.parse_args()
    data, out = Path(args.data), Path(args.out)
    t0 = time.time()

    parts = set(args.parts.split(","))
    m_lbf, p_lbf = api.resolve("lbf", args.weights_lbf) if "lbf" in parts else (None, None)
    m_nlm, p_nlm = api.resolve("lbf-nlm", args.weights_nlm) if "lbf-nlm" in parts else (None, None)
    f_lbf = inference_fn(m_lbf) if m_lbf else None
    f_nlm = inference_fn(m_nlm) if m_nlm else None
    cfg = lbf.Config()  # the global baseline uses the paper's filter settings (same as lbf)
    old_path = out / "lbf_eval.json"
    old = {r["file"]: r for r in json.loads(old_path.read_text())["records"]} if old_path.is_file() else {}
    prep_fn = jax.jit(lambda b: lbf.prepare(b, cfg))

    @jax.jit
    def global_filter(prep, lam_s, lam_f):
        h, w = prep["color"].shape[:2]
        k = len(cfg.features)
        lam = jnp.concatenate([jnp.full((h, w, 1), lam_s), jnp.full((h, w, k), lam_f)], -1)
        return lbf.postprocess(lbf.filter_with(lam, prep, cfg), cfg)

    grid = list(itertools.product(THETA_S, THETA_F))
    records = []
    spps_eval = {int(x) for x in args.spp.split(",")}
    spps_global = {int(x) for x in args.global_spp.split(",")}
    for shot, spp, path, refp in frames(data, scenes=args.scenes):
        if spp not in spps_eval:
            continue
        ref = read_image(refp)[..., :3]
        b, _ = read_buffers(path)
        b = b.only(lbf.needs(cfg))
        row = old.get(str(path), {"shot": shot, "spp": spp, "file": str(path)})

        def score(name, img):
            img = np.asarray(img)
            row[name] = {"relmse": float(metrics.relmse(img, ref)), "ssim": float(metrics.ssim(img, ref))}

        if "input" in parts:
            score("input", b.color)
        if f_lbf:
            score("lbf", f_lbf(p_lbf, b))
        if f_nlm:
            score("lbf-nlm", f_nlm(p_nlm, b))
        if "global" in parts and not args.no_grid and spp in spps_global:
            prep = prep_fn(b)
            for ts, tf in grid:
                if f"global_s{ts}_f{tf}" in row:  # kept from an earlier run (merge)
                    continue
                score(f"global_s{ts}_f{tf}", global_filter(prep, 1.0 / (2 * ts * ts), 1.0 / (2 * tf * tf)))
        records.append(row)
        print(f"{shot} spp {spp}: " + "  ".join(f"{k} {v['relmse']:.4g}" for k, v in row.items() if isinstance(v, dict)
                                               and not k.startswith("global")) + f"  ({time.time() - t0:.0f} s)", flush=True)

    spps = sorted({r["spp"] for r in records})
    table = []
    for s in spps:
        rs = [r for r in records if r["spp"] == s]
        mean = lambda name, k: float(np.mean([r[name][k] for r in rs]))
        entry = {"spp": s, "frames": len(rs)}
        for name in ("input", "lbf", "lbf-nlm"):
            if all(name in r for r in rs):  # a method not scored on every frame has no mean (page: an error)
                entry[name] = {"relmse": mean(name, "relmse"), "ssim": mean(name, "ssim")}
        if all(f"global_s{ts}_f{tf}" in r for r in rs for ts, tf in grid):
            best = min((f"global_s{ts}_f{tf}" for ts, tf in grid), key=lambda n: mean(n, "relmse"))
            entry["global_best"] = {"setting": best, "relmse": mean(best, "relmse"), "ssim": mean(best, "ssim")}
        table.append(entry)
    result = {"data": str(data), "weights": {"lbf": args.weights_lbf or "shipped", "lbf-nlm": args.weights_nlm or "shipped"},
              "grid": {"theta_s": THETA_S, "theta_f": THETA_F}, "per_spp": table, "records": records,
              "seconds": time.time() - t0, "command": "python " + " ".join(sys.argv)}
    write_json(out / "lbf_eval.json", result)
    write_text(out / "lbf_eval.md", page(result))
    print(f"lbf_eval: {len(records)} frames in {time.time() - t0:.0f} s -> {out / 'lbf_eval.md'}")


def page(res: dict) -> str:
    """``lbf_eval.md`` from ``lbf_eval.json`` alone: the per-rate means, then how they were made.
    The global grid's best setting is shown at the rates whose records hold the grid's scores and
    must be there for each of them; above them (claim (b)) the cell is "-" (not searched)."""
    grid_spp = sorted({r["spp"] for r in res["records"] if any(k.startswith("global_") for k in r)})
    rows = []
    for e in res["per_spp"]:
        g = e["global_best"] if e["spp"] in grid_spp else None
        rows.append(f"| {e['spp']} | {e['frames']} | {num(e['input']['relmse'])} | "
                    f"{num(g['relmse']) if g else '-'} | {num(e['lbf']['relmse'])} | {num(e['lbf-nlm']['relmse'])} | "
                    f"{num(e['input']['ssim'], '.4f')} | {num(g['ssim'], '.4f') if g else '-'} | "
                    f"{num(e['lbf']['ssim'], '.4f')} | {num(e['lbf-nlm']['ssim'], '.4f')} | {g['setting'] if g else '-'} |")
    theta = lambda v: "off" if v == math.inf else f"{v:g}"  # noqa: E731
    ts, tf = res["grid"]["theta_s"], res["grid"]["theta_f"]
    lines = ["# LBF claims (a) and (b): held-out frames", "",
             "| spp | frames | input RelMSE | global best RelMSE | lbf RelMSE | lbf-nlm RelMSE | input SSIM | "
             "global best SSIM | lbf SSIM | lbf-nlm SSIM | global setting |",
             "|---|---|---|---|---|---|---|---|---|---|---|", *rows, "",
             "Mean over shots per sampling rate. RelMSE: lower is better; SSIM: higher is better.  ",
             f"Global best: the same pipeline as `lbf` with one constant spatial and one constant feature "
             f"bandwidth, the lowest mean RelMSE of the {len(ts)} x {len(tf)} grid (theta_s in "
             f"{{{', '.join(theta(v) for v in ts)}}} px, theta_f in {{{', '.join(theta(v) for v in tf)}}}) chosen per "
             f"sampling rate on these test frames (an oracle); searched at "
             f"{', '.join(str(s) for s in grid_spp) or 'no'} spp" + (" only (\"-\": not searched)." if any(
                 e["spp"] not in grid_spp for e in res["per_spp"]) else "."), "",
             f"Command: `{res['command']}`  ",
             f"Data: `{res['data']}` (instance 00 of each render; never used in training); weights: "
             f"`lbf` {res['weights']['lbf']}, `lbf-nlm` {res['weights']['lbf-nlm']}."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
