"""LBF run time on a 1200x800 frame (Kalantari 2015 Sec. 5: 8.4 s on a GTX TITAN, of which 5 s
features and 3.4 s network + filter): features (prefilter + secondary features), network, filter
(+ spike removal), each jitted separately, median of ``--runs`` calls after a warm-up; compile time
reported separately. Peer measured in the same run: the Gaussian blur of the same frame.

    python experiments/lbf_timing.py --frame runs/lbf_eval_data/scene_0000/spp0004_00.exr --out docs/results

The 1200x800 frame tiles the given 128x128 render (content does not change the cost: every
filter walks its full window). Writes ``lbf_timing.json`` and ``lbf_timing.md``.
"""
from __future__ import annotations

import argparse
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
    ap.add_argument("--out", default="docs/results")
    args = ap.parse_args()
    b0, _ = read_buffers(args.frame)
    res = {"frame": args.frame, "height": args.height, "width": args.width, "runs": args.runs,
           "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
           "load_avg_start": os.getloadavg(), "command": "python " + " ".join(sys.argv), "methods": {}}
    _, g = timed(lambda c: gaussian(c, 2.0, radius=6), tile(b0, args.height, args.width).color, runs=args.runs)
    res["gaussian_sigma2"] = g
    print(f"gaussian: {g['median_s']:.3f} s", flush=True)
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
        _, t_filt = timed(lambda l, pr: lbf.postprocess(lbf.filter_with(l, pr, cfg), cfg), lam, prep, runs=args.runs)
        total = t_feat["median_s"] + t_net["median_s"] + t_filt["median_s"]
        res["methods"][name] = {"features": t_feat, "network": t_net, "filter": t_filt, "total_median": total,
                                "ratio_to_gaussian": total / g["median_s"]}
        print(f"{name}: features {t_feat['median_s']:.2f} s, network {t_net['median_s']:.3f} s, "
              f"filter {t_filt['median_s']:.2f} s, total {total:.2f} s", flush=True)
    res["load_avg_end"] = os.getloadavg()
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
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
