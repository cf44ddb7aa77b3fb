"""RAE's temporal stability and quality over fly-throughs it never saw, against the same network run
frame by frame from a zero state, OIDN per frame, LBF (its 7-frame window) and the Gaussian, at
every sampling rate of the data (the network is trained at 1 spp: 2-16 spp test generalisation).

    python experiments/rae_temporal.py --data data/rae_test --out docs/results/rae_temporal.json

Each sequence (``scene/frame_XXXX/``) at each rate is run through the sequence driver (`jaxdenoise.
load(...).sequence`: state carried, windows read) except ``rae (per frame)``, which calls the same
weights' `apply` on every frame (the first step from a zero state). Scores: mean RelMSE and SSIM
over frames and the temporal error (`jaxdenoise.metrics.temporal_error`), averaged over sequences;
each row also keeps the RelMSE of every frame and the temporal error of every consecutive pair
(`jaxdenoise.metrics.temporal_error_per_frame`), so a recurrent method's warm-up (its first frame
from a zero state) can be told from its steady state, and every frame's colour level per channel
(`demc_levels.frame_levels`: the median box-mean ratio to the reference over the lit surface pixels
of the frame's rebuilt scene, issue 34's measure; ``--masks none``: every lit pixel).

A method ``label=FOLDER`` runs `rae` with the weights (and config) in ``FOLDER`` (an earlier version, for
a before/after row); ``name+taa`` runs ``name`` and then temporal anti-aliasing over its frames with
the shipped `rae`'s TAA settings (`jaxdenoise.filters.taa_step`; Chaitanya et al. Sec. 5.4 apply TAA to
every method they compare), so a per-frame method can be compared with TAA too:

    python experiments/rae_temporal.py --data data/rae_library_eval \
        --methods input,oidn,oidn+taa,rae-paper,rae,rae-0.9.16=runs/rae_0916,rae-0.9.15=runs/rae_0915,rae-per-frame \
        --out docs/results/rae_rates/temporal.json
"""
from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from jaxdenoise import load, metrics  # noqa: E402
from jaxdenoise.buffers import BuffersError  # noqa: E402
from jaxdenoise.data import discover, renders_by_spp, sequences  # noqa: E402
from jaxdenoise.filters import taa_init, taa_step  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.io import read_buffers, read_image  # noqa: E402
from jaxdenoise.methods import get  # noqa: E402
from demc_levels import frame_levels, scene_masks, scene_of  # noqa: E402


@functools.lru_cache(maxsize=None)
def _taa_fn(alpha: float, window: int, tolerance: float):
    """`taa_step` jitted once per setting (every sequence and rate reuses it)."""
    return jax.jit(functools.partial(taa_step, alpha=alpha, window=window, tolerance=tolerance))


