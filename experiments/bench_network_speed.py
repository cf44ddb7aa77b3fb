"""Inference speed of the registered networks at 1280x720 against OIDN and a float32 matmul, all
measured in one run (`experiments/bench_conv.py`'s timers: compile apart, median of ``--runs``
after a warm-up; GFLOP from XLA's cost analysis of the compiled program).

    JAX_PLATFORMS=cpu python experiments/bench_network_speed.py --methods demc --out docs/results/network_speed.json

For each method: its shipped parameters, a synthetic 1280x720 frame with every buffer it needs, the
jitted ``apply`` (what `jaxdenoise.load` runs), in float32 and with its stated variants. Run on a
quiet machine; the load average before and after is recorded. The allocator keeps freed memory
(`jaxdenoise.runtime.keep_memory`, as the CLI and bench; ``JAXDENOISE_KEEP_MEMORY=off`` measures
without) and the JSON says which (``allocator``).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from bench_conv import matmul, oidn, timed  # noqa: E402
from jaxdenoise import runtime  # noqa: E402
from jaxdenoise.api import resolve  # noqa: E402
from jaxdenoise.inference import prepare  # noqa: E402
from jaxdenoise.buffers import CHANNELS, Buffers  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402


def frame(h: int, w: int, fields) -> Buffers:
    r = np.random.default_rng(0)
    out = {}
    camera = np.eye(4, dtype=np.float32)
    camera[2, 3] = 5.0  # 5 units in front of the origin (jaxdenoise.view conventions)
    for f in fields:
        if f == "spp":  # frame metadata, set below
            continue
        if f in ("world_to_camera", "world_to_ndc"):
            out[f] = camera
            continue
        v = r.uniform(0.0, 1.0, (h, w, len(CHANNELS[f]))).astype(np.float32)
        if f == "normal":
            v = v * 2 - 1
            v /= np.linalg.norm(v, axis=-1, keepdims=True)
        out[f] = v
    return Buffers(**out, spp=4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--methods", default="demc")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--out", default="docs/results/network_speed.json")
    args = ap.parse_args()
    # the library's fast path, as the CLI and bench run it (JAXDENOISE_KEEP_MEMORY=off: without)
    runtime.keep_memory(respect_env=True)
    w, h = (int(v) for v in args.size.split("x"))
    res = {"size": [w, h], "runs": args.runs, "note": "causal methods: one `step` (state carried in and out)",
           "load_before": os.getloadavg(), "jax": jax.__version__, "cpus": os.cpu_count(),
           "allocator": runtime.status(), "methods": {}}
    res["matmul_2048"] = matmul(2048, args.runs)
    res["oidn"] = oidn(h, w, args.runs)
    for name in args.methods.split(","):
        m, params = resolve(name)
        b = prepare(m, frame(h, w, sorted(m.needs() - {"spp"})))
        if m.temporal == "causal":  # one step of a sequence, the state carried in and out
            state = m.module.init_state(b, m.config)
            _, r = timed(lambda p, st, x: m.module.step(p, st, x, m.config), params, state, b, runs=args.runs)
            r["state_mb"] = sum(int(np.prod(a.shape)) * 4 for a in jax.tree_util.tree_leaves(state)) / 2**20
        else:
            _, r = timed(lambda p, x: m.module.apply(p, x, m.config), params, b, runs=args.runs)
        r["params"] = int(sum(np.prod(a.shape) for a in jax.tree_util.tree_leaves(params)))
        r["vs_oidn"] = r["median_s"] / res["oidn"].get("median_s", float("nan"))
        r["vs_matmul_rate"] = r["gflops"] / res["matmul_2048"]["gflops"]
        res["methods"][name] = r
        print(name, f"{r['median_s'] * 1e3:.0f} ms, {r['gflop']:.1f} GFLOP, {r['gflops']:.0f} GFLOP/s; "
              f"OIDN {res['oidn'].get('median_s', float('nan')) * 1e3:.0f} ms; "
              f"matmul {res['matmul_2048']['gflops']:.0f} GFLOP/s; compile {r['compile_s']:.1f} s", flush=True)
    res["load_after"] = os.getloadavg()
    write_json(Path(args.out), res)


if __name__ == "__main__":
    main()
