"""Choose a network's refinement pass (`jaxdenoise.filters.refine`: the ``refine_*`` settings of
`jaxdenoise.methods.demc.Config` and `jaxdenoise.methods.rae.Config`; docs/methods/demc.md
"Refinement") for a weights folder, on validation data only, no training (issues 33 and 34).

    python experiments/refine_choice.py --method demc --init jaxdenoise/weights/demc \
        --data data/library_val,data/library_val2,data/procedural_val --out docs/results/refine/demc
    python experiments/refine_choice.py --method rae --init jaxdenoise/weights/rae \
        --data data/library_val,data/library_val2,data/procedural_val --sequences runs/rae_val4 \
        --albedos 0.03 --normals 0.1 --out docs/results/refine/rae

Off and every combination of ``--sigmas`` x ``--ranges`` x ``--albedos`` x ``--normals`` (by default
`SIGMAS` x `RANGES` x `ALBEDOS` x `NORMALS`; the weights' other inference settings as in ``--init``'s
config), each scored on the single frames of ``--data`` at every rate they hold as
`level_correction.score_settings` scores (`demc_levels.measure`: RelMSE, SSIM, the colour level on
surface pixels, surface halo pixels, the exposure test) and, with ``--sequences``, on those validation
fly-throughs (state carried: per-frame RelMSE and the temporal error, per rate). The rule, fixed before
any evaluation frame was scored:

1. a setting is eligible when, at every folder and rate, its mean SSIM is at least off's and its level
   (every channel) is no further from 1 than off's plus ``--level-slack``, and, with ``--sequences``,
   its fly-through RelMSE and temporal error at every rate are at most off's;
2. the best is the eligible setting with the lowest geometric mean of the single frames' RelMSE over
   (folder, rate); the chosen one is the smallest window (``sigma``: the pass's cost grows with its
   square) among the eligible settings within ``--cost-slack`` of that geometric mean, the lowest
   geometric mean among those;
3. off when no eligible setting's geometric mean is below off's.

Writes ``refine.json`` and ``refine.md`` into ``--out``.
"""
from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import all_measured, num, write_study  # noqa: E402

SIGMAS = (2.0, 3.0, 5.0)
RANGES = (0.2, 0.4, 0.8)
ALBEDOS = (0.03, 0.1)
NORMALS = (0.1, 0.3)


def label_of(over: dict) -> str:
    if not over["refine_sigma"]:
        return "off"
    return (f"s{over['refine_sigma']:g} r{over['refine_range']:g} a{over['refine_albedo']:g} "
            f"n{over['refine_normal']:g}")


def grid(sigmas=SIGMAS, ranges=RANGES, albedos=ALBEDOS, normals=NORMALS) -> dict[str, dict]:
    settings = [{"refine_sigma": 0.0}] + [
        {"refine_sigma": s, "refine_range": r, "refine_albedo": a, "refine_normal": n}
        for s, r, a, n in itertools.product(sigmas, ranges, albedos, normals)]
    return {label_of(o): o for o in settings}


def score_sequences(method: str, init: str, settings: dict[str, dict], folder: str) -> dict:
    """Per setting and rate: the fly-throughs' mean per-frame RelMSE and mean temporal error (state
    carried through `jaxdenoise.sequence.run_all`, as training's validation runs them)."""
    from jaxdenoise import metrics
    from jaxdenoise.api import resolve
    from jaxdenoise.sequence import run_all
    from jaxdenoise.train import load_validation

    base, params = resolve(method, init)
    seqs = [f for f in load_validation(base, folder) if "frames" in f]
    if not seqs:
        raise SystemExit(f"refine_choice: no validation fly-through in {folder}")
    out = {}
    for label, over in settings.items():
        m = base.with_config(**over)
        rows = []
        for f in seqs:
            outs, refs = run_all(m, params, f["frames"]), np.stack(f["references"])
            rows.append((int(f["spp"]), float(np.mean([metrics.relmse(o, r) for o, r in zip(outs, refs)])),
                         float(metrics.temporal_error(outs, refs))))
        out[label] = {str(s): {"relmse": float(np.mean([r[1] for r in rows if r[0] == s])),
                               "temporal": float(np.mean([r[2] for r in rows if r[0] == s])),
                               "sequences": sum(r[0] == s for r in rows)}
                      for s in sorted({r[0] for r in rows})}
        print(label, out[label], flush=True)
    return out


def choose_setting(res: dict, level_slack: float, cost_slack: float, cost_key: str = "refine_sigma") -> str:
    """The rule of the module docstring on ``res``'s scores; marks each setting's ``eligible``. ``cost_key``
    names the config field whose smallest value is preferred within ``cost_slack`` (0: no preference, the
    lowest geometric mean; experiments/output_clamp_choice.py)."""
    off = res["settings"]["off"]
    seq_off = res.get("sequences", {}).get("off")
    for label, v in res["settings"].items():
        ok = all(v["ssim"][k] >= off["ssim"][k] for k in off["ssim"])
        ok &= all(abs(a - 1) <= abs(b - 1) + level_slack
                  for k in off["level"] for a, b in zip(v["level"][k], off["level"][k]))
        if seq_off is not None:
            seq = res["sequences"][label]
            ok &= all(seq[s][m] <= seq_off[s][m] for s in seq_off for m in ("relmse", "temporal"))
        v["eligible"] = bool(ok) and label != "off"
    eligible = [k for k, v in res["settings"].items() if v["eligible"]]
    if not eligible:
        return "off"
    best = min(res["settings"][k]["geomean"] for k in eligible)
    if best >= off["geomean"]:
        return "off"
    near = [k for k in eligible if res["settings"][k]["geomean"] <= best * (1 + cost_slack)]
    cheapest = min(res["settings"][k]["config"][cost_key] for k in near)
    return min((k for k in near if res["settings"][k]["config"][cost_key] == cheapest),
               key=lambda k: res["settings"][k]["geomean"])


