"""The speed levers of issue 36, measured in one run: XLA:CPU's flags (oneDNN, XNNPACK, fast math,
vector width), the kernel-gradient implementation of `jaxdenoise.nn.conv` and glibc's allocator told
to keep freed memory (`jaxdenoise.runtime.keep_memory`), on the forward pass and the training step of
every registered network, each beside OIDN, a float32 matmul and today's path.

    JAX_PLATFORMS=cpu python experiments/bench_xla_flags.py --data DATA --out docs/results/xla_flags

``DATA`` is a data_gen folder with fly-throughs and gradients (the trainer's input for all three
networks), e.g. ``python -m data_gen dataset --family rooms --count 2 --frames 7 --spp 4,64 --ref-spp 64 --primal gpt
--methods demc,rae,gradnet --out DATA``.

XLA flags are read once per process, so each configuration (`CONFIGS`) runs in a child process of
its own (``XLA_FLAGS``, the compile cache off; `keep_memory` called before JAX starts), one after
another; nothing else should run. A child measures, with `common.timed` (compile apart, a warm-up,
then the median of ``--runs``; page faults and kernel time per call beside the time), and its peak
resident memory:

- peers: a float32 matmul (2048^3) and OIDN (`high`, colour + albedo + normal) at 1280x720;
- the forward pass of each network's shipped weights at 1280x720 on a synthetic frame with every
  buffer it reads (`rae`: one `step`, its state carried), what `bench_network_speed.py` times;
- one training step of each network as `jaxdenoise.train` takes it (`train.step_fn`: loss,
  gradient, clipping, the optimizer), on a batch the method's own ``batch`` draws from ``DATA``
  at its shipped training crop size; a method with parameter groups (`gradnet`) times each group's
  step and reports their mean (the trainer alternates them); crops per second counts the crops of
  one step (`rae`: sequences x frames).

Exactness: each child also writes every network's output on a real frame of ``DATA`` and the
gradient of its loss on the first training batch; the page gives the largest difference to the
``today`` configuration relative to the largest magnitude (``max |a - b| / max |b|``).

Writes ``xla_flags.json`` and ``xla_flags.md`` (`page`: the page from the JSON alone).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import numpy as np  # noqa: E402

from common import all_measured, num, write_study  # noqa: E402

NETWORKS = ("demc", "rae", "gradnet")
# name -> (XLA_FLAGS, nn.conv.WEIGHT_GRADIENT, jaxdenoise.runtime.keep_memory called first); "today" is the
# path before this study (XLA's defaults)
CONFIGS = {
    "today": ("", "xla", False),
    "fast kernel gradient": ("", "fast", False),
    "oneDNN": ("--xla_cpu_use_onednn=true", "fast", False),
    "oneDNN custom calls": ("--xla_cpu_use_onednn=true --xla_cpu_experimental_onednn_custom_call=true", "fast",
                            False),
    "oneDNN fusions": ("--xla_cpu_use_onednn=true --xla_cpu_experimental_onednn_fusion_type=dot,eltwise", "fast",
                       False),
    "XNNPACK off": ("--xla_cpu_use_xnnpack=false", "fast", False),
    "XNNPACK fusions": ("--xla_cpu_experimental_xnn_fusion_type=dot,eltwise,reduce", "fast", False),
    "512-bit vectors": ("--xla_cpu_prefer_vector_width=512", "fast", False),
    "fast math": ("--xla_cpu_enable_fast_math=true", "fast", False),
    "memory kept": ("", "fast", True),
    "memory kept + XNNPACK fusions": ("--xla_cpu_experimental_xnn_fusion_type=dot,eltwise,reduce", "fast", True),
    "memory kept + XNNPACK convolutions": ("--xla_cpu_experimental_xnn_fusion_type=individual_convolution", "fast",
                                           True),
}


# -- the child: one configuration ------------------------------------------------------------------
def _frame(data: Path):
    """The first noisy render of ``data`` (a real frame) as Buffers."""
    from jaxdenoise.io import read_buffers

    for exr in sorted(data.rglob("*.exr")):
        if exr.name != "reference.exr":
            return exr, read_buffers(exr)[0]
    raise SystemExit(f"{data}: no noisy render")


def child(args) -> None:
    import jax

    from bench_conv import matmul, oidn
    from bench_network_speed import frame
    from common import timed
    from jaxdenoise import nn, runtime, train
    from jaxdenoise.api import resolve
    from jaxdenoise.fsutil import write_json
    from jaxdenoise.inference import prepare

    nn.conv.WEIGHT_GRADIENT = args.grad
    w, h = (int(v) for v in args.size.split("x"))
    res = {"xla_flags": os.environ.get("XLA_FLAGS", ""), "weight_gradient": args.grad,
           "keep_memory": runtime.status()["kept"] is True, "load_before": os.getloadavg()[0],
           "matmul_2048": matmul(2048, args.runs), "oidn": oidn(h, w, args.runs), "forward": {}, "train": {}}
    exact = {}
    exr, real = _frame(Path(args.data))
    for name in NETWORKS:
        m, params = resolve(name)
        causal = m.temporal == "causal"

        def run(p, b):
            if causal:
                return m.module.step(p, m.module.init_state(b, m.config), b, m.config)[1]
            return m.module.apply(p, b, m.config)

        fields = sorted(m.needs() - {"spp"})
        _, r = timed(run, params, prepare(m, frame(h, w, fields)), runs=args.runs)
        res["forward"][name] = r
        exact[f"{name}/forward"] = np.asarray(jax.jit(run)(params, prepare(m, real)))

        data = train.load_data(m, args.data, progress=False)
        tc = train.TrainConfig.for_method(m, steps=1, progress=False)
        groups = train.param_groups(m, tc, params)
        state = train.optimizer_state(groups, params)
        b = m.module.batch(data.dataset, 0, m.config, np.random.default_rng([0, 0]))
        b = jax.tree_util.tree_map(jax.numpy.asarray, b)
        steps = []
        for g in groups:
            s = state if g.name is None else state[g.name]
            step = train.step_fn(m, g.train, g.name, g.keys)
            out, r = timed(step, params, s, b, runs=args.runs)
            r["group"] = g.name
            steps.append(r)

            def grads_of(q, g=g):
                def f(sub):
                    full = sub if g.name is None else {**q, **sub}
                    kw = {} if g.name is None else {"group": g.name}
                    out = m.module.loss(full, b, m.config, **kw)
                    return out[0] if isinstance(out, tuple) else out
                return jax.grad(f)(q if g.name is None else {k: q[k] for k in g.keys})

            grads = jax.jit(grads_of)(params)
            for path, leaf in jax.tree_util.tree_leaves_with_path(grads):
                exact[f"{name}/grad/{g.name}/{jax.tree_util.keystr(path)}"] = np.asarray(leaf)
        lead = jax.tree_util.tree_leaves(b)[0].shape
        crops = int(np.prod(lead[:2])) if causal else int(lead[0])
        med = float(np.mean([s["median_s"] for s in steps]))
        res["train"][name] = {"steps": steps, "median_s": med, "crops": crops, "crops_per_s": crops / med,
                              "crop": int(m.config.train_crop), "compile_s": float(sum(s["compile_s"] for s in steps))}
        print(f"  {name}: forward {res['forward'][name]['median_s'] * 1e3:.0f} ms, train {med * 1e3:.0f} ms "
              f"({crops / med:.1f} crops/s)", flush=True)
    res["frame"] = str(exr.relative_to(Path(args.data)))
    res["load_after"] = os.getloadavg()[0]
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB
    np.savez(args.arrays, **exact)
    write_json(Path(args.result), res)


# -- the parent: every configuration, then the page ------------------------------------------------
def _rel(a: np.ndarray, b: np.ndarray) -> float:
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    return float(np.max(np.abs(a - b)) / scale) if scale > 0 else float(np.max(np.abs(a - b), initial=0.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", default="docs/results/xla_flags")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--configs", default=",".join(CONFIGS), help="comma list of CONFIGS names")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--grad", default="fast", help=argparse.SUPPRESS)
    ap.add_argument("--keep-memory", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--arrays", help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        if args.keep_memory:  # before JAX starts its threads (see jaxdenoise.runtime)
            from jaxdenoise import runtime

            if not runtime.keep_memory():
                raise SystemExit(f"keep_memory: {runtime.status()['why']}")
        return child(args)
    names = [n.strip() for n in args.configs.split(",")]
    unknown = [n for n in names if n not in CONFIGS]
    if unknown or "today" not in names:
        raise SystemExit(f"--configs: unknown {unknown} (known: {list(CONFIGS)}); 'today' is required")
    t0 = time.time()
    shown = args.data if not os.path.isabs(args.data) else "DATA"  # no machine path in a report
    command = [shown if a == args.data else a for a in sys.argv]
    res = {"size": args.size, "runs": args.runs, "data": shown, "cpus": os.cpu_count(),
           "load_at_start": os.getloadavg()[0], "configs": {}, "command": "python " + " ".join(command)}
    arrays = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            flags, grad, keep = CONFIGS[name]
            print(f"{name}: XLA_FLAGS='{flags}', kernel gradient {grad}, memory kept {keep}", flush=True)
            env = {**os.environ, "XLA_FLAGS": flags, "JAXDENOISE_CACHE_DIR": "off", "JAX_PLATFORMS": "cpu"}
            a, r = Path(tmp) / f"{len(arrays)}.npz", Path(tmp) / f"{len(arrays)}.json"
            done = subprocess.run([sys.executable, __file__, "--child", "--data", args.data, "--size", args.size,
                                   "--runs", str(args.runs), "--grad", grad, "--arrays", str(a), "--result", str(r)]
                                  + (["--keep-memory"] if keep else []),
                                  env=env, stderr=subprocess.PIPE, text=True)
            if done.returncode != 0:  # a configuration that crashes XLA is a result, not the end of the sweep
                tail = [ln for ln in done.stderr.splitlines() if ln.strip() and "Warning" not in ln][-3:]
                res["configs"][name] = {"xla_flags": flags, "weight_gradient": grad, "keep_memory": keep,
                                        "error": f"exit status {done.returncode}: " + " / ".join(tail)}
                print(f"  failed: {res['configs'][name]['error']}", flush=True)
                continue
            res["configs"][name] = json.loads(r.read_text())
            with np.load(a) as z:
                arrays[name] = {k: z[k] for k in z.files}
    base = arrays["today"]
    for name in arrays:
        diffs = {}
        for key, ref in base.items():
            net, kind = key.split("/")[:2]
            d = _rel(arrays[name][key], ref)
            diffs[f"{net}/{kind}"] = max(diffs.get(f"{net}/{kind}", 0.0), d)
        res["configs"][name]["max_rel_diff"] = diffs
    res["load_at_end"] = os.getloadavg()[0]
    res["seconds"] = time.time() - t0
    write_study(Path(args.out), "xla_flags.json", "xla_flags.md", res, page)
    print(f"bench_xla_flags: {res['seconds']:.0f} s -> {Path(args.out) / 'xla_flags.md'}")


def page(res: dict) -> str:
    """``xla_flags.md`` from ``xla_flags.json`` alone."""
    all_measured(res, "xla_flags.json")
    order = list(CONFIGS)
    cfg = {k: res["configs"][k] for k in sorted(res["configs"], key=lambda k: (order.index(k) if k in order else len(order), k))}
    today = cfg["today"]
    lines = ["# Speed levers on this CPU: XLA flags and the kernel gradient", "",
             f"Every registered network at {res['size']} (forward) and its training step (the trainer's own, on "
             "real crops), per configuration, with the peers measured in the same child process. Times are "
             "medians in ms; `x today` is today's time over this configuration's (above 1: faster).", "",
             "## Training step", "",
             "| configuration | " + " | ".join(f"{n} ms | {n} crops/s | x today" for n in NETWORKS) + " | grad diff |",
             "|---|" + "---:|" * (3 * len(NETWORKS) + 1)]
    ok = {name: c for name, c in cfg.items() if "error" not in c}
    for name, c in ok.items():
        cells = []
        for n in NETWORKS:
            t = c["train"][n]
            cells += [f"{t['median_s'] * 1e3:.0f}", f"{t['crops_per_s']:.1f}",
                      f"{today['train'][n]['median_s'] / t['median_s']:.2f}"]
        worst = max(v for k, v in c["max_rel_diff"].items() if k.endswith("/grad"))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {num(worst, '.1e')} |")
    lines += ["", "## Forward pass", "",
              "| configuration | " + " | ".join(f"{n} ms | {n} / OIDN" for n in NETWORKS)
              + " | OIDN ms | matmul GFLOP/s | output diff |",
              "|---|" + "---:|" * (2 * len(NETWORKS) + 3)]
    for name, c in ok.items():
        o = c["oidn"].get("median_s", float("nan"))
        cells = []
        for n in NETWORKS:
            f = c["forward"][n]["median_s"]
            cells += [f"{f * 1e3:.0f}", f"{f / o:.2f}"]
        worst = max(v for k, v in c["max_rel_diff"].items() if k.endswith("/forward"))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {o * 1e3:.0f} | {c['matmul_2048']['gflops']:.0f} | "
                     f"{num(worst, '.1e')} |")
    if all("peak_rss_mb" in c for c in ok.values()):  # runs since the allocator study (jaxdenoise.runtime)
        lines += ["", "## Page faults and memory", "",
                  "Per call, medians: page faults and the process's CPU time spent in the kernel (`sys s`); "
                  "the child's peak resident memory over all its work.", "",
                  "| configuration | " + " | ".join(f"{n} forward faults | {n} forward sys s | {n} train faults"
                                                   for n in NETWORKS) + " | peak RSS MB |",
                  "|---|" + "---:|" * (3 * len(NETWORKS) + 1)]
        for name, c in ok.items():
            cells = []
            for n in NETWORKS:
                steps = c["train"][n]["steps"]
                cells += [f"{c['forward'][n]['median_faults']:.0f}", f"{c['forward'][n]['median_sys_s']:.2f}",
                          f"{np.mean([s['median_faults'] for s in steps]):.0f}"]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {c['peak_rss_mb']:.0f} |")
    lines += ["", "## Configurations", ""]
    for name, c in cfg.items():
        state = (f"**failed**: {c['error']}" if "error" in c else
                 f"load {c['load_before']:.2f} before, {c['load_after']:.2f} after")
        kept = "; memory kept (`jaxdenoise.runtime.keep_memory`)" if c.get("keep_memory") else ""
        lines.append(f"- **{name}**: `XLA_FLAGS='{c['xla_flags']}'`, kernel gradient `{c['weight_gradient']}`{kept}; "
                     f"{state}.")
    lines += ["", "Diffs: the largest `max |a - b| / max |b|` against `today` over the networks' outputs on the real "
              f"frame `{today['frame']}` (forward) and over every parameter's loss gradient on the first training "
              "batch (grad).", "", "## Run", "",
              f"`{res['command']}` ({res['seconds']:.0f} s, {res['cpus']} cores; load average {res['load_at_start']:.2f} "
              f"at start, {res['load_at_end']:.2f} at the end; medians of {res['runs']} runs after a warm-up, compile "
              "apart)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
