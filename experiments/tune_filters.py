"""Grid search of the global bandwidths of the `bilateral` and `nlm` methods on TRAINING frames.

The search never sees benchmark frames: it reads a data folder made for it (distinct seed), e.g.

    python -m data_gen dataset --family mixed --count 12 --res 96 --spp 4,16 --ref-spp 512 \\
        --seed 7000 --out /tmp/jd_filters_train
    python experiments/tune_filters.py --data /tmp/jd_filters_train --out docs/results

Procedure (docs/methods/bilateral.md): every noisy render of every shot is prepared once (feature
prefilter, Sec. 3.2, which does not depend on the bandwidths); the cross filter plus spike removal
is jitted once with the lambdas as traced scalars; every configuration is scored by the mean
RelMSE (docs/architecture.md convention, eps = 0.01) over all frames. Stage 1 scores the full grid below with
one feature bandwidth shared by all features; stage 2 starts from its best and does coordinate
descent (``--passes`` sweeps) over each feature's own bandwidth, then over the stage-1 axes.
Bandwidths are ``theta`` (``lambda = 1 / (2 theta^2)``; "off" = lambda 0). The window radius is fixed
(``--radius``, default the method's) because it trades error against run time, which `bench`
measures.
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

from jaxdenoise import io, metrics
from jaxdenoise.data import discover
from jaxdenoise.fsutil import write_json, write_text
from jaxdenoise.methods import bilateral as method
from common import num

GRIDS = {
    "bilateral": {
        "sigma_spatial": [2.0, 8.0, 16.0],
        "sigma_color": [3.5, 7.0, None],
        "sigma_feature": [0.0625, 0.125, 0.25, 0.5, 1.0, None],
    },
    "nlm": {
        "sigma_patch": [1.0, 2.0, 4.0],
        "sigma_feature": [0.0625, 0.125, 0.25, 0.5, 1.0, None],
    },
}


def load_frames(data: Path, config: method.Config, limit: int | None):
    frames = []
    prepare = jax.jit(lambda a: method.prepare(a, config))  # one compile for all same-shaped frames
    for shot in discover(data):
        ref = io.read_image(shot.reference)
        for r in shot.renders:
            buffers, _ = io.read_buffers(r.path)
            arrays = {k: v for k, v in buffers.to_dict().items() if k in method.needs(config)}
            prep = prepare(arrays)
            frames.append({"name": f"{shot.name}/{r.path.name}", "spp": r.spp, "prep": prep, "ref": ref})
            if limit and len(frames) >= limit:
                return frames
    return frames


FEATURE_SIGMAS = [0.0625, 0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, None]


class Scorer:
    """Mean RelMSE over the training frames of one config (jitted once; results cached)."""

    def __init__(self, frames, config: method.Config):
        self.frames = frames
        self.fn = jax.jit(lambda prep, ls, lc, lp, lf: method.filter_prepared(prep, ls, lc, lp, lf, config))
        self.rows: dict = {}

    def __call__(self, cfg: method.Config, label: dict) -> float:
        key = (cfg.sigma_spatial, cfg.sigma_color, cfg.sigma_patch, cfg.feature_sigmas)
        if key not in self.rows:
            lam = method.lambdas(cfg)
            t0 = time.perf_counter()
            errs = [float(metrics.relmse(self.fn(f["prep"], lam["lam_spatial"], lam["lam_color"], lam["lam_patch"],
                                                 lam["lam_features"]), f["ref"])) for f in self.frames]
            self.rows[key] = {**label, "relmse_mean": float(np.mean(errs)), "relmse_median": float(np.median(errs)),
                              "relmse": errs, "seconds": time.perf_counter() - t0}
            print(f"  {label}: mean RelMSE {self.rows[key]['relmse_mean']:.5g}", file=sys.stderr)
        return self.rows[key]["relmse_mean"]


def search(frames, config: method.Config, grid: dict, passes: int) -> tuple[list[dict], method.Config]:
    """Stage 1: the full grid with one gamma shared by all features. Stage 2: coordinate descent,
    ``passes`` sweeps over each feature's own gamma (FEATURE_SIGMAS), then over the stage-1 axes."""
    score = Scorer(frames, config)
    names = list(grid)
    best, best_err = config, float("inf")
    nfeat = len(config.features)
    for values in itertools.product(*(grid[n] for n in names)):
        setting = dict(zip(names, values))
        # one gamma for every feature; "off" (None) is spelled out per feature
        sig = (setting.pop("sigma_feature"),) * nfeat
        cfg = dataclasses.replace(config, **setting, feature_sigmas=sig)
        err = score(cfg, {"stage": 1, **dict(zip(names, values))})
        if err < best_err:
            best, best_err = cfg, err
    for _ in range(passes):
        for k, fname in enumerate(config.features):
            for val in FEATURE_SIGMAS:
                trial = list(best.feature_sigmas)
                trial[k] = val
                cfg = dataclasses.replace(best, feature_sigmas=tuple(trial))
                label = {"stage": 2, **{n: getattr(cfg, n) for n in names if n != "sigma_feature"},
                         "feature_sigmas": list(cfg.feature_sigmas)}
                err = score(cfg, label)
                if err < best_err:
                    best, best_err = cfg, err
        for n in names:
            if n == "sigma_feature":
                continue
            for val in grid[n]:
                cfg = dataclasses.replace(best, **{n: val})
                label = {"stage": 2, **{m: getattr(cfg, m) for m in names if m != "sigma_feature"},
                         "feature_sigmas": list(cfg.feature_sigmas)}
                err = score(cfg, label)
                if err < best_err:
                    best, best_err = cfg, err
    rows = sorted(score.rows.values(), key=lambda r: r["relmse_mean"])
    return rows, best