def page(res: dict) -> str:
    keys = sorted(res["settings"]["off"]["relmse"],
                  key=lambda c: (res["data"].index(c.rsplit(" ", 1)[0]), int(c.rsplit(" ", 1)[1])))
    off = res["settings"]["off"]["geomean"]
    seq = res.get("sequences")
    lines = [f"# `{res['method']}`'s refinement pass: the choice on validation data", "",
             f"Weights `{res['init']}`, validation folders {', '.join(f'`{f}`' for f in res['data'])}"
             + (f" and the fly-throughs of `{res['sequences_data']}`" if seq else "")
             + " (experiments/refine_choice.py; `jaxdenoise.filters.refine`, docs/methods/demc.md \"Refinement\"). "
             "Setting `sS rR aA nN`: `refine_sigma` S px, `refine_range` R, `refine_albedo` A, `refine_normal` N. "
             "RelMSE and SSIM: means over the frames of each folder and rate; geomean: the geometric mean of the "
             "RelMSE over (folder, rate); level: per channel, the median over frames of the median 15x15 box "
             "ratio to the reference on surface pixels (experiments/demc_levels.py); halo: surface pixels above 4x "
             "the reference's 9x9 maximum, summed over every frame.", "",
             "| setting | " + " | ".join(f"RelMSE / SSIM {k}" for k in keys) + " | level furthest from 1 | halo | "
             + ("fly-throughs RelMSE / temporal per rate | " if seq else "") + "eligible | geomean | x off |",
             "|---|" + "---:|" * len(keys) + "---:|---:|" + ("---|" if seq else "") + "---|---:|---:|"]
    for label, v in sorted(res["settings"].items(), key=lambda kv: kv[1]["geomean"]):
        worst = max((x for lv in v["level"].values() for x in lv), key=lambda x: abs(x - 1))
        row = (f"| {label} | " + " | ".join(f"{num(v['relmse'][k], '.4f')} / {num(v['ssim'][k], '.3f')}" for k in keys)
               + f" | {num(worst, '.3f')} | {sum(v['halo'].values())} | ")
        if seq:
            row += "; ".join(f"{s}: {num(r['relmse'], '.4f')} / {num(r['temporal'], '.4f')}"
                             for s, r in sorted(seq[label].items(), key=lambda kv: int(kv[0]))) + " | "
        row += f"{'yes' if v['eligible'] else 'no'} | {num(v['geomean'], '.5f')} | {num(v['geomean'] / off, '.3f')} |"
        lines.append(row)
    worst_exp = max(e for v in res["settings"].values() for e in v["exposure"].values())
    lines += ["", f"Exposure test (f(k x) against k f(x), k = 1/16 .. 16, one 4-spp frame per folder): the largest "
              f"difference over every setting, relative to the output's peak: {num(worst_exp, '.2e')}.", "",
              f"Chosen: `{res['chosen']}` (rule: experiments/refine_choice.py; level slack "
              f"{num(res['level_slack'], 'g')}, cost slack {num(res['cost_slack'], 'g')}).", "",
              "Command: `" + res["command"] + "`", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", required=True, choices=("demc", "rae"))
    ap.add_argument("--init", required=True, help="the weights folder (its config's other settings are kept)")
    ap.add_argument("--data", required=True, help="validation folders of single frames (comma-separated)")
    ap.add_argument("--sequences", default=None, help="a folder of validation fly-throughs (rae)")
    ap.add_argument("--level-slack", type=float, default=0.005,
                    help="how much further from 1 than off's a chosen setting's level may be")
    ap.add_argument("--cost-slack", type=float, default=0.01,
                    help="a smaller window is preferred within this fraction of the best geometric mean")
    for name, default in (("sigmas", SIGMAS), ("ranges", RANGES), ("albedos", ALBEDOS), ("normals", NORMALS)):
        ap.add_argument(f"--{name}", default=",".join(f"{v:g}" for v in default),
                        help=f"the grid's refine_{name[:-1]} values (comma-separated)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from level_correction import score_settings

    folders = args.data.split(",")
    settings = grid(*([float(v) for v in getattr(args, k).split(",")] for k in ("sigmas", "ranges", "albedos",
                                                                              "normals")))
    res = {"method": args.method, "init": args.init, "data": folders, "level_slack": args.level_slack,
           "cost_slack": args.cost_slack, "settings": score_settings(args.init, settings, folders, args.method)}
    if args.sequences:
        res["sequences_data"] = args.sequences
        res["sequences"] = score_sequences(args.method, args.init, settings, args.sequences)
    res["chosen"] = choose_setting(res, args.level_slack, args.cost_slack)
    res["command"] = "python experiments/refine_choice.py " + " ".join(sys.argv[1:] if argv is None else argv)
    all_measured(res, "refine.json")
    print(write_study(Path(args.out), "refine.json", "refine.md", res, page))
    print("chosen:", res["chosen"])


if __name__ == "__main__":
    main()