def with_taa(outs: np.ndarray, frames: list, config) -> np.ndarray:
    """``outs`` (T, H, W, 3) after `jaxdenoise.filters.taa_step` with ``config``'s ``taa_*`` settings,
    frame by frame, reprojected through ``frames``' positions, normals and cameras."""
    if not config.taa_alpha:
        raise SystemExit("+taa: the shipped rae config has no TAA (taa_alpha 0)")
    step = _taa_fn(config.taa_alpha, config.taa_window, config.taa_tolerance)
    state, res = taa_init(outs.shape[1:]), []
    for o, f in zip(outs, frames):
        if f.position is None or f.normal is None or f.world_to_ndc is None:
            raise BuffersError("+taa: a frame lacks position, normal or world_to_ndc (TAA reprojects through them)")
        state, y = step(state, o, f.position, f.normal, f.world_to_ndc)
        res.append(np.asarray(y))
    return np.stack(res)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="data/rae_test")
    ap.add_argument("--methods", default="input,gaussian,lbf,oidn,rae,rae-per-frame")
    ap.add_argument("--weights", default=None, help="rae weights folder (default: shipped)")
    ap.add_argument("--out", default="docs/results/rae_temporal.json")
    ap.add_argument("--masks", default="scene", choices=("scene", "none"),
                    help="the level over surface pixels (scene: each frame's scene rebuilt with its own camera, "
                    "`demc_levels.scene_masks`) or over every lit pixel (none)")
    args = ap.parse_args()
    seqs, _ = sequences(discover(args.data))
    if not seqs:
        raise SystemExit(f"{args.data}: no frame_XXXX/ sequence")
    names = args.methods.split(",")
    fns, taa = {}, get("rae").config
    for n in names:
        label, _, folder = n.partition("=")
        base = "rae" if label == "rae-per-frame" or folder else label.removesuffix("+taa")
        if get(base).requirements() is not None:
            print(f"skipping {n}: {get(base).requirements()}")
            continue
        if label.endswith("+taa") and getattr(get(base).config, "taa_alpha", 0):
            raise SystemExit(f"{n}: '{base}' runs TAA itself; '+taa' would run it twice")
        fns[label] = load(base, folder or (args.weights if base == "rae" else None))
    res: dict = {"data": args.data, "sequences": [str(s.folder) for s in seqs], "rows": [], "masks": args.masks}
    for seq in seqs:
        by_spp = [renders_by_spp(s) for s in seq.shots]
        refs = np.stack([np.asarray(read_image(s.reference), np.float32)[..., :3] for s in seq.shots])
        surfaces = [None] * len(refs)
        if args.masks == "scene":  # one mask per frame (its own camera), the same at every rate
            first = [b[min(b)][0].path for b in by_spp]
            surfaces = [scene_masks(*scene_of(p.parent, p.name))["surface"] for p in first]
        for spp in sorted(set.intersection(*(set(b) for b in by_spp))):
            frames = [read_buffers(b[spp][0].path)[0] for b in by_spp]
            for n, fn in fns.items():
                try:
                    if n == "rae-per-frame":
                        outs = np.stack([np.asarray(fn(f)) for f in frames])
                    else:
                        outs = np.stack([np.asarray(o) for o in fn.sequence(frames)])
                    if n.endswith("+taa"):
                        outs = with_taa(outs, frames, taa)
                except BuffersError as e:  # e.g. lbf at 1 spp: no variance can be estimated from one sample
                    res.setdefault("not_run", []).append({"sequence": seq.folder.name, "spp": spp, "method": n,
                                                          "reason": str(e)})
                    print(f"not run: {n} at {spp} spp: {e}", flush=True)
                    continue
                per_frame = [float(metrics.relmse(o, r)) for o, r in zip(outs, refs)]
                per_pair = np.asarray(metrics.temporal_error_per_frame(outs, refs), np.float64)
                row = {"sequence": seq.folder.name, "spp": spp, "method": n,
                       "relmse": float(np.mean(per_frame)),
                       "ssim": float(np.mean([metrics.ssim(o, r) for o, r in zip(outs, refs)])),
                       "temporal": float(np.mean(per_pair)),
                       "relmse_per_frame": per_frame, "temporal_per_pair": per_pair.tolist(),
                       "level_per_frame": [frame_levels(o, r, m) for o, r, m in zip(outs, refs, surfaces)]}
                res["rows"].append(row)
                print(row, flush=True)
    write_json(Path(args.out), res)
    spps = sorted({r["spp"] for r in res["rows"]})
    print("\n| method | spp | RelMSE | SSIM | temporal error |\n|---|---:|---:|---:|---:|")
    for n in fns:
        for s in spps:
            rs = [r for r in res["rows"] if r["method"] == n and r["spp"] == s]
            if not rs:
                continue
            print(f"| {n} | {s} | {np.mean([r['relmse'] for r in rs]):.4g} | {np.mean([r['ssim'] for r in rs]):.4f} | "
                  f"{np.mean([r['temporal'] for r in rs]):.4g} |")


if __name__ == "__main__":
    main()
