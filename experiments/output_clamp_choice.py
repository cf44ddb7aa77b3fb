"""Choose `rae`'s output clamp (``output_clamp`` / ``output_clamp_radius`` of
`jaxdenoise.methods.rae.Config`; docs/methods/rae.md "Output clamp") for a weights folder, on validation
data only, no training (issue 34: "no surface pixel above 4x the reference's 9x9 local maximum").

    python experiments/output_clamp_choice.py --init jaxdenoise/weights/rae \
        --data data/library_val,data/library_val2,data/procedural_val --sequences runs/rae_val4 \
        --out docs/results/rae_rates/output_clamp

Off and every combination of ``--factors`` x ``--radii`` (the weights' other inference settings as in
``--init``'s config), each scored on the single frames of ``--data`` at every rate they hold as
`level_correction.score_settings` scores them (RelMSE, SSIM, the colour level on surface pixels, surface
halo pixels, the exposure test) and on the validation fly-throughs of ``--sequences`` (state carried:
per-frame RelMSE and the temporal error, per rate; `refine_choice.score_sequences`). The rule, fixed
before any evaluation frame was scored with the clamp, is the refinement choice's
(`refine_choice.choose_setting`, experiments/refine_choice.py) without its window preference:

1. a setting is eligible when, at every folder and rate, its mean SSIM is at least off's and its level
   (every channel) is no further from 1 than off's plus ``--level-slack``, and its fly-through RelMSE and
   temporal error at every rate are at most off's;
2. the chosen one is the eligible setting with the lowest geometric mean of the single frames' RelMSE
   over (folder, rate); off when none is below off's.

The halo pixels are reported beside it, not part of the rule. Writes ``output_clamp.json`` and
``output_clamp.md`` into ``--out``.
"""
from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import all_measured, num, write_study  # noqa: E402

FACTORS = (1.0, 1.5, 2.0, 3.0, 4.0)
RADII = (2, 3, 4)


def clamp_label(over: dict) -> str:
    return f"k{over['output_clamp']:g} r{over['output_clamp_radius']}" if over["output_clamp"] else "off"


def clamp_grid(factors=FACTORS, radii=RADII) -> dict[str, dict]:
    settings = [{"output_clamp": 0.0}] + [{"output_clamp": k, "output_clamp_radius": r}
                                          for k, r in itertools.product(factors, radii)]
    return {clamp_label(o): o for o in settings}


def page(res: dict) -> str:
    keys = sorted(res["settings"]["off"]["relmse"],
                  key=lambda c: (res["data"].index(c.rsplit(" ", 1)[0]), int(c.rsplit(" ", 1)[1])))
    off = res["settings"]["off"]["geomean"]
    seq = res["sequences"]
    lines = ["# `rae`'s output clamp: the choice on validation data", "",
             f"Weights `{res['init']}`, validation folders {', '.join(f'`{f}`' for f in res['data'])} and the "
             f"fly-throughs of `{res['sequences_data']}` (experiments/output_clamp_choice.py; docs/methods/rae.md "
             "\"Output clamp\"). Setting `kK rR`: each output frame's luminance limited to K times the largest at "
             "Chebyshev distance R. RelMSE and SSIM: means over the frames of each folder and rate; geomean: the "
             "geometric mean of the RelMSE over (folder, rate); level: per channel, the median over frames of the "
             "median 15x15 box ratio to the reference on surface pixels (experiments/demc_levels.py); halo: surface "
             "pixels above 4x the reference's 9x9 maximum, summed over every frame (issue 34's check; reported, "
             "not part of the rule).", "",
             "| setting | " + " | ".join(f"RelMSE / SSIM {k}" for k in keys) + " | level furthest from 1 | halo | "
             "fly-throughs RelMSE / temporal per rate | eligible | geomean | x off |",
             "|---|" + "---:|" * len(keys) + "---:|---:|---|---|---:|---:|"]
    for label, v in sorted(res["settings"].items(), key=lambda kv: kv[1]["geomean"]):
        worst = max((x for lv in v["level"].values() for x in lv), key=lambda x: abs(x - 1))
        lines.append(
            f"| {label} | " + " | ".join(f"{num(v['relmse'][k], '.4f')} / {num(v['ssim'][k], '.3f')}" for k in keys)
            + f" | {num(worst, '.3f')} | {sum(v['halo'].values())} | "
            + "; ".join(f"{s}: {num(r['relmse'], '.4f')} / {num(r['temporal'], '.4f')}"
                        for s, r in sorted(seq[label].items(), key=lambda kv: int(kv[0])))
            + f" | {'yes' if v['eligible'] else 'no'} | {num(v['geomean'], '.5f')} | "
            + f"{num(v['geomean'] / off, '.3f')} |")
    worst_exp = max(e for v in res["settings"].values() for e in v["exposure"].values())
    lines += ["", f"Exposure test (f(k x) against k f(x), k = 1/16 .. 16, one 4-spp frame per folder): the largest "
              f"difference over every setting, relative to the output's peak: {num(worst_exp, '.2e')}.", "",
              f"Chosen: `{res['chosen']}` (rule: experiments/output_clamp_choice.py; level slack "
              f"{num(res['level_slack'], 'g')}).", "", "Command: `" + res["command"] + "`", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--init", required=True, help="the weights folder (its config's other settings are kept)")
    ap.add_argument("--data", required=True, help="validation folders of single frames (comma-separated)")
    ap.add_argument("--sequences", required=True, help="a folder of validation fly-throughs")
    ap.add_argument("--level-slack", type=float, default=0.005,
                    help="how much further from 1 than off's a chosen setting's level may be")
    ap.add_argument("--factors", default=",".join(f"{v:g}" for v in FACTORS), help="output_clamp values")
    ap.add_argument("--radii", default=",".join(str(v) for v in RADII), help="output_clamp_radius values")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from level_correction import score_settings
    from refine_choice import choose_setting, score_sequences

    folders = args.data.split(",")
    settings = clamp_grid([float(v) for v in args.factors.split(",")], [int(v) for v in args.radii.split(",")])
    res = {"method": "rae", "init": args.init, "data": folders, "level_slack": args.level_slack,
           "settings": score_settings(args.init, settings, folders, "rae"), "sequences_data": args.sequences,
           "sequences": score_sequences("rae", args.init, settings, args.sequences)}
    res["chosen"] = choose_setting(res, args.level_slack, cost_slack=0.0, cost_key="output_clamp_radius")
    res["command"] = "python experiments/output_clamp_choice.py " + " ".join(sys.argv[1:] if argv is None else argv)
    all_measured(res, "output_clamp.json")
    print(write_study(Path(args.out), "output_clamp.json", "output_clamp.md", res, page))
    print("chosen:", res["chosen"])


if __name__ == "__main__":
    main()
