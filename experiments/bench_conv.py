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

Writes ``conv.json`` and ``conv.md`` (`page`: the page from the JSON alone). Run on a quiet machine (nothing
else running).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxdenoise.solvers import optim  # noqa: E402
from common import all_measured, timed, unet, write_study  # noqa: E402

RAE_WIDTHS = (32, 43, 57, 76, 101)
# the forward-pass variants, in the page's order: (pad the widths to a multiple of, compute dtype)
VARIANTS = {"f32": (1, "float32"), "f32 widths padded to 8": (8, "float32"),
            "f32 widths padded to 16": (16, "float32"), "bf16 compute": (1, "bfloat16")}


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


# OIDN's U-Net as its `high` quality runs it for colour + albedo + normal (the "base" model of its
# published training code, RenderKit/oidn training/model.py, UNet(small=False); OIDN keeps a "large"
# model only for clean-auxiliary and auxiliary-only filters): each 3x3 convolution as (input
# channels, output channels, level), level k at 1/2^k of the side; input channels as the parts a skip
# concatenates, ``IC`` the frame's own (9: colour, albedo, normal).
IC = "ic"
OIDN_UNET = (((IC,), 32, 0), ((32,), 32, 0), ((32,), 48, 1), ((48,), 64, 2), ((64,), 80, 3), ((80,), 96, 4),
             ((96,), 96, 4), ((96, 64), 112, 3), ((112,), 112, 3), ((112, 48), 96, 2), ((96,), 96, 2),
             ((96, 32), 64, 1), ((64,), 64, 1), ((64, IC), 64, 0), ((64,), 32, 0), ((32,), 3, 0))
OIDN_ALIGNMENT = 16  # OIDN pads the image to a multiple of 16 (its four 2x2 poolings)


