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

from .errors import JaxdenoiseError


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

    from .api import AUTO, choose_method, resolve
    from .inference import inference_fn, notes, prepare
    from .methods import get
    from .fsutil import write_json
    from .io import read_buffers, write_image

    t0 = time.perf_counter()
    if args.frames:
        return _denoise_frames(args, t0)
    if args.input is None:
        raise SystemExit("error: give an input EXR, or --frames GLOB for a sequence")
    repair = "zero" if args.repair else None
    inp = Path(args.input)
    buffers, attrs = read_buffers(inp, repair=repair)
    name = choose_method(buffers) if args.method == AUTO else args.method
    if args.weights is None:  # every missing buffer named before the weights load or anything compiles
        prepare(get(name), buffers, where=str(inp))
    m, params = resolve(name, args.weights)
    prepared = prepare(m, buffers, where=str(inp))
    _warn(notes(m, buffers))
    image = inference_fn(m)(params, prepared)
    out = write_image(args.output, np.asarray(image), {"jaxdenoise:method": m.name,
                                                       "jaxdenoise:input": str(inp)})
    cfg_path = out.with_name(out.stem + ".config.json")
    write_json(cfg_path, {"method": m.name, "config": dataclasses.asdict(m.config), "input": str(inp),
                          "weights": args.weights, "repair": repair,
                          "input_attrs": {k: v for k, v in attrs.items() if isinstance(v, (int, float, str))}})
    print(f"denoise: {inp.name} -> {out} with {m.name} ({buffers.shape[1]}x{buffers.shape[0]}) "
          f"in {time.perf_counter() - t0:.2f} s; config {cfg_path.name}")
    return 0


def frame_output_names(paths: list[Path]) -> list[str]:
    """Output file names for a sequence's frames: the frame's file name when those are unique, else
    its path below the frames' common folder with ``/`` as ``_`` (``frame_0003/spp0001_00.exr`` ->
    ``frame_0003_spp0001_00.exr``)."""
    import os

    if len({p.name for p in paths}) == len(paths):
        return [p.name for p in paths]
    common = Path(os.path.commonpath([str(p.resolve().parent) for p in paths]))
    return [str(p.resolve().relative_to(common)).replace(os.sep, "_") for p in paths]


def _warn(remarks: list[str]) -> None:
    """What the run does without (`inference.notes`), one ``warning:`` line each on stderr."""
    for r in remarks:
        print(f"warning: {r}", file=sys.stderr)


