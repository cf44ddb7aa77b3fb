"""LBF run time on a 1200x800 frame (Kalantari 2015 Sec. 5: 8.4 s on a GTX TITAN, of which 5 s
features and 3.4 s network + filter): features (prefilter + secondary features), network, filter
(+ spike removal), each jitted separately, median of ``--runs`` calls after a warm-up; compile time
reported separately. Peers measured in the same run: the Gaussian blur of the same frame, and
``lbf``'s filter on each cross-bilateral engine of ``--engines`` (the tiled default against the
per-offset engine it replaced, with the largest difference between their outputs).

    python experiments/lbf_timing.py --frame runs/lbf_eval_data/scene_0000/spp0004_00.exr --out docs/results

The 1200x800 frame tiles the given 128x128 render (content does not change the cost: every
filter walks its full window). Writes ``lbf_timing.json`` and ``lbf_timing.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise import api  # noqa: E402
from jaxdenoise.filters import gaussian  # noqa: E402
from jaxdenoise.fsutil import write_json, write_text  # noqa: E402
from jaxdenoise.io import read_buffers  # noqa: E402
from jaxdenoise.methods import get, lbf  # noqa: E402
from common import num, timed  # noqa: E402


def tile(b, h: int, w: int):
    def t(a):
        if a is None or np.ndim(a) < 3:
            return a
        a = np.asarray(a)
        reps = (-(-h // a.shape[0]), -(-w // a.shape[1]), 1)
        return np.tile(a, reps)[:h, :w]
    return b.__class__(**{k: t(v) for k, v in b.to_dict().items()})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frame", required=True)
    ap.add_argument("--methods", default="lbf,lbf-nlm")
    ap.add_argument("--height", type=int, default=800)
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--engines", default="tiles,offsets",
                    help="cross-bilateral window engines to time (the first is the default one)")
    ap.add_argument("--out", default="docs/results")
    ap.add_argument("--before", action="append", default=[], metavar="JSON=COMMIT",
                    help="an lbf_timing.json written by this script at an earlier commit (run from a worktree of "
                         "it under runs/, on the same frame, right before or after this run), merged as that "
                         "commit's 'before' row; repeatable")
    args = ap.parse_args()
    home = lambda t: t.replace(str(Path.home()), "~")  # no machine paths in committed results
    before = []
    for spec in args.before:
        path, sep, commit = spec.rpartition("=")
        if not sep or not commit or not Path(path).is_file():
            raise SystemExit(f"--before {spec!r}: expected JSON=COMMIT with JSON an existing lbf_timing.json")
        if Path(path).is_absolute() or not Path(path).resolve().is_relative_to(Path.cwd()):
            raise SystemExit(f"--before {spec!r}: give JSON relative to the repository (e.g. runs/...): the command "
                             "is written into the committed page")
        old = json.loads(Path(path).read_text())
        rows = {m: r for m, r in old.get("methods", {}).items() if m in ("lbf", "lbf-nlm")}
        if not rows:
            raise SystemExit(f"--before {spec!r}: {path} has no 'lbf' or 'lbf-nlm' row (run it with --methods lbf)")
        before.append({"commit": commit, "command": home(old["command"]), "methods": rows,
                       "load_avg_start": old["load_avg_start"], "load_avg_end": old["load_avg_end"]})
    b0, _ = read_buffers(args.frame)
    res = {"frame": home(args.frame), "height": args.height, "width": args.width, "runs": args.runs,
           "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
           "load_avg_start": os.getloadavg(), "methods": {},
           "command": home("python " + " ".join(sys.argv))}
    _, g = timed(lambda c: gaussian(c, 2.0, radius=6), tile(b0, args.height, args.width).color, runs=args.runs)
    res["gaussian_sigma2"] = g
    print(f"gaussian: {g['median_s']:.3f} s", flush=True)
    outs = {}
    for name in args.methods.split(","):
        try:
            m, params = api.resolve(name)
        except Exception as e:  # no weights yet: the cost does not depend on the weight values
            print(f"{name}: {e}; timing with init() weights", flush=True)
            m = get(name)
            params = m.init(jax.random.PRNGKey(0))
        cfg = m.config
        b = tile(b0.only(lbf.needs(cfg)), args.height, args.width)
        prep, t_feat = timed(lambda bb: lbf.prepare(bb, cfg), b, runs=args.runs)
        lam, t_net = timed(lambda p, x: lbf.filter_params(p, x, cfg), params, prep["x"], runs=args.runs)
        # lbf-nlm has one engine; the cross-bilateral is timed with each engine asked for.
        engines = ["tiles"] if cfg.filter == "nlm" else args.engines.split(",")
        for engine in engines:
            out, t_filt = timed(lambda l, pr: lbf.postprocess(lbf.filter_with(l, pr, cfg, engine=engine), cfg), lam,
                                prep, runs=args.runs)
            key = name if engine == "tiles" or cfg.filter == "nlm" else f"{name} ({engine} engine)"
            total = t_feat["median_s"] + t_net["median_s"] + t_filt["median_s"]
            res["methods"][key] = {"features": t_feat, "network": t_net, "filter": t_filt, "total_median": total,
                                   "ratio_to_gaussian": total / g["median_s"], "engine": engine}
            outs[key] = np.asarray(out)
            print(f"{key}: features {t_feat['median_s']:.2f} s, network {t_net['median_s']:.3f} s, "
                  f"filter {t_filt['median_s']:.2f} s, total {total:.2f} s", flush=True)
        if len(engines) > 1:  # the engines' outputs on the same lambdas (features and network shared)
            a, b = outs[name], outs[f"{name} ({engines[1]} engine)"]
            res["methods"][name]["max_rel_diff_to_" + engines[1]] = float(np.max(np.abs(a - b) / (np.abs(b) + 1e-3)))
    res["load_avg_end"] = os.getloadavg()
    if before:
        res["before"] = before
    out = Path(args.out)
    write_json(out / "lbf_timing.json", res)
    write_text(out / "lbf_timing.md", page(res))


def page(res: dict) -> str:
    """``lbf_timing.md`` from ``lbf_timing.json`` alone (stages as `common.timed` writes them)."""
    g = res["gaussian_sigma2"]
    rows = []
    for name, r in res["methods"].items():
        comp = r["features"]["compile_s"] + r["network"]["compile_s"] + r["filter"]["compile_s"]
        rows.append(f"| {name} | {num(r['features']['median_s'], '.2f')} | {num(r['network']['median_s'], '.3f')} | "
                    f"{num(r['filter']['median_s'], '.2f')} | {num(r['total_median'], '.2f')} | "
                    f"{num(r['ratio_to_gaussian'], '.0f')} | {num(comp, '.1f')} |")
    rows.append(f"| gaussian (sigma 2, 13x13) | - | - | {num(g['median_s'], '.3f')} | {num(g['median_s'], '.3f')} | 1 | "
                f"{num(g['compile_s'], '.1f')} |")
    lines = [f"# LBF run time on a {res['width']}x{res['height']} frame", "",
             "| method | features (s) | network (s) | filter + spikes (s) | total (s) | x Gaussian blur | compile (s) |",
             "|---|---|---|---|---|---|---|", *rows, "",
             f"Median of {res['runs']} runs after a warm-up; compile time separate. Device: {res['device']}, "
             f"{res['cpu_count']} CPU cores (shared; load average {num(res['load_avg_start'][0], '.1f')} at start, "
             f"{num(res['load_avg_end'][0], '.1f')} at end).  ",
             f"Command: `{res['command']}`", "",
             "Paper (GTX TITAN GPU): 8.4 s total, 5 s features, 3.4 s network + filter (goal 8.4 s, stretch 3.4 s)."]
    for b in res.get("before", []):  # earlier commits' runs on the same frame and machine (--before)
        said = []
        for name, lb in b["methods"].items():
            now = res["methods"].get(name)
            said.append(f"`{name}` features {num(lb['features']['median_s'], '.2f')} s, filter + spikes "
                        f"{num(lb['filter']['median_s'], '.2f')} s, total {num(lb['total_median'], '.2f')} s"
                        + ("" if now is None else
                           f" (now {num(lb['total_median'] / now['total_median'], '.2f')}x faster in total, the filter "
                           f"{num(lb['filter']['median_s'] / now['filter']['median_s'], '.2f')}x, the features "
                           f"{num(lb['features']['median_s'] / now['features']['median_s'], '.2f')}x)"))
        lines += ["", f"Before (commit {b['commit']}, run from a worktree of it on the same frame and machine, "
                  f"load average {num(b['load_avg_start'][0], '.1f')} at its start; `{b['command']}`): "
                  + "; ".join(said) + "."]
    for name, r in res["methods"].items():
        for key, val in r.items():
            if key.startswith("max_rel_diff_to_"):
                other = key[len("max_rel_diff_to_"):]
                peer = res["methods"][f"{name} ({other} engine)"]
                lines += ["", f"{name}'s cross-bilateral on the {r['engine']} engine against the {other} engine in the "
                          f"same run: filter + spikes {num(peer['filter']['median_s'] / r['filter']['median_s'], '.1f')}x "
                          f"faster; outputs on the same lambdas within a relative difference of {num(val, '.1e')} "
                          "(|a - b| / (|b| + 1e-3), max over pixels)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
