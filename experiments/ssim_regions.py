"""Where a method wins or loses SSIM (issue 33's check "SSIM at 4 spp above lbf's"): each frame's SSIM
map (docs/metrics.md: tone-mapped, 11x11 Gaussian window) split into the textured and the flat pixels
by the albedo's local contrast, and the error's spectrum.

    python experiments/ssim_regions.py --data data/library_eval4k --spp 4 --methods demc,lbf,oidn \
        --out docs/results/demc_rates/ssim_regions.json

Per frame and method: the mean SSIM over all pixels (the bench's number), over the textured pixels
(the top quarter of the albedo luminance's standard deviation in the same window) and over the rest;
the share of the tone-mapped error's power in the upper half of the spectrum (|f| above a quarter of
the sampling rate on either axis); and the RMS of the error's mean over the pixel classes modulo
p = 2, 4, 8, 16 (a periodic pattern, e.g. an up-sampler's checkerboard, shows there).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise import api, io  # noqa: E402
from jaxdenoise.color import tonemap  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.metrics import ssim_per_image  # noqa: E402

C1, C2 = 0.01 ** 2, 0.03 ** 2  # Wang et al. 2004, data range 1 (docs/metrics.md)
TEXTURED = 0.75  # quantile of the albedo's local standard deviation above which a pixel is textured


def _blur(a: np.ndarray) -> np.ndarray:
    """The SSIM window (11 taps, sigma 1.5) over the valid region, per channel."""
    from scipy.ndimage import gaussian_filter

    out = gaussian_filter(a, sigma=(1.5, 1.5, 0), truncate=5 / 1.5, mode="constant")
    return out[5:-5, 5:-5]


def ssim_map(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(H - 10, W - 10) SSIM, mean over the colour channels, on the tone-mapped images."""
    x, r = np.asarray(tonemap(x), np.float64), np.asarray(tonemap(ref), np.float64)
    mx, mr = _blur(x), _blur(r)
    sxx, srr, sxr = _blur(x * x) - mx * mx, _blur(r * r) - mr * mr, _blur(x * r) - mx * mr
    s = ((2 * mx * mr + C1) * (2 * sxr + C2)) / ((mx * mx + mr * mr + C1) * (sxx + srr + C2))
    return s.mean(-1)


def spectrum(x: np.ndarray, ref: np.ndarray) -> dict:
    d = (np.asarray(tonemap(x), np.float64) - np.asarray(tonemap(ref), np.float64)).mean(-1)
    d = d - d.mean()
    h, w = d.shape
    power = np.abs(np.fft.fft2(d)) ** 2
    fy, fx = np.abs(np.fft.fftfreq(h))[:, None], np.abs(np.fft.fftfreq(w))[None, :]
    upper = float(power[(fy > 0.25) | (fx > 0.25)].sum() / power.sum())
    periodic = {str(p): float(np.sqrt(np.mean([[d[i::p, j::p].mean() ** 2 for j in range(p)] for i in range(p)])))
                for p in (2, 4, 8, 16)}
    return {"upper_half_power_share": upper, "periodic_rms": periodic}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="data/library_eval4k")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--methods", default="demc,lbf,oidn")
    ap.add_argument("--out", default="docs/results/demc_rates/ssim_regions.json")
    args = ap.parse_args()
    frames = sorted(Path(args.data).glob(f"*/spp{args.spp:04d}_00.exr"))
    if not frames:
        raise SystemExit(f"{args.data}: no */spp{args.spp:04d}_00.exr frames")
    res = {"data": args.data, "spp": args.spp, "textured_quantile": TEXTURED, "frames": {},
           "command": "python experiments/ssim_regions.py " + " ".join(sys.argv[1:])}
    for f in frames:
        buf, _ = io.read_buffers(f)
        ref = io.read_image(f.parent / "reference.exr")[..., :3]
        if buf.albedo is None:
            raise SystemExit(f"{f}: no albedo layer (the textured/flat split needs it)")
        a = np.asarray(buf.albedo, np.float64).mean(-1, keepdims=True)
        tex = np.sqrt(np.maximum(_blur(a * a) - _blur(a) ** 2, 0.0))[..., 0]
        textured = tex > np.quantile(tex, TEXTURED)
        rec = {}
        for m in args.methods.split(","):
            y = api.denoise(buf, m)
            s = ssim_map(y, ref)
            bench = float(ssim_per_image(jnp.asarray(y)[None], jnp.asarray(ref)[None])[0])
            rec[m] = {"ssim": float(s.mean()), "ssim_metrics": bench, "textured": float(s[textured].mean()),
                      "flat": float(s[~textured].mean()), **spectrum(y, ref)}
            print(f.parent.name, m, {k: round(v, 3) for k, v in rec[m].items() if isinstance(v, float)}, flush=True)
        res["frames"][f.parent.name] = rec
    write_json(Path(args.out), res)
    print(args.out)


if __name__ == "__main__":
    main()
