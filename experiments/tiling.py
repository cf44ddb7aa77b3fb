"""Tiled inference (issue 36, part 4; `jaxdenoise.tiling`): how much context a tile needs, and what
tiling saves on a 4K frame.

1. **Margin.** A real frame (data_gen's default scene, ``--size`` square, ``--spp`` spp, every buffer
   the networks read, G-PT gradients) denoised whole and in ``--tile`` tiles with each margin of
   ``--margins``: the tiled output's difference from the whole one (max over pixels of
   ``|tiled - whole| / (|whole| + 0.01)``, and ``||tiled - whole|| / ||whole||``) and both outputs'
   RelMSE against a ``--ref-spp`` reference. The margin each network ships (``TILE_MARGIN``) is the
   smallest here whose max rel. diff is below ``MAX_REL_DIFF`` (a pixel-level match: RelMSE alone
   changes by under 1 % from 16-64 px on and would allow margins whose tile seams show in single
   pixels); the page says whether each shipped margin is that one.
2. **4K.** That frame repeated to 3840x2160, each network in a process of its own, whole and under
   ``--budget-mb`` (`jaxdenoise.denoise(..., max_memory_mb=)`): XLA's estimate of the program(s),
   the process's peak resident memory (``ru_maxrss``), wall time of the call after a warm one.

    python experiments/tiling.py [--size 512] [--spp 16] [--ref-spp 512] [--tile 128] \
        [--margins 0,16,32,64,96,128] [--budget-mb 1024]

Writes docs/results/tiling/tiling.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import all_measured, num, write_study  # noqa: E402

MAX_REL_DIFF = 5e-3  # the margin rule: max over pixels of |tiled - whole| / (|whole| + 0.01) below this

OUT = ROOT / "docs" / "results" / "tiling"
NETWORKS = ("demc", "rae", "gradnet")
UHD = (2160, 3840)


def render(size: int, spp: int, ref_spp: int) -> tuple[dict, np.ndarray]:
    from data_gen.integrator import PathSettings, derive_seed
    from data_gen.render import render_reference
    from data_gen.scenes import default_scene, load_scene
    from data_gen.shot import render_frame

    scene = load_scene(default_scene(width=size, height=size))
    b = render_frame(scene, spp=spp, methods=list(NETWORKS), seed=7)
    ref, _ = render_reference(scene, spp=ref_spp, seed=derive_seed(7, "reference"), settings=PathSettings())
    return {k: np.asarray(v) for k, v in b.to_dict().items()}, np.asarray(ref)


def margins(frame: dict, ref: np.ndarray, tile: int, pads: list[int]) -> list[dict]:
    import warnings

    from jaxdenoise.api import resolve
    from jaxdenoise.buffers import Buffers
    from jaxdenoise.inference import inference_fn, prepare
    from jaxdenoise.metrics import relmse
    from jaxdenoise.tiling import denoise_tiled

    warnings.filterwarnings("ignore", message=".*outside its trained rates.*")
    rows = []
    for name in NETWORKS:
        m, params = resolve(name)
        b = prepare(m, Buffers(**frame))
        fn = inference_fn(m)
        whole = np.asarray(fn(params, b), np.float64)
        row = {"method": name, "relmse_whole": float(relmse(whole, ref)), "margins": []}
        for pad in pads:
            t = np.asarray(denoise_tiled(fn, m, params, b, tile=tile, pad=pad), np.float64)
            row["margins"].append({
                "margin": pad, "relmse": float(relmse(t, ref)),
                "max_rel_diff": float(np.max(np.abs(t - whole) / (np.abs(whole) + 0.01))),
                "rel_l2_diff": float(np.linalg.norm(t - whole) / np.linalg.norm(whole))})
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def uhd_run(path: str, name: str, budget_mb: float | None) -> dict:
    """One network on the 4K frame in this process: the call's wall time (after a warm call), XLA's
    estimate, the process's peak RSS."""
    import warnings

    import jaxdenoise
    from jaxdenoise.api import resolve
    from jaxdenoise.buffers import Buffers
    from jaxdenoise.inference import inference_fn, prepare
    from jaxdenoise import tiling

    warnings.filterwarnings("ignore")
    data = dict(np.load(path))
    frame = {k: (v if v.ndim < 3 or k in ("world_to_camera", "world_to_ndc")
                 else np.tile(v, (-(-UHD[0] // v.shape[0]), -(-UHD[1] // v.shape[1]), 1))[:UHD[0], :UHD[1]])
             for k, v in data.items()}
    b = Buffers(**frame)
    m, params = resolve(name)
    fn = inference_fn(m)
    prepared = prepare(m, b)
    if budget_mb is None:
        tile, need = None, fn.compile(params, prepared, check=False).xla_bytes
    else:
        tile, need = tiling.plan(fn, m, params, prepared, int(budget_mb * 2**20))
    jaxdenoise.denoise(b, name, params, max_memory_mb=budget_mb)  # warm: every program compiled
    t0 = time.perf_counter()
    jaxdenoise.denoise(b, name, params, max_memory_mb=budget_mb)
    wall = time.perf_counter() - t0
    n_windows = 1 if tile is None else len(tiling.windows(UHD[0], UHD[1], tile, tiling.margin(m)))
    return {"method": name, "budget_mb": budget_mb, "tile": tile, "windows": n_windows, "xla_mb": need / 2**20,
            "wall_s": wall,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def uhd(frame: dict, budget_mb: float) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "frame.npz")
        np.savez(path, **frame)
        for name in NETWORKS:
            for budget in (None, budget_mb):
                cmd = [sys.executable, __file__, "--child", path, name] + ([] if budget is None else [str(budget)])
                res = subprocess.run(cmd, capture_output=True, text=True, check=True)
                rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
                print(rows[-1], flush=True)
    return rows


def page(res: dict) -> str:
    c = res["config"]
    lines = ["# Tiled inference: the context a tile needs, and memory on a 4K frame", "",
             f"Frame: data_gen's default scene at {c['size']}x{c['size']}, {c['spp']} spp (G-PT gradients, every "
             f"buffer the networks read), reference {c['ref_spp']} spp. Tiles of {c['tile']} px; each margin is the "
             "context a tile sees on every side (shifted inward at the border); the output keeps each tile's core.", "",
             "## Tiled against whole, by margin", "",
             "Max rel. diff = max over pixels of |tiled - whole| / (|whole| + 0.01); L2 diff = ||tiled - whole|| / ||whole||.", "",
             "| method | margin px | RelMSE whole | RelMSE tiled | change | max rel. diff | L2 diff | shipped |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in res["margins"]:
        for q in r["margins"]:
            ch = q["relmse"] / r["relmse_whole"] - 1
            lines.append(f"| {r['method']} | {q['margin']} | {num(r['relmse_whole'])} | {num(q['relmse'])} | "
                         f"{100 * ch:+.2f} % | {num(q['max_rel_diff'], '.3g')} | {num(q['rel_l2_diff'], '.3g')} | "
                         f"{'yes' if q['margin'] == res['shipped'][r['method']] else ''} |")
    lines += ["", f"The rule: the smallest margin whose max rel. diff is below {MAX_REL_DIFF:g}."]
    for r in res["margins"]:
        ok = [q["margin"] for q in r["margins"] if q["max_rel_diff"] < MAX_REL_DIFF]
        pick, shipped = (min(ok) if ok else None), res["shipped"][r["method"]]
        verdict = "the shipped margin" if pick == shipped else f"**the shipped margin is {shipped} px**"
        lines.append(f"- {r['method']}: {'none measured' if pick is None else f'{pick} px'}: {verdict}")
    lines += ["", f"## {UHD[1]}x{UHD[0]}: whole against a {c['budget_mb']:.0f} MiB budget", "",
              "One process per row; XLA = the program's estimate (arguments + outputs + temporaries; tiled: one tile's "
              "program); peak RSS = the process's (Python, JAX, the weights, the frame and its output included); "
              "wall = one `jaxdenoise.denoise` call after a warm one.", "",
              "| method | budget MiB | tile px | windows | XLA MiB | peak RSS MiB | wall s | wall / whole |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    whole_wall = {r["method"]: r["wall_s"] for r in res["uhd"] if r["budget_mb"] is None}
    for r in res["uhd"]:
        budget = "-" if r["budget_mb"] is None else f"{r['budget_mb']:.0f}"
        lines.append(f"| {r['method']} | {budget} | "
                     f"{r['tile'] or 'whole'} | {r['windows']} | {num(r['xla_mb'], '.0f')} | "
                     f"{num(r['peak_rss_mb'], '.0f')} | {num(r['wall_s'], '.2f')} | "
                     f"{r['wall_s'] / whole_wall[r['method']]:.2f}x |")
    lines += ["", "## Run", "", f"Reproduce: `{res['command']}` ({res['seconds']:.0f} s).", "",
              f"{res['cpu_count']} CPU cores, {res['machine']}, load average at the end "
              f"{' / '.join(f'{v:.2f}' for v in res['load_average'])} (1/5/15 min).", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        print(json.dumps(uhd_run(argv[1], argv[2], float(argv[3]) if len(argv) > 3 else None)))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--ref-spp", type=int, default=512)
    ap.add_argument("--tile", type=int, default=128)
    ap.add_argument("--margins", default="0,16,32,64,96,128")
    ap.add_argument("--budget-mb", type=float, default=1024.0)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    from data_gen.mitsuba_setup import setup_mitsuba
    from jaxdenoise.methods import get

    setup_mitsuba("llvm_ad_rgb")
    t0 = time.perf_counter()
    frame, ref = render(args.size, args.spp, args.ref_spp)
    res = {"command": "python experiments/tiling.py " + " ".join(
               f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out"),
           "config": {k: v for k, v in vars(args).items() if k != "out"},
           "margins": margins(frame, ref, args.tile, [int(p) for p in args.margins.split(",")]),
           "shipped": {n: get(n).module.TILE_MARGIN for n in NETWORKS}}
    res["uhd"] = uhd(frame, args.budget_mb)
    res.update(seconds=time.perf_counter() - t0, cpu_count=os.cpu_count(), machine=platform.machine(),
               load_average=list(os.getloadavg()))
    all_measured(res, "tiling.json")
    print(f"tiling: wrote {write_study(Path(args.out), 'tiling.json', 'tiling.md', res, page)}")


if __name__ == "__main__":
    main()
