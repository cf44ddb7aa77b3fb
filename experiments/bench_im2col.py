"""Convolutions as matrix products on this CPU (issue 36, "Convolutions as matrix products" and the
bf16 lever): one 3x3 convolution per level of RAE's U-Net at 1280x720 (padded to 1280x736; widths 32,
43, 57, 76, 101, in and out), the forward pass, in one run:

- ``xla f32``: `jaxdenoise.nn.Conv` as the networks call it (XLA's convolution, input channels padded to
  a multiple of 8): today's path;
- ``xla bf16``: the same convolution in bfloat16 (accumulating in float32);
- ``im2col f32`` / ``im2col bf16``: the 9 shifted views concatenated over channels (the patch matrix,
  ``H W x 9 C``), then one matrix product with the ``9 C x C_out`` kernel;
- ``row blocks bf16``: the same by blocks of output rows, so each block's patch matrix stays in cache:
  `jaxdenoise.nn.conv.conv_by_rows` (the kernel gradient's row-block path, blocks of about
  `jaxdenoise.nn.conv.BLOCK_PIXELS` pixels) in bfloat16, accumulating in float32;
- ``9 taps bf16``: nine ``H W x C`` by ``C x C_out`` products of the shifted views, summed (no patch
  matrix);
- peers: the bf16 patch matrix's product alone (built before the clock starts: what the matrix product
  costs when the patches are free), and 2048^3 matrix products in float32 and bfloat16.

Each: median ms of ``--runs`` after a warm-up (compile apart), GFLOP/s of the convolution's
``2 H W 9 C C_out``, and the largest difference from ``xla f32`` relative to its largest output.

    JAX_PLATFORMS=cpu python experiments/bench_im2col.py --out docs/results/im2col

The allocator keeps freed memory (`jaxdenoise.runtime.keep_memory`, as the CLI and bench; without it the
large patch matrices are faulted in on every call); the JSON says which (``allocator``). Writes
``im2col.json`` and ``im2col.md`` (`page`: the page from the JSON alone). Run on a quiet machine.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "experiments"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from common import all_measured, num, timed, write_study  # noqa: E402

WIDTHS = (32, 43, 57, 76, 101)
SIZE = (736, 1280)  # 1280x720 padded to the network's stride of 32
VARIANTS = ("xla f32", "xla bf16", "im2col f32", "im2col bf16", "row blocks bf16", "9 taps bf16",
            "patch product alone (bf16)")


def _patches(x, dt):
    """The ``(N, H, W, 9 C)`` patch matrix of a SAME 3x3 convolution of ``x`` (NHWC), as ``dt``."""
    import jax.numpy as jnp

    h, w = x.shape[1], x.shape[2]
    xp = jnp.pad(x.astype(dt), ((0, 0), (1, 1), (1, 1), (0, 0)))
    return jnp.concatenate([xp[:, a:a + h, b:b + w, :] for a in range(3) for b in range(3)], axis=-1)


def conv_variants() -> dict:
    """``name -> f(x, w)`` for every measured way to compute the same convolution (module docstring)."""
    import jax.numpy as jnp
    from jax import lax

    from jaxdenoise import nn
    from jaxdenoise.nn.conv import conv_by_rows

    bf = jnp.bfloat16
    f32 = jnp.float32

    def xla(x, w):
        return nn.Conv(w.shape[-1], 3, bias=False)[1]({"w": w}, x)

    def xla_bf16(x, w):
        return lax.conv_general_dilated(x.astype(bf), w.astype(bf), (1, 1), "SAME",
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"), preferred_element_type=f32)

    def im2col(dt):
        return lambda x, w: jnp.dot(_patches(x, dt), w.reshape(-1, w.shape[-1]).astype(dt), preferred_element_type=f32)

    def by_rows(x, w):
        return conv_by_rows(x.astype(bf), w.astype(bf), (1, 1), "SAME", (1, 1), preferred_element_type=f32)

    def taps(x, w):
        h, wd = x.shape[1], x.shape[2]
        xp = jnp.pad(x.astype(bf), ((0, 0), (1, 1), (1, 1), (0, 0)))
        out = 0.0
        for a in range(3):
            for b in range(3):
                out = out + jnp.dot(xp[:, a:a + h, b:b + wd, :], w[a, b].astype(bf), preferred_element_type=f32)
        return out

    return {"xla f32": xla, "xla bf16": xla_bf16, "im2col f32": im2col(f32), "im2col bf16": im2col(bf),
            "row blocks bf16": by_rows, "9 taps bf16": taps}


def measure_levels(runs: int, mm_n: int) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxdenoise import runtime
    from jaxdenoise.nn.conv import BLOCK_PIXELS

    runtime.keep_memory(respect_env=True)
    res: dict = {"allocator": runtime.status(), "size": list(SIZE), "widths": list(WIDTHS),
                 "block_pixels": BLOCK_PIXELS, "runs": runs, "levels": [],
                 "jax": jax.__version__, "device": str(jax.devices()[0]), "cores": os.cpu_count(),
                 "load_start": os.getloadavg()[0]}
    rng = np.random.default_rng(0)
    for dt, name in ((jnp.float32, "matmul_f32"), (jnp.bfloat16, "matmul_bf16")):
        a = jnp.asarray(rng.standard_normal((mm_n, mm_n), np.float32)).astype(dt)
        _, st = timed(lambda p, q: jnp.dot(p, q, preferred_element_type=jnp.float32), a, a, runs=runs)
        res[name] = {"n": mm_n, "median_s": st["median_s"], "runs_s": st["runs_s"],
                     "gflops": 2 * mm_n ** 3 / 1e9 / st["median_s"]}
    fns = conv_variants()
    for level, c in enumerate(WIDTHS):
        h, w = SIZE[0] >> level, SIZE[1] >> level
        x = jnp.asarray(rng.standard_normal((1, h, w, c), np.float32))
        k = jnp.asarray(rng.standard_normal((3, 3, c, c), np.float32) * np.sqrt(2 / (9 * c)))
        gflop = 2 * h * w * 9 * c * c / 1e9
        row = {"level": level, "h": h, "w": w, "c_in": c, "c_out": c, "gflop": gflop, "variants": {}}
        ref = None
        for name, fn in fns.items():
            out, st = timed(fn, x, k, runs=runs)
            out = np.asarray(out, np.float32)
            ref = out if ref is None else ref
            row["variants"][name] = {"median_s": st["median_s"], "runs_s": st["runs_s"], "compile_s": st["compile_s"],
                                     "max_rel_diff": float(np.max(np.abs(out - ref)) / np.max(np.abs(ref)))}
            print(level, name, f"{1e3 * st['median_s']:.1f} ms", flush=True)
        cols = jax.block_until_ready(jax.jit(lambda x: _patches(x, jnp.bfloat16))(x))
        km = k.reshape(-1, c).astype(jnp.bfloat16)
        _, st = timed(lambda p, q: jnp.dot(p, q, preferred_element_type=jnp.float32), cols, km, runs=runs)
        row["variants"]["patch product alone (bf16)"] = {"median_s": st["median_s"], "runs_s": st["runs_s"],
                                                         "compile_s": st["compile_s"], "max_rel_diff": None}
        res["levels"].append(row)
    res["load_end"] = os.getloadavg()[0]
    return res


def page(res: dict) -> str:
    """``im2col.md`` from ``im2col.json`` alone."""
    all_measured(res, "im2col.json")
    h, w = res["size"]
    lines = ["# Convolutions as matrix products (issue 36)", "",
             f"One 3x3 convolution per level of RAE's U-Net at {w}x{h} (widths {'/'.join(map(str, res['widths']))} in "
             f"and out), forward pass: median ms of {res['runs']} runs after a warm-up, GFLOP/s of the convolution's "
             "2 H W 9 C C_out, and in brackets the largest difference from `xla f32` relative to its largest output.",
             "", "| level | size | channels | " + " | ".join(VARIANTS) + " |",
             "|---:|---|---:|" + "---:|" * len(VARIANTS)]
    for r in res["levels"]:
        cells = []
        for v in VARIANTS:
            m = r["variants"].get(v)
            if m is None:
                cells.append("-")
                continue
            diff = "" if m["max_rel_diff"] is None else f" ({m['max_rel_diff']:.1e})"
            cells.append(f"{1e3 * m['median_s']:.1f} ms, {r['gflop'] / m['median_s']:.0f} GFLOP/s{diff}")
        lines.append(f"| {r['level']} | {r['w']}x{r['h']} | {r['c_in']} | " + " | ".join(cells) + " |")
    f32, b16 = res["matmul_f32"], res["matmul_bf16"]
    total = {v: sum(r["variants"][v]["median_s"] for r in res["levels"]) for v in VARIANTS
             if all(v in r["variants"] for r in res["levels"])}
    best = min((v for v in total if v != "patch product alone (bf16)"), key=total.get)
    lines += ["", f"Peers in the same run: {f32['n']}^3 matrix products, float32 **{f32['gflops']:.0f} GFLOP/s**, "
              f"bfloat16 **{b16['gflops']:.0f} GFLOP/s** ({b16['gflops'] / f32['gflops']:.1f}x).", "",
              "Summed over the levels (those measured at every level): "
              + "; ".join(f"{v} {1e3 * t:.0f} ms" for v, t in total.items())
              + f". Fastest complete convolution: **{best}**.", "",
              f"Row blocks: about {res['block_pixels']} output pixels per block. "
              f"Memory kept for reuse: {res['allocator'].get('kept')}. "
              f"jax {res['jax']}, {res['device']}, {res['cores']} "
              f"cores; load average {num(res['load_start'], '.2f')} at start, "
              f"{num(res['load_end'], '.2f')} at the end.",
              "", "Command: `JAX_PLATFORMS=cpu python experiments/bench_im2col.py --out docs/results/im2col`."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/results/im2col")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--matmul", type=int, default=2048, help="the peer matrix products' cube size")
    args = ap.parse_args()
    t = time.perf_counter()
    res = measure_levels(args.runs, args.matmul)
    res["seconds"] = time.perf_counter() - t
    print(write_study(Path(args.out), "im2col.json", "im2col.md", res, page))


if __name__ == "__main__":
    main()
