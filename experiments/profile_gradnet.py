"""GradNet's inference at 1280x720, stage by stage and layer by layer (issue 36, part 3).

    JAX_PLATFORMS=cpu python experiments/profile_gradnet.py --out docs/results/gradnet_profile

The shipped weights on a synthetic frame with every buffer GradNet reads (`bench_network_speed.frame`).
Each stage of `gradnet.apply` is jitted and timed alone on its real input (`common.timed`: compile
apart, a warm-up, the median of ``--runs``; GFLOP from XLA's cost analysis): the input transform
(`gradnet.inputs` and the padding to the network's stride), every layer of `gradnet.forward` in
order (`gradnet.layers`), the output transform (`gradnet.to_hdr`), and Eq. 13's post-process
(`gradnet.postprocess`, a Gaussian of radius `pp_radius`). The whole `apply` is timed beside them,
with OIDN and a float32 matmul in the same run.

Writes ``gradnet_profile.json`` and ``gradnet_profile.md`` (`page`).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bench_conv import matmul, oidn  # noqa: E402
from bench_network_speed import frame  # noqa: E402
from common import all_measured, timed, write_study  # noqa: E402
from jaxdenoise import nn  # noqa: E402
from jaxdenoise.api import resolve  # noqa: E402
from jaxdenoise.inference import prepare  # noqa: E402
from jaxdenoise.methods import gradnet  # noqa: E402


def stages(params, b, config, runs):
    """``[(name, stats)]`` in execution order, each stage on the output of the ones before."""
    out = []

    def run(name, fn, *args):
        y, r = timed(fn, *args, runs=runs)
        out.append((name, {k: r[k] for k in ("median_s", "gflop", "gflops", "compile_s")}))
        return y

    def prep(bb):
        x = gradnet.inputs(bb, config)
        return {k: nn.pad_to_multiple(v, gradnet.STRIDE)[0] for k, v in x.items()}

    x = run("inputs (transform + pad)", prep, b)
    size = b.color.shape[-3:-1]
    L = gradnet.layers(config)
    hd = jnp.concatenate([x["tb"], x["feat"]], -1)
    hg = jnp.concatenate([x["tdx"], x["tdy"]], -1)
    skips_d, skips_g = [], []
    for i in range(3):
        hd = run(f"data encoder {i} ({hd.shape[-3]}x{hd.shape[-2]}, {hd.shape[-1]} -> {config.widths[i]})",
                 L["data"][i][1], params["data"][str(i)], hd)
        hg = run(f"gradient encoder {i} ({hg.shape[-3]}x{hg.shape[-2]}, {hg.shape[-1]} -> {config.widths[i]})",
                 L["grad"][i][1], params["grad"][str(i)], hg)
        skips_d.append(hd)
        skips_g.append(hg)
    h = jnp.concatenate([hd, hg], -1)
    for i in range(config.res_blocks):
        h = run(f"residual block {i} ({h.shape[-3]}x{h.shape[-2]}, {h.shape[-1]} channels)", L["res"][i][1],
                params["res"][str(i)], h)
    for i in range(3):
        lvl = 2 - i
        c = jnp.concatenate([h, skips_d[lvl], skips_g[lvl]], -1)
        h = run(f"decoder {i} ({c.shape[-3]}x{c.shape[-2]}, {c.shape[-1]} -> x2)", L["dec"][i][1],
                params["dec"][str(i)], c)
    if config.input_skip:
        c = jnp.concatenate([h, x["tb"], x["feat"], x["tdx"], x["tdy"]], -1)
        y = run(f"output conv ({c.shape[-1]} -> 3)", L["out"][1], params["out"], c)
        if config.head_width:
            y = y + run(f"head ({c.shape[-1]} -> {config.head_width} -> 3)", L["head"][1], params["head"], c)
        h = y
    y = x["tb"] + h if config.residual_output else h
    hdr = run("output transform", lambda v: jnp.maximum(gradnet.to_hdr(nn.crop_to(v, size), config), 0.0), y)
    if config.postprocess:
        run(f"post-process (Eq. 13, Gaussian radius {config.pp_radius}, sigma {config.pp_sigma})",
            lambda o, bb: gradnet.postprocess(o, nn.crop_to(bb, size), config), hdr, x["base"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--out", default="docs/results/gradnet_profile")
    args = ap.parse_args()
    t0 = time.time()
    w, h = (int(v) for v in args.size.split("x"))
    m, params = resolve("gradnet")
    b = prepare(m, frame(h, w, sorted(m.needs() - {"spp"})))
    res = {"size": args.size, "runs": args.runs, "jax": jax.__version__, "cpus": os.cpu_count(),
           "load_at_start": os.getloadavg()[0], "matmul_2048": matmul(2048, args.runs), "oidn": oidn(h, w, args.runs)}
    _, whole = timed(lambda p, x: m.module.apply(p, x, m.config), params, b, runs=args.runs)
    res["apply"] = {k: whole[k] for k in ("median_s", "gflop", "gflops", "compile_s")}
    res["stages"] = [{"stage": n, **r} for n, r in stages(params, b, m.config, args.runs)]
    res["load_at_end"] = os.getloadavg()[0]
    res["seconds"] = time.time() - t0
    res["command"] = "python " + " ".join(sys.argv)
    write_study(Path(args.out), "gradnet_profile.json", "gradnet_profile.md", res, page)
    print(page(res))


def page(res: dict) -> str:
    all_measured(res, "gradnet_profile.json")
    total = sum(s["median_s"] for s in res["stages"])
    mm = res["matmul_2048"]["gflops"]
    o = res["oidn"].get("median_s", float("nan"))
    a = res["apply"]
    lines = [f"# GradNet at {res['size']}, stage by stage", "",
             f"The whole `apply`: **{a['median_s'] * 1e3:.0f} ms** ({a['gflop']:.1f} GFLOP, {a['gflops']:.0f} GFLOP/s), "
             f"{a['median_s'] / o:.2f}x OIDN `high` ({o * 1e3:.0f} ms) in the same run; a float32 matmul runs at "
             f"{mm:.0f} GFLOP/s. The stages below, each jitted alone, sum to {total * 1e3:.0f} ms.", "",
             "| stage | ms | share | GFLOP | GFLOP/s | / matmul |", "|---|---:|---:|---:|---:|---:|"]
    for s in res["stages"]:
        lines.append(f"| {s['stage']} | {s['median_s'] * 1e3:.1f} | {100 * s['median_s'] / total:.0f} % | "
                     f"{s['gflop']:.2f} | {s['gflops']:.0f} | {s['gflops'] / mm:.2f} |")
    lines += ["", "## Run", "",
              f"`{res['command']}` ({res['seconds']:.0f} s; jax {res['jax']}, {res['cpus']} cores; load average "
              f"{res['load_at_start']:.2f} at start, {res['load_at_end']:.2f} at the end; medians of {res['runs']} runs "
              "after a warm-up, compile apart)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
