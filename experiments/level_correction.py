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


def correct(y: np.ndarray, target: np.ndarray, sigma: float, eps: float) -> np.ndarray:
    """``y * (G(target) + eps) / (G(y) + eps)`` per channel (module docstring)."""
    from jaxdenoise.filters import gaussian

    return np.asarray(y * (gaussian(target, sigma) + eps) / (gaussian(y, sigma) + eps))


def measure_corrections(methods: list[str], folder: str, spps: list[int], sigma: float) -> dict:
    import jax.numpy as jnp

    from jaxdenoise import color, metrics
    from jaxdenoise.api import resolve
    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.filters import clamp_outliers
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
                    outs[t] = correct(y, est, sigma, eps)
                for t, out in outs.items():
                    rows.setdefault(t, {}).setdefault(str(spp), []).append(
                        {"relmse": float(metrics.relmse(out, ref)), "ssim": float(metrics.ssim(out, ref)),
                         "level": frame_levels(out, ref)})
        res["methods"][name] = rows
        print(name, {t: {s: round(float(np.mean([r["relmse"] for r in v])), 4) for s, v in d.items()}
                     for t, d in rows.items()}, flush=True)
    return res


def page(res: dict) -> str:
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
    args = ap.parse_args(argv)
    res = measure_corrections(args.methods.split(","), args.data, [int(s) for s in args.spps.split(",")], args.sigma)
    res["command"] = "python experiments/level_correction.py " + " ".join(argv if argv is not None else sys.argv[1:])
    all_measured(res, "level_correction.json")
    print(write_study(Path(args.out), "level_correction.json", "level_correction.md", res, page))


if __name__ == "__main__":
    main()