def oidn_gflop(h: int, w: int, in_channels: int = 9) -> float:
    """GFLOP of OIDN's U-Net (`OIDN_UNET`) on an ``h`` x ``w`` frame, a multiply-add counted as 2
    (XLA's convention; products with the zero border counted, which XLA leaves out: under 1 % at
    1280x720), the 2x2 poolings, up-samplings and ReLUs left out."""
    ph, pw = (-(-v // OIDN_ALIGNMENT) * OIDN_ALIGNMENT for v in (h, w))
    flop = 0
    for cin, cout, level in OIDN_UNET:
        cin = sum(in_channels if c == IC else c for c in cin)
        flop += 2 * 9 * cin * cout * (ph >> level) * (pw >> level)
    return flop / 1e9


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
    res = {"size": [args.height, args.width], "padded": [h, w], "jax": jax.__version__,
           "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(), "load_at_start": os.getloadavg()[0]}
    res["matmul"] = {"n": args.matmul, **matmul(args.matmul, args.runs)}
    print(f"matmul {args.matmul}: {res['matmul']['gflops']:.1f} GFLOP/s", flush=True)
    res["oidn"] = oidn(args.height, args.width, args.runs)
    print(f"oidn: {res['oidn']}", flush=True)
    res["forward"] = {}
    for name, (multiple, dt) in VARIANTS.items():
        widths = padded(RAE_WIDTHS, multiple)
        res["forward"][name] = {"widths": list(widths), **forward(widths, h, w, args.runs, getattr(jnp, dt))}
        f = res["forward"][name]
        print(f"forward {name}: {1e3 * f['median_s']:.0f} ms, {f['gflop']:.1f} GFLOP, {f['gflops']:.1f} GFLOP/s",
              flush=True)
    res["train_step"] = train_step(RAE_WIDTHS, args.runs)
    print(f"train step: {res['train_step']['crops_per_s']:.1f} crops/s, {res['train_step']['gflops']:.1f} GFLOP/s",
          flush=True)
    from jaxdenoise.nn import conv as nn_conv

    default, nn_conv.WEIGHT_GRADIENT = nn_conv.WEIGHT_GRADIENT, "xla"  # the path before the row-block gradient
    try:
        res["train_step_xla_gradient"] = train_step(RAE_WIDTHS, args.runs)
    finally:
        nn_conv.WEIGHT_GRADIENT = default
    print(f"train step, XLA's kernel gradient: {res['train_step_xla_gradient']['crops_per_s']:.1f} crops/s", flush=True)
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
        res["pipeline"] = {"data": args.data, "median_s": med, "batches_per_s": 1 / med, "cache_build_s": build_s,
                           "fields": ["color"] + fields, "vs_train_step": res["train_step"]["median_s"] / med}
        print(f"pipeline: {1e3 * med:.1f} ms per batch of 28 crops ({res['pipeline']['vs_train_step']:.0f}x the "
              f"training step's rate)", flush=True)
    res["load_at_end"] = os.getloadavg()[0]
    res["seconds"] = time.time() - t0
    res["command"] = "python " + " ".join(sys.argv)
    out = Path(args.out)
    write_study(out, "conv.json", "conv.md", res, page)
    print(f"bench_conv: {res['seconds']:.0f} s -> {out / 'conv.md'}")


def page(res: dict) -> str:
    """``conv.md`` from ``conv.json`` alone (a missing value raises, never prints a hole)."""
    all_measured(res, "conv.json")
    mm, forward = res["matmul"], dict(res["forward"])
    timings = [mm, res["train_step"], res["train_step_xla_gradient"], *forward.values()]
    runs = {len(x["runs_s"]) for x in timings}
    if len(runs) != 1:
        raise ValueError(f"conv.json: the timings have different run counts {sorted(runs)}")
    (runs,) = runs
    height, width = res["size"]
    ph, pw = res["padded"]
    oidn_s = None if "error" in res["oidn"] else res["oidn"]["median_s"]
    order = list(VARIANTS)
    names = sorted(forward, key=lambda n: (order.index(n) if n in order else len(order), n))
    lines = ["# Convolutions on this CPU (RAE-sized U-Net)", "",
             f"## Forward pass at {width:d}x{height:d} (padded to {pw:d}x{ph:d})", "",
             "| variant | widths | params | ms | GFLOP (XLA) | GFLOP/s | / matmul | vs OIDN | compile s |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in names:
        f = forward[name]
        vs = "-" if oidn_s is None else f"{f['median_s'] / oidn_s:.2f}x"
        lines.append(f"| {name} | {'/'.join(f'{c:d}' for c in f['widths'])} | {f['params']:d} | {1e3 * f['median_s']:.0f} | "
                     f"{f['gflop']:.1f} | {f['gflops']:.1f} | {f['gflops'] / mm['gflops']:.2f} | {vs} | "
                     f"{f['compile_s']:.1f} |")
    base = forward["f32"]
    lines += ["", f"Peers in the same run: float32 matmul {mm['n']:d}^3: **{mm['gflops']:.1f} GFLOP/s**; OIDN at "
              f"{width:d}x{height:d}: " + (f"not measured ({res['oidn']['error']:s})" if oidn_s is None
                                       else f"**{1e3 * oidn_s:.0f} ms**") + ".", ""]
    if oidn_s is not None:
        met = base["gflops"] >= mm["gflops"] and base["median_s"] <= oidn_s
        lines += [f"Goal (the f32 forward pass at least at the matmul rate and faster than OIDN): "
                  f"**{'met' if met else 'missed'}**: {base['gflops'] / mm['gflops']:.2f} of the matmul rate, "
                  f"{base['median_s'] / oidn_s:.2f}x OIDN's time.", ""]
    t = res["train_step"]
    lines += ["## Training step (forward + backward + Adam), 4 x 7 crops of 128x128", "",
              f"{1e3 * t['median_s']:.0f} ms per step: **{t['crops_per_s']:.1f} crops/s**, {t['gflop']:.1f} GFLOP, "
              f"{t['gflops']:.1f} GFLOP/s ({t['gflops'] / mm['gflops']:.2f} of the matmul rate); compile "
              f"{t['compile_s']:.1f} s.", ""]
    x = res["train_step_xla_gradient"]
    lines += [f"The same step with XLA's own kernel gradient (`nn.conv.WEIGHT_GRADIENT = \"xla\"`, the path before "
              f"the row-block gradient): {1e3 * x['median_s']:.0f} ms, {x['crops_per_s']:.1f} crops/s; the default is "
              f"**{x['median_s'] / t['median_s']:.2f}x** its rate.", ""]
    if "pipeline" in res:
        q = res["pipeline"]
        lines += ["## Training-data pipeline", "",
                  f"`jaxdenoise.pipeline` on `{q['data']:s}` ({', '.join(q['fields'])}): a batch of 28 augmented "
                  f"128x128 crops from the memory-mapped cache in **{1e3 * q['median_s']:.1f} ms**, "
                  f"{q['vs_train_step']:.0f}x faster than the training step consumes them (cache built in "
                  f"{q['cache_build_s']:.1f} s, once).", ""]
    lines += ["## Notes", "",
              "- `jaxdenoise.nn.conv` makes two exact rewrites that XLA's CPU back end does not: input channels "
              "are zero-padded to a multiple of 8 before every spatial convolution, and a 1x1 stride-1 "
              "convolution is a matrix product over channels (`jnp.dot`). Transposed convolutions are computed "
              "per output phase instead of over a zero-dilated input. Reverse mode computes a spatial "
              "convolution's kernel gradient as a scan of row-block im2col matrix products (`conv_by_rows`) "
              "instead of XLA's transposed convolution.",
              "- A small U-Net trained for 20 minutes on real crops (the issue's end-to-end check) is "
              "`experiments/unet_20min.py`; its results are in `unet_20min.json`.", "",
              "## Run", "",
              f"Command: `{res['command']:s}` ({res['seconds']:.0f} s). jax {res['jax']:s}, {res['device']:s}, "
              f"{res['cpu_count']:d} cores; load average {res['load_at_start']:.2f} at start, {res['load_at_end']:.2f} "
              f"at the end. Medians of {runs} runs after a warm-up; compile apart."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