# the order a setting's axes are listed in (the JSON's keys are sorted)
AXES = ("sigma_spatial", "sigma_color", "sigma_patch", "sigma_feature", "feature_sigmas")
SCORES = ("stage", "relmse_mean", "relmse_median", "relmse", "seconds")


def page(res: dict) -> str:
    """``tune_<filter>.md`` from ``tune_<filter>.json`` alone (one filter per file): the ten best
    configurations, then the best, the noisy input and how the search was run."""
    (name, f), = res["filters"].items()
    order = lambda keys: sorted(keys, key=lambda k: (AXES.index(k), k) if k in AXES else (len(AXES), k))  # noqa: E731
    rows = []
    for r in f["rows"][:10]:
        setting = ", ".join(f"{k}={r[k]}" for k in order(k for k in r if k not in SCORES))
        rows.append(f"| {r['stage']} | {setting} | {num(r['relmse_mean'], '.5g')} | {num(r['relmse_median'], '.5g')} |")
    best = {k: f["best"][k] for k in order(k for k in f["best"] if k != "feature_sigmas")}
    if set(f["best"]["feature_sigmas"]) != set(f["features"]):
        raise ValueError(f"best feature_sigmas {sorted(f['best']['feature_sigmas'])} are not the features {f['features']}")
    best["feature_sigmas"] = {k: f["best"]["feature_sigmas"][k] for k in f["features"]}
    lines = [f"# Bandwidth search for `{name}` (training frames)", "",
             f"## `{name}` ({len(f['frames'])} frames, {len(f['rows'])} configurations scored)", "",
             "| stage | setting | mean RelMSE | median RelMSE |", "|---|---|---|---|", *rows, "",
             f"Best: `{best}` (mean RelMSE {num(f['best_relmse_mean'], '.5g')})", "",
             f"Noisy input (no filter): mean RelMSE {num(f['input_relmse_mean'], '.5g')}, "
             f"median {num(f['input_relmse_median'], '.5g')}.", "",
             f"Command: `python {res['command']}`", "",
             f"Data: `{res['data']}`; window radius {res['radius']}; objective: mean RelMSE over frames.", ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="folder of training shots (reference.exr + noisy EXRs)")
    ap.add_argument("--out", default="docs/results", help="folder for tune_<filter>.json / .md")
    ap.add_argument("--filters", default="bilateral,nlm")
    ap.add_argument("--radius", type=int, default=method.Config().radius)
    ap.add_argument("--limit", type=int, default=None, help="use at most this many frames")
    ap.add_argument("--passes", type=int, default=1, help="coordinate-descent sweeps of stage 2")
    a = ap.parse_args(argv)
    out = Path(a.out)
    command = " ".join([sys.argv[0], *(sys.argv[1:] if argv is None else argv)])
    for name in a.filters.split(","):
        result = {"data": str(Path(a.data).resolve()), "radius": a.radius, "command": command, "filters": {}}
        config = method.Config(filter=name, radius=a.radius)
        frames = load_frames(Path(a.data), config, a.limit)
        print(f"{name}: {len(frames)} frames, {np.prod([len(v) for v in GRIDS[name].values()])} grid points",
              file=sys.stderr)
        rows, best = search(frames, config, GRIDS[name], a.passes)
        best_d = {k: getattr(best, k) for k in GRIDS[name] if k != "sigma_feature"}
        best_d["feature_sigmas"] = dict(zip(config.features, best.feature_sigmas))
        inp = [float(metrics.relmse(np.asarray(f["prep"]["color"]), f["ref"])) for f in frames]
        result["filters"][name] = {"frames": [f["name"] for f in frames], "grid": GRIDS[name],
                                   "feature_sigma_grid": FEATURE_SIGMAS, "features": list(config.features),
                                   "rows": rows, "best": best_d, "best_relmse_mean": rows[0]["relmse_mean"],
                                   "input_relmse_mean": float(np.mean(inp)), "input_relmse_median": float(np.median(inp))}
        write_json(out / f"tune_{name}.json", result)
        write_text(out / f"tune_{name}.md", page(result))
        print(f"tune_filters: {name} best {json.dumps(result['filters'][name]['best'])} -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
