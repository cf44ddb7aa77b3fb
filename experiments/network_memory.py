"""Memory of each network's inference by frame size (issue 36, part 4: what tiled inference must
stay under), from XLA's own memory plan of the compiled program: nothing is run, so a 4K frame costs
only its compile.

    JAX_PLATFORMS=cpu python experiments/network_memory.py --out docs/results/network_memory

For each registered network (shipped weights, a synthetic frame with every buffer it reads, what
`bench_network_speed.py` times) and each ``--sizes`` entry: the compiled ``apply`` (`rae`: one
``step``, its state carried in and out) and ``compiled.memory_analysis()``: argument, output and
temporary bytes (the temporaries are the activations XLA keeps live at once), and `rae`'s state.

Writes ``network_memory.json`` and ``network_memory.md`` (`page`).
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
import numpy as np  # noqa: E402

from bench_network_speed import frame  # noqa: E402
from common import all_measured, write_study  # noqa: E402
from jaxdenoise.api import resolve  # noqa: E402
from jaxdenoise.inference import prepare  # noqa: E402

MB = 2 ** 20


def plan(name: str, w: int, h: int) -> dict:
    m, params = resolve(name)
    b = prepare(m, frame(h, w, sorted(m.needs() - {"spp"})))
    out = {}
    if m.temporal == "causal":
        state = m.module.init_state(b, m.config)
        fn, args = (lambda p, st, x: m.module.step(p, st, x, m.config)), (params, state, b)
        out["state_mb"] = sum(int(np.prod(a.shape)) * a.dtype.itemsize for a in jax.tree_util.tree_leaves(state)) / MB
    else:
        fn, args = (lambda p, x: m.module.apply(p, x, m.config)), (params, b)
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    ma = compiled.memory_analysis()
    out.update(compile_s=time.perf_counter() - t, argument_mb=ma.argument_size_in_bytes / MB,
               output_mb=ma.output_size_in_bytes / MB, temp_mb=ma.temp_size_in_bytes / MB)
    out["total_mb"] = out["argument_mb"] + out["output_mb"] + out["temp_mb"]
    out["bytes_per_pixel"] = out["total_mb"] * MB / (w * h)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--methods", default="demc,rae,gradnet")
    ap.add_argument("--sizes", default="1280x720,1920x1080,3840x2160")
    ap.add_argument("--out", default="docs/results/network_memory")
    args = ap.parse_args()
    t0 = time.time()
    res = {"jax": jax.__version__, "sizes": args.sizes.split(","), "methods": {}}
    for name in args.methods.split(","):
        res["methods"][name] = {}
        for size in res["sizes"]:
            w, h = (int(v) for v in size.split("x"))
            res["methods"][name][size] = r = plan(name, w, h)
            print(f"{name} {size}: {r['total_mb']:.0f} MB ({r['temp_mb']:.0f} MB temporaries)", flush=True)
    res["seconds"] = time.time() - t0
    res["command"] = "python " + " ".join(sys.argv)
    write_study(Path(args.out), "network_memory.json", "network_memory.md", res, page)


def page(res: dict) -> str:
    all_measured(res, "network_memory.json")
    sizes = res["sizes"]
    lines = ["# Network inference memory by frame size (XLA's memory plan)", "",
             "MB of the compiled program: arguments (weights and buffers) + output + temporaries (activations "
             "live at once); nothing is run. `rae` is one `step` with its state.", "",
             "| method | " + " | ".join(f"{s} total | {s} temporaries" for s in sizes) + " | bytes / pixel (largest) |",
             "|---|" + "---:|" * (2 * len(sizes) + 1)]
    for name, by in res["methods"].items():
        cells = []
        for s in sizes:
            cells += [f"{by[s]['total_mb']:.0f}", f"{by[s]['temp_mb']:.0f}"]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {by[sizes[-1]]['bytes_per_pixel']:.0f} |")
    states = {n: by[sizes[-1]]["state_mb"] for n, by in res["methods"].items() if "state_mb" in by[sizes[-1]]}
    if states:
        lines += ["", "Recurrent state at " + sizes[-1] + ": "
                  + ", ".join(f"`{n}` {v:.0f} MB" for n, v in states.items()) + "."]
    lines += ["", "## Run", "", f"`{res['command']}` ({res['seconds']:.0f} s, jax {res['jax']}; compile only)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
