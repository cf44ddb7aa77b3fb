"""Where a method wins or loses SSIM (issue 33's check "SSIM at 4 spp above lbf's"): each frame's SSIM
map (docs/metrics.md: tone-mapped, 11x11 Gaussian window) split into the textured and the flat pixels
by the albedo's local contrast, and the error's spectrum.

    python experiments/ssim_regions.py --data data/library_eval4k --spp 4 --methods demc,lbf,oidn \
        --out docs/results/demc_rates/ssim_regions.json

Per frame and method: the mean SSIM over all pixels (`jaxdenoise.metrics.ssim_map`, whose mean is
the bench's number), over the textured pixels (the top quarter of the albedo luminance's standard
deviation in SSIM's window) and over the rest;
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

import numpy as np  # noqa: E402

from jaxdenoise import api, io  # noqa: E402
from jaxdenoise.color import tonemap  # noqa: E402
from jaxdenoise.filters import gaussian  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.metrics import ssim_map  # noqa: E402

TEXTURED = 0.75  # quantile of the albedo's local standard deviation above which a pixel is textured
BORDER = 5  # the pixels `ssim_map` leaves out on each side (its 11-tap window's radius)


def local_std(a: np.ndarray) -> np.ndarray:
    """Standard deviation of an (H, W, 1) image in SSIM's window (Gaussian, sigma 1.5, radius 5) on
    the pixels `ssim_map` keeps."""
    mean, mean_sq = (np.asarray(gaussian(v, 1.5, radius=BORDER), np.float64) for v in (a, a * a))
    inner = (slice(BORDER, -BORDER), slice(BORDER, -BORDER), 0)
    return np.sqrt(np.maximum(mean_sq[inner] - mean[inner] ** 2, 0.0))


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
        tex = local_std(np.asarray(buf.albedo, np.float32).mean(-1, keepdims=True))
        textured = tex > np.quantile(tex, TEXTURED)
        rec = {}
        for m in args.methods.split(","):
            y = api.denoise(buf, m)
            s = np.asarray(ssim_map(y, ref), np.float64).mean(-1)  # the bench's SSIM is its mean
            rec[m] = {"ssim": float(s.mean()), "textured": float(s[textured].mean()),
                      "flat": float(s[~textured].mean()), **spectrum(y, ref)}
            print(f.parent.name, m, {k: round(v, 3) for k, v in rec[m].items() if isinstance(v, float)}, flush=True)
        res["frames"][f.parent.name] = rec
    write_json(Path(args.out), res)
    print(args.out)


if __name__ == "__main__":
    main()
