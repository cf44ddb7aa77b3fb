"""Does a low-frequency level correction fix a network's colour level, and what does it cost in RelMSE?
(issues 33 and 34: the 3 % level check next to the RelMSE checks.)

A denoiser whose output is darker than the reference over large areas can be corrected after the
fact: multiply it by the ratio of a wide Gaussian low-pass of a level estimate to the same low-pass
of the output, ``y * (G(t) + e) / (G(y) + e)`` per channel (``G``: `jaxdenoise.filters.gaussian`,
sigma ``--sigma``; ``e`` 1 % of the frame's exposure level). Three targets ``t`` per frame:

- ``input``: the noisy input with its isolated spikes cut (`jaxdenoise.filters.clamp_outliers`,
  factor 8 at the exposure level, `rae`'s setting): an unbiased-but-noisy estimate;
- ``input K2``: the same with factor 2 (fewer spikes, a little darker);
- ``reference``: the reference itself (an oracle: what the correction gives with noise-free low
  frequencies), so the cost of the correction is told apart from the noise of its estimate.

For each method and frame of ``--data`` at each rate: RelMSE, SSIM and the colour level
(`demc_levels.frame_levels`, every lit pixel, no mask) of the output and of each correction.

    python experiments/level_correction.py --data data/library_val --methods demc,rae \
        --out docs/results/level_correction

Writes ``level_correction.json`` and ``level_correction.md`` into ``--out``.

``--choose WEIGHTS`` instead chooses `demc`'s inference settings for the weights folder ``WEIGHTS``
(docs/methods/demc.md "Colour level at inference"), no training, on validation folders only
(``--data``, comma-separated), scored as `demc_levels.measure` scores (surface pixels of each frame's
rebuilt scene):

1. ``exact_window`` (the 1-spp exact-pixel rule, `Config.exact_window`) over `WINDOWS`, ``keep_exact``
   on, ``match_level`` off: the lowest geometric mean over (folder, rate) of the mean RelMSE;
2. with that window, ``match_level`` (sigma) x ``match_max_gain`` x the cut over `SIGMAS`, `GAINS`
   and either a fixed ``match_spike`` from `SPIKES` (labels ``kN``) or one scaled by the frame's rate
   (``match_spike_by_rate``, a single sample's factor from `RATE_SPIKES`, labels ``rN``: a pixel of
   n spp cut at ``1 + (N - 1) / sqrt(n)`` times its median), and off (0): among the settings whose
   per-channel level (median over frames) is within ``--level-tolerance`` of 1 at every folder and
   rate, the lowest geometric mean; off when none is.

    python experiments/level_correction.py --choose jaxdenoise/weights/demc \
        --data data/library_val,data/procedural_val --out docs/results/level_correction

Writes ``choice.json`` and ``choice.md``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import all_measured, num, write_study  # noqa: E402
from demc_levels import frame_levels  # noqa: E402

TARGETS = {"input": 8.0, "input K2": 2.0, "reference": None}
WINDOWS = (0, 3, 5, 7)
SIGMAS = (8.0, 16.0, 32.0)
GAINS = (1.05, 1.1, 1.2, 0.0)  # 0: no limit
SPIKES = (4.0, 8.0)
CHUNK = 12  # settings measured per child process (`score_settings`)
RATE_SPIKES = (8.0, 16.0)  # `match_spike_by_rate`: one sample's factor (4 spp: 4.5 and 8.5)


def measure_corrections(methods: list[str], folder: str, spps: list[int], sigma: float) -> dict:
    import jax.numpy as jnp

    from jaxdenoise import color, metrics
    from jaxdenoise.api import resolve
    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.filters import clamp_outliers, match_level
    from jaxdenoise.inference import inference_fn, prepare
    from jaxdenoise.io import read_buffers, read_image

    res = {"data": folder, "sigma": sigma, "spps": spps, "targets": list(TARGETS), "methods": {}}
    for name in methods:
        m, params = resolve(name)
        fn = inference_fn(m)
        rows: dict = {}
        for shot in discover(folder):
            ref = np.asarray(read_image(shot.reference), np.float32)[..., :3]
            for spp, renders in sorted(renders_by_spp(shot, set(spps)).items()):
                b, _ = read_buffers(renders[0].path)
                y = np.asarray(fn(params, prepare(m, b)))
                c = jnp.asarray(b.color)
                scale = color.exposure_scale(c)
                eps = 1e-2 * float(color.exposure_level(c)[0])
                outs = {"none": y}
                for t, k in TARGETS.items():
                    est = ref if k is None else np.asarray(clamp_outliers(c * scale, k, color.EXPOSURE_LEVEL) / scale)
                    outs[t] = np.asarray(match_level(y, est, sigma, eps))
                for t, out in outs.items():
                    rows.setdefault(t, {}).setdefault(str(spp), []).append(
                        {"relmse": float(metrics.relmse(out, ref)), "ssim": float(metrics.ssim(out, ref)),
                         "level": frame_levels(out, ref)})
        res["methods"][name] = rows
        print(name, {t: {s: round(float(np.mean([r["relmse"] for r in v])), 4) for s, v in d.items()}
                     for t, d in rows.items()}, flush=True)
    return res


def _measure(labels: list[str], folders: list[str]) -> dict:
    from demc_levels import measure

    return measure(labels, folders, [1, 4, 16, 64])


def score_settings(init: str, settings: dict[str, dict], folders: list[str], method: str = "demc") -> dict:
    """For each label -> ``method``'s Config overrides: the weights in ``init`` with them, measured by
    `demc_levels.measure` on ``folders`` at every rate they hold: mean RelMSE and SSIM per (folder,
    rate), the RelMSE's geometric mean, the level (median over frames, R/G/B), the surface halo pixels
    (summed over frames), the emitters (median over frames that show one) and the exposure test."""
    import multiprocessing
    import tempfile
    from concurrent.futures import ProcessPoolExecutor

    from jaxdenoise import checkpoint
    from jaxdenoise.api import resolve

    base, params = resolve(method, init)
    lv: dict = {"methods": {}}
    with tempfile.TemporaryDirectory() as tmp:
        labels = [f"{k}={checkpoint.save(Path(tmp) / k, params, base.with_config(**v).config, {'method': method})}"
                  for k, v in settings.items()]
        # a child process per `CHUNK` settings: each setting compiles its own programs, and one process
        # compiling them all ran out of memory maps (XLA's LLVM: "Cannot allocate memory") after ~45
        for i in range(0, len(labels), CHUNK):
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as ex:
                lv["methods"].update(ex.submit(_measure, labels[i:i + CHUNK], folders).result()["methods"])
    out = {}
    for label, over in settings.items():
        rec = lv["methods"][label]
        keys = [(f, s) for f in folders for s in sorted(rec["scores"][f], key=int)]
        rel = {f"{f} {s}": float(np.mean([x[0] for x in rec["scores"][f][s]])) for f, s in keys}
        emit = {f"{f} {s}": np.median([e for e in rec["emitters"][f][s] if e is not None], 0).tolist()
                for f, s in keys if any(e is not None for e in rec["emitters"][f][s])}
        out[label] = {"config": over, "relmse": rel, "geomean": float(np.exp(np.mean(np.log(list(rel.values()))))),
                      "ssim": {f"{f} {s}": float(np.mean([x[1] for x in rec["scores"][f][s]])) for f, s in keys},
                      "level": {f"{f} {s}": np.median(rec["levels"][f][s], 0).tolist() for f, s in keys},
                      "halo": {f"{f} {s}": int(np.sum(rec["halo_surface"][f][s])) for f, s in keys},
                      "exposure": {f: rec["exposure"][f]["max_rel_diff"] for f in folders if f in rec["exposure"]},
                      "emitters": emit}
        print(label, round(out[label]["geomean"], 5), flush=True)
    return out


def choose(init: str, folders: list[str], tolerance: float) -> dict:
    """The ``--choose`` run (module docstring): the window, then the level setting."""
    res = {"init": init, "data": folders, "level_tolerance": tolerance}
    res["windows"] = score_settings(init, {f"w{w}": {"keep_exact": True, "exact_window": w, "match_level": 0.0}
                                           for w in WINDOWS}, folders)
    window = min(WINDOWS, key=lambda w: res["windows"][f"w{w}"]["geomean"])
    grid = {"off": {"keep_exact": True, "exact_window": window, "match_level": 0.0}}
    for sigma in SIGMAS:
        for gain in GAINS:
            for spike, by_rate in [(k, False) for k in SPIKES] + [(k, True) for k in RATE_SPIKES]:
                label = f"s{sigma:g} g{gain:g} {'r' if by_rate else 'k'}{spike:g}"
                grid[label] = {"keep_exact": True, "exact_window": window, "match_level": sigma,
                               "match_max_gain": gain, "match_spike": spike, "match_spike_by_rate": by_rate}
    res["levels"] = score_settings(init, grid, folders)
    for v in res["levels"].values():
        v["level_ok"] = all(abs(x - 1) <= tolerance for lv in v["level"].values() for x in lv)
    ok = [k for k, v in res["levels"].items() if v["level_ok"]]
    res["chosen"] = {"exact_window": window,
                     "level": min(ok, key=lambda k: res["levels"][k]["geomean"]) if ok else "off"}
    return res


def choice_page(res: dict) -> str:
    first = next(iter(res["windows"].values()))["relmse"]
    cols = sorted(first, key=lambda c: (res["data"].index(c.rsplit(" ", 1)[0]), int(c.rsplit(" ", 1)[1])))
    off = res["levels"]["off"]["geomean"]
    lines = ["# `demc`'s inference settings: the exact-pixel window and the level match", "",
             f"Weights `{res['init']}`, validation folders {', '.join(f'`{f}`' for f in res['data'])}, every "
             "rate they hold (experiments/level_correction.py `--choose`; docs/methods/demc.md \"Colour level at "
             "inference\"; `g0`: no gain limit; `kN`: outliers cut at N times their 3x3 median, `rN`: at "
             "1 + (N - 1) / sqrt(spp) times, `match_spike_by_rate`). RelMSE: mean over frames; level: per "
             "channel, the median over "
             "frames of the median 15x15 box ratio to the reference on surface pixels (experiments/demc_levels.py); "
             "emitters: the output over the reference on the interior of area lights, median over the frames that "
             "show one.", "",
             "## 1. The exact-pixel window (`exact_window`, 1-spp frames; match off)", "",
             "| setting | " + " | ".join(f"RelMSE {c}" for c in cols) + " | emitters (median) | geomean |",
             "|---|" + "---:|" * (len(cols) + 2)]
    for k, v in res["windows"].items():
        em = "; ".join(f"{c}: " + "/".join(num(x, ".3f") for x in e) for c, e in v["emitters"].items()) or "-"
        lines.append(f"| {k} | " + " | ".join(num(v["relmse"][c], ".4f") for c in cols)
                     + f" | {em} | {num(v['geomean'], '.5f')} |")
    lines += ["", f"Chosen: `exact_window = {res['chosen']['exact_window']}` (lowest geometric mean).", "",
              "## 2. The level match (`match_level` sigma px, `match_max_gain`, `match_spike`, "
              "`match_spike_by_rate`)", "",
              "| setting | " + " | ".join(f"level {c}" for c in cols) + f" | within {num(res['level_tolerance'], 'g')} "
              "| geomean | x off |", "|---|" + "---|" * len(cols) + "---|---:|---:|"]
    for k, v in sorted(res["levels"].items(), key=lambda kv: kv[1]["geomean"]):
        lines.append(f"| {k} | " + " | ".join("/".join(num(x, ".3f") for x in v["level"][c]) for c in cols)
                     + f" | {'yes' if v['level_ok'] else 'no'} | {num(v['geomean'], '.5f')} | "
                     f"{num(v['geomean'] / off, '.3f')} |")
    if any(v["level_ok"] for v in res["levels"].values()):
        why = "the lowest geometric mean among the settings within the tolerance at every folder and rate"
    else:
        why = "no setting is within the tolerance at every folder and rate: the rule falls back to no match"
    lines += ["", f"Chosen: `{res['chosen']['level']}` ({why}).", "", "Command: `" + res["command"] + "`", ""]
    return "\n".join(lines)


def page(res: dict) -> str:
    if "windows" in res:  # a --choose run's JSON
        return choice_page(res)
    lines = ["# A low-frequency level correction: colour level against RelMSE", "",
             f"Each method's output on `{res['data']}` (single frames), uncorrected (`none`) and multiplied by "
             f"G(t) / G(output) per channel (Gaussian sigma {num(res['sigma'], 'g')} px) with the target t: "
             "`input` (the noisy input, isolated spikes cut at 8x), `input K2` (cut at 2x) or `reference` "
             "(an oracle with noise-free low frequencies). RelMSE and SSIM: means over frames; level: the "
             "median over frames of each frame's median 15x15 box ratio to the reference, R/G/B, every lit "
             "pixel (experiments/level_correction.py).", "",
             "| method | spp | correction | RelMSE | x none | SSIM | level R/G/B |",
             "|---|---:|---|---:|---:|---:|---|"]
    for name, rows in res["methods"].items():
        for spp in sorted(rows["none"], key=int):
            base = float(np.mean([r["relmse"] for r in rows["none"][spp]]))
            for t in ["none", *res["targets"]]:
                v = rows[t][spp]
                e = float(np.mean([r["relmse"] for r in v]))
                lv = np.median([r["level"] for r in v], 0)
                lines.append(f"| {name} | {spp} | {t} | {num(e, '.4f')} | {num(e / base, '.3f')} | "
                             f"{num(float(np.mean([r['ssim'] for r in v])), '.3f')} | "
                             + "/".join(num(float(x), ".3f") for x in lv) + " |")
    lines += ["", "Command: `" + res["command"] + "`", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a data_gen folder of single frames")
    ap.add_argument("--methods", default="demc,rae")
    ap.add_argument("--spps", default="1,4,16,64")
    ap.add_argument("--sigma", type=float, default=16.0)
    ap.add_argument("--out", required=True)
    ap.add_argument("--choose", metavar="WEIGHTS", help="choose demc's inference settings for this weights folder "
                    "on the --data folders (comma-separated) instead (module docstring)")
    ap.add_argument("--level-tolerance", type=float, default=0.03, help="--choose: the level's allowed distance "
                    "from 1 (issue 33: 3 %%)")
    args = ap.parse_args(argv)
    if args.choose:
        res = choose(args.choose, args.data.split(","), args.level_tolerance)
        res["command"] = "python experiments/level_correction.py " + " ".join(sys.argv[1:] if argv is None else argv)
        all_measured(res, "choice.json")
        print(write_study(Path(args.out), "choice.json", "choice.md", res, choice_page))
        return
    res = measure_corrections(args.methods.split(","), args.data, [int(s) for s in args.spps.split(",")], args.sigma)
    res["command"] = "python experiments/level_correction.py " + " ".join(argv if argv is not None else sys.argv[1:])
    all_measured(res, "level_correction.json")
    print(write_study(Path(args.out), "level_correction.json", "level_correction.md", res, page))


if __name__ == "__main__":
    main()
