"""Speed of convolutions on this CPU: a U-Net of RAE's size (Chaitanya 2017 Fig. 2 without the
recurrent blocks: 7 input channels, encoder stages of 32/43/57/76/101 channels with two 3x3 convs
each, 2x2 max pooling, a 101-channel bottleneck, a mirrored decoder of nearest up-sampling, skip
concatenation and two 3x3 convs, linear 3-channel output), built from `jaxdenoise.nn`.

Measured in one run, each after a warm-up, median of ``--runs`` (compile time apart):

- forward pass at 1280x720 (padded to 1280x736, the network's stride of 32): ms, GFLOP from XLA's
  cost analysis of the compiled program, achieved GFLOP/s;
- peers in the same run: a float32 matmul (``--matmul`` cube) in GFLOP/s, and OIDN (`pyoidn`, RT
  filter, colour + albedo + normal) on a 1280x720 frame;
- variants that might move the forward pass: channel widths padded to multiples of 8 and 16, and
  bfloat16 compute (weights and activations in bf16, convolutions accumulating in float32);
- a training step (forward + backward + Adam) on a batch of 4 x 7 frames of 128x128 (28 crops, as the
  per-frame U-Net sees a 7-frame sequence batch): crops per second and GFLOP/s;
- with ``--data DIR``: the training-data pipeline (`jaxdenoise.pipeline`) delivering the same 28
  augmented crops of colour, albedo, normal and depth (the 4-spp renders) from its decoded cache,
  batches per second against the training step's rate.

    JAX_PLATFORMS=cpu python experiments/bench_conv.py --out docs/results

Writes ``conv.json`` and ``conv.md``. Run on a quiet machine (nothing else running).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise.fsutil import write_json, write_text  # noqa: E402
from jaxdenoise.solvers import optim  # noqa: E402
from common import timed, unet  # noqa: E402

RAE_WIDTHS = (32, 43, 57, 76, 101)


def padded(widths, m):
    return tuple(-(-c // m) * m for c in widths)


def forward(widths, h, w, runs, dtype=jnp.float32):
    init, apply = unet(widths)
    _, params = init(jax.random.PRNGKey(0), (1, h, w, 7))
    x = jnp.asarray(np.random.default_rng(0).random((1, h, w, 7), np.float32))
    if dtype != jnp.float32:
        params = jax.tree_util.tree_map(lambda a: a.astype(dtype), params)
        fn = lambda p, v: apply(p, v.astype(dtype)).astype(jnp.float32)
    else:
        fn = apply
    n_params = sum(int(np.prod(a.shape)) for a in jax.tree_util.tree_leaves(params))
    return {**timed(fn, params, x, runs=runs)[1], "params": n_params}


def train_step(widths, runs, batch=4, frames=7, size=128):
    init, apply = unet(widths)
    _, params = init(jax.random.PRNGKey(0), (-1, size, size, 7))
    opt_init, opt_update = optim.adam(1e-3, b1=0.9, b2=0.99)
    state = opt_init(params)
    r = np.random.default_rng(0)
    x = jnp.asarray(r.random((batch * frames, size, size, 7), np.float32))
    y = jnp.asarray(r.random((batch * frames, size, size, 3), np.float32))

    def step(p, s, x, y):
        loss, g = jax.value_and_grad(lambda q: jnp.mean(jnp.abs(apply(q, x) - y)))(p)
        p, s = opt_update(g, s, p)
        return p, s, loss

    res = timed(step, params, state, x, y, runs=runs)[1]
    res["crops_per_s"] = batch * frames / res["median_s"]
    return res


def matmul(n, runs):
    a = jnp.asarray(np.random.default_rng(0).random((n, n), np.float32))
    return timed(lambda u, v: u @ v, a, a, runs=runs)[1]


def oidn(h, w, runs):
    try:
        import pyoidn
    except ImportError as e:
        return {"error": str(e)}
    r = np.random.default_rng(0)
    c, al = r.random((h, w, 3), np.float32), r.random((h, w, 3), np.float32)
    n = r.normal(size=(h, w, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    pyoidn.denoise(c, al, n, hdr=True)
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        pyoidn.denoise(c, al, n, hdr=True)
        ts.append(time.perf_counter() - t)
    return {"median_s": statistics.median(ts), "all_s": ts}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/results")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--matmul", type=int, default=2048)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--data", default=None, help="data_gen folder for the pipeline's throughput (optional)")
    ap.add_argument("--cache", default="runs/cache", help="where the pipeline's decoded cache goes")
    args = ap.parse_args()
    t0 = time.time()
    h = -(-args.height // 32) * 32
    w = -(-args.width // 32) * 32
    load = os.getloadavg()[0]
    res = {"size": [args.height, args.width], "padded": [h, w], "jax": jax.__version__,
           "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(), "load_at_start": load}
    res["matmul"] = matmul(args.matmul, args.runs)
    print(f"matmul {args.matmul}: {res['matmul']['gflops']:.1f} GFLOP/s", flush=True)
    res["oidn"] = oidn(args.height, args.width, args.runs)
    print(f"oidn: {res['oidn']}", flush=True)
    variants = {"f32": (RAE_WIDTHS, jnp.float32), "f32 widths padded to 8": (padded(RAE_WIDTHS, 8), jnp.float32),
                "f32 widths padded to 16": (padded(RAE_WIDTHS, 16), jnp.float32),
                "bf16 compute": (RAE_WIDTHS, jnp.bfloat16)}
    res["forward"] = {}
    for name, (widths, dt) in variants.items():
        res["forward"][name] = {"widths": list(widths), **forward(widths, h, w, args.runs, dt)}
        f = res["forward"][name]
        print(f"forward {name}: {1e3 * f['median_s']:.0f} ms, {f['gflop']:.1f} GFLOP, {f['gflops']:.1f} GFLOP/s",
              flush=True)
    res["train_step"] = train_step(RAE_WIDTHS, args.runs)
    print(f"train step: {res['train_step']['crops_per_s']:.1f} crops/s, {res['train_step']['gflops']:.1f} GFLOP/s",
          flush=True)
    if args.data:
        from jaxdenoise import pipeline

        fields = ["albedo", "normal", "depth"]  # RAE's inputs that every data_gen frame has (roughness is
        # left out where a scene's roughness is constant)
        t = time.perf_counter()
        cache = pipeline.build_cache(args.data, fields, args.cache, spps=(4,))
        build_s = time.perf_counter() - t
        ts = []
        for step in range(args.runs * 4):
            t = time.perf_counter()
            cache.crops(28, 128, np.random.default_rng([0, step]))
            ts.append(time.perf_counter() - t)
        med = statistics.median(ts)
        res["pipeline"] = {"median_s": med, "batches_per_s": 1 / med, "cache_build_s": build_s,
                           "fields": ["color"] + fields, "vs_train_step": res["train_step"]["median_s"] / med}
        print(f"pipeline: {1e3 * med:.1f} ms per batch of 28 crops ({res['pipeline']['vs_train_step']:.0f}x the "
              f"training step's rate)", flush=True)
    res["load_at_end"] = os.getloadavg()[0]
    res["seconds"] = time.time() - t0
    res["command"] = "python " + " ".join(sys.argv)
    out = Path(args.out)
    write_json(out / "conv.json", res)
    mm = res["matmul"]["gflops"]
    lines = ["# Convolutions on this CPU (RAE-sized U-Net)", "",
             f"Command: `{res['command']}` ({res['seconds']:.0f} s). jax {res['jax']}, {res['device']}, "
             f"{res['cpu_count']} cores; load average {load:.2f} at start, {res['load_at_end']:.2f} at the end. "
             f"Medians of {args.runs} runs after a warm-up; compile apart.", "",
             f"Peers in the same run: float32 matmul {args.matmul}^3: **{mm:.1f} GFLOP/s**; OIDN at "
             f"{args.width}x{args.height}: " + (f"**{1e3 * res['oidn']['median_s']:.0f} ms**" if "median_s" in res["oidn"]
                                                else res["oidn"].get("error", "?")) + ".", "",
             f"## Forward pass at {args.width}x{args.height} (padded to {w}x{h})", "",
             "| variant | widths | params | ms | GFLOP (XLA) | GFLOP/s | / matmul | vs OIDN | compile s |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, f in res["forward"].items():
        vs = f"{f['median_s'] / res['oidn']['median_s']:.2f}x" if "median_s" in res["oidn"] else "-"
        lines.append(f"| {name} | {'/'.join(map(str, f['widths']))} | {f['params']} | {1e3 * f['median_s']:.0f} | "
                     f"{f['gflop']:.1f} | {f['gflops']:.1f} | {f['gflops'] / mm:.2f} | {vs} | {f['compile_s']:.1f} |")
    t = res["train_step"]
    lines += ["", "## Training step (forward + backward + Adam), 4 x 7 crops of 128x128", "",
              f"{1e3 * t['median_s']:.0f} ms per step: **{t['crops_per_s']:.1f} crops/s**, {t['gflop']:.1f} GFLOP, "
              f"{t['gflops']:.1f} GFLOP/s ({t['gflops'] / mm:.2f} of the matmul rate); compile {t['compile_s']:.1f} s.", ""]
    if "pipeline" in res:
        q = res["pipeline"]
        lines += ["## Training-data pipeline", "",
                  f"`jaxdenoise.pipeline` on `{args.data}` ({', '.join(q['fields'])}): a batch of 28 augmented "
                  f"128x128 crops from the memory-mapped cache in **{1e3 * q['median_s']:.1f} ms**, "
                  f"{q['vs_train_step']:.0f}x faster than the training step consumes them (cache built in "
                  f"{q['cache_build_s']:.1f} s, once).", ""]
    write_text(out / "conv.md", "\n".join(lines) + "\n")
    print(f"bench_conv: {res['seconds']:.0f} s -> {out / 'conv.md'}")


if __name__ == "__main__":
    main()
