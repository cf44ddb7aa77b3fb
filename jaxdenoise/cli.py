"""``jaxdenoise`` command line (DESIGN.md "Command line").

Verbs: ``denoise``, ``bench``, ``train``, ``methods``, plus verbs other installed packages add
through the ``jaxdenoise.commands`` entry-point group (``demo`` comes from ``data_gen``, which the
library never imports). Every verb ends with a one-line summary and writes its resolved config next
to its outputs.
"""
from __future__ import annotations

import argparse
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path


def _cmd_methods(args: argparse.Namespace) -> int:
    from .methods import available, get

    for name, why in available().items():
        m = get(name)
        status = "ok" if why is None else f"unavailable: {why}"
        print(f"{name:12s} needs {sorted(m.needs())}  [{status}]")
    print(f"methods: {sum(w is None for w in available().values())} of {len(available())} available")
    return 0


def _cmd_denoise(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np

    from .api import inference_fn, prepare, resolve
    from .buffers import stack
    from .fsutil import write_json
    from .io import read_buffers, read_sequence, write_image

    t0 = time.perf_counter()
    m, params = resolve(args.method, args.weights)
    repair = "zero" if args.repair else None
    inp = Path(args.input)
    buffers, attrs = read_buffers(inp, repair=repair)
    if args.frames:
        frames, paths = read_sequence(args.frames, repair=repair)
        resolved = [p.resolve() for p in paths]
        if inp.resolve() not in resolved:
            raise SystemExit(f"error: {inp} is not among the frames matched by --frames '{args.frames}'")
        index = resolved.index(inp.resolve())
        if m.recurrent:
            state = m.module.init_state(prepare(m, frames[0]), m.config)
            for frame in frames[: index + 1]:
                state, image = m.module.step(params, state, prepare(m, frame), m.config)
        elif hasattr(m.module, "apply_sequence"):
            seq = stack([prepare(m, f) for f in frames])
            image = m.module.apply_sequence(params, seq, m.config)[index]
        else:
            raise SystemExit(f"error: method '{m.name}' does not use neighbouring frames; drop --frames")
    else:
        image = inference_fn(m)(params, prepare(m, buffers))
    out = write_image(args.output, np.asarray(image), {"jaxdenoise:method": m.name,
                                                       "jaxdenoise:input": str(inp)})
    cfg_path = out.with_name(out.stem + ".config.json")
    write_json(cfg_path, {"method": m.name, "config": dataclasses.asdict(m.config), "input": str(inp),
                          "weights": args.weights, "frames": args.frames, "repair": repair,
                          "input_attrs": {k: v for k, v in attrs.items() if isinstance(v, (int, float, str))}})
    print(f"denoise: {inp.name} -> {out} with {m.name} ({buffers.shape[1]}x{buffers.shape[0]}) "
          f"in {time.perf_counter() - t0:.2f} s; config {cfg_path.name}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from . import bench
    from .methods import parse_list

    weights = {}
    for item in args.weights or []:
        name, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"error: --weights '{item}': expected METHOD=PATH")
        weights[name] = path
    report = bench.run(args.data, parse_list(args.methods), args.out, runs=args.runs, weights=weights,
                       progress=not args.quiet)
    print(bench.markdown_table(bench.summarize(report["records"])))
    print(f"reports: {Path(args.out) / 'results.md'}, {Path(args.out) / 'results.json'}, "
          f"{Path(args.out) / 'error_vs_time.png'}")
    print(bench.one_line(report))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from .train import TrainError, train

    overrides = {"validate_every": args.validate_every} if args.validate_every is not None else {}
    try:
        summary = train(args.method, args.data, args.out, resume=args.resume, steps=args.steps, seed=args.seed,
                        progress=not args.quiet, val_data=args.val_data, val_spps=args.val_spps,
                        init_from=args.init, **overrides)
    except TrainError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(summary.get("line", f"train: {args.method} done; outputs in {args.out}"))
    return 0


def _int_list(text: str) -> list[int]:
    try:
        values = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated integers, e.g. 4,16,64") from None
    if any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: sampling rates must be positive")
    return values


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxdenoise", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="verb", required=True)

    s = sub.add_parser("methods", help="list registered methods, what they need, and whether they run here")
    s.set_defaults(func=_cmd_methods)

    s = sub.add_parser("denoise", help="denoise one EXR frame")
    s.add_argument("input", help="noisy multi-channel EXR (R G B plus optional buffers)")
    s.add_argument("-o", "--output", required=True, help="output EXR")
    s.add_argument("--method", default="gaussian")
    s.add_argument("--weights", help="folder with params.npz + config.json (default: shipped weights)")
    s.add_argument("--frames", help="glob of the whole sequence, for temporal methods")
    s.add_argument("--repair", action="store_true", help="replace NaN/Inf and clamp negative radiance (see docs)")
    s.set_defaults(func=_cmd_denoise)

    s = sub.add_parser("bench", help="error against run time of methods on a data folder")
    s.add_argument("data", help="folder of shots (folders with reference.exr + noisy EXRs)")
    s.add_argument("--methods", default="all", help="comma-separated names, or 'all' available")
    s.add_argument("--out", required=True, help="report folder")
    s.add_argument("--runs", type=int, default=5, help="timed runs per frame (>= 5)")
    s.add_argument("--weights", action="append", help="METHOD=PATH, repeatable")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_bench)

    s = sub.add_parser("train", help="train a learned method")
    s.add_argument("method")
    s.add_argument("--data", required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--resume", action="store_true")
    s.add_argument("--steps", type=int)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--init", help="weights folder to start from (fine-tuning; default: random init)")
    s.add_argument("--val-data", help="folder of shots scored during training; the best params go to OUT/best")
    s.add_argument("--val-spps", type=_int_list,
                   help="comma-separated sampling rates of --val-data to score (default: all)")
    s.add_argument("--validate-every", type=int, help="steps between validations (default: only at the end)")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_train)

    for ep in entry_points(group="jaxdenoise.commands"):
        ep.load()(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted; finished outputs are intact (all writes are atomic)", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