def _denoise_frames(args: argparse.Namespace, t0: float) -> int:
    """``denoise --frames GLOB -o OUT_DIR``: every frame through the sequence driver, each written."""
    import dataclasses

    from .api import AUTO, choose_method, resolve
    from .fsutil import write_json
    from .inference import notes, prepare
    from .io import read_sequence, write_image
    from .methods import get
    from .sequence import run

    repair = "zero" if args.repair else None
    frames, paths = read_sequence(args.frames, repair=repair)
    name = choose_method(frames[0]) if args.method == AUTO else args.method
    if args.weights is None:  # every missing buffer named before the weights load or anything compiles
        for f, p in zip(frames, paths):
            prepare(get(name), f, where=str(p))
    m, params = resolve(name, args.weights)
    if args.input is not None and Path(args.input).resolve() not in [p.resolve() for p in paths]:
        raise SystemExit(f"error: {args.input} is not among the frames matched by --frames '{args.frames}'")
    out_dir = Path(args.output)
    if out_dir.suffix.lower() == ".exr" or out_dir.is_file():
        raise SystemExit(f"error: with --frames, -o/--output is a folder for every denoised frame; got {out_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    if frames:
        _warn(notes(m, frames[0], sequence=True))
    names = frame_output_names(paths)
    written = []
    for path, name, image in zip(paths, names, run(m, params, frames, names=[str(p) for p in paths])):
        written.append(str(write_image(out_dir / name, image, {"jaxdenoise:method": m.name,
                                                               "jaxdenoise:input": str(path)})))
    write_json(out_dir / "denoise.config.json", {
        "method": m.name, "kind": m.temporal, "config": dataclasses.asdict(m.config), "frames": args.frames,
        "inputs": [str(p) for p in paths], "outputs": [Path(w).name for w in written],
        "weights": args.weights, "repair": repair})
    print(f"denoise: {len(written)} frame(s) of '{args.frames}' -> {out_dir} with {m.name} ({m.temporal}) "
          f"in {time.perf_counter() - t0:.2f} s; config denoise.config.json")
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
                       progress=not args.quiet, scheduler=args.scheduler, timing=not args.no_timing)
    print(bench.markdown_table(bench.summarize(report["records"])))
    out = Path(args.out)
    plot = f"{out / 'error_vs_time.png'}, " if (out / "error_vs_time.png").is_file() and not args.no_timing else ""
    print(f"reports: {out / 'results.md'}, {out / 'results.json'}, {plot}viewer {out / 'viewer.html'}")
    print(bench.one_line(report))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from .methods import get
    from .train import TrainConfig, train

    # Each option maps onto one TrainConfig field; options left unset keep the method's TRAIN default.
    options = {"steps": args.steps, "seed": args.seed, "resume": args.resume, "init_from": args.init,
               "val_data": args.val_data, "val_spps": args.val_spps, "validate_every": args.validate_every,
               "ema": args.ema, "progress": not args.quiet}
    method = get(args.method)
    summary = train(method, args.data, args.out,
                    TrainConfig.for_method(method, **{k: v for k, v in options.items() if v is not None}))
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
    p.add_argument("--debug", action="store_true", help="show the traceback of every error, bad input included "
                                                        "(default: one line for bad input, a traceback for bugs)")
    sub = p.add_subparsers(dest="verb", required=True)

    s = sub.add_parser("methods", help="list registered methods, what they need, and whether they run here")
    s.set_defaults(func=_cmd_methods)

    s = sub.add_parser("denoise", help="denoise one EXR frame, or every frame of a sequence (--frames)")
    s.add_argument("input", nargs="?", help="noisy multi-channel EXR (R G B plus optional buffers)")
    s.add_argument("-o", "--output", required=True, help="output EXR (with --frames: output folder)")
    s.add_argument("--method", default="auto",
                   help="registered method (jaxdenoise methods); default 'auto': the best one the frame has "
                        "the buffers for (gradnet on G-PT frames, demc, lbf, oidn, bilateral: docs/guide.md)")
    s.add_argument("--weights", help="folder with params.npz + config.json (default: shipped weights)")
    s.add_argument("--frames", help="glob of a sequence's frames (sorted by path = time order); every "
                                    "frame is denoised through the sequence driver and written into -o")
    s.add_argument("--repair", action="store_true", help="replace NaN/Inf and clamp negative radiance (see docs)")
    s.set_defaults(func=_cmd_denoise)

    s = sub.add_parser("bench", help="error against run time of methods on a data folder")
    s.add_argument("data", help="folder of shots (folders with reference.exr + noisy EXRs)")
    s.add_argument("--methods", default="all", help="comma-separated names, or 'all' available")
    s.add_argument("--out", required=True, help="report folder")
    s.add_argument("--runs", type=int, default=5, help="timed runs per frame (>= 5)")
    s.add_argument("--weights", action="append", help="METHOD=PATH, repeatable")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--scheduler", help="score the frames on Dask: 'local', 'local:N' or a scheduler address "
                                       "(cluster extra); timings are then taken on this machine alone, after")
    s.add_argument("--no-timing", action="store_true", help="quality columns only (no timed runs, no plot)")
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
    s.add_argument("--ema", type=float, help="validate and save an exponential moving average of the params "
                                             "with this decay, e.g. 0.999 (default: the method's, else off)")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_train)

    for ep in entry_points(group="jaxdenoise.commands"):
        ep.load()(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run a verb. Input the library refuses (`jaxdenoise.errors.JaxdenoiseError`, a missing file)
    ends in one ``error:`` line and exit code 2; anything else is a bug and keeps its traceback, as
    does everything with ``--debug``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted; finished outputs are intact (all writes are atomic)", file=sys.stderr)
        return 130
    except (JaxdenoiseError, FileNotFoundError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
