"""``jaxdenoise`` command line (docs/architecture.md, "Command line"; docs/guide.md).

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
from .runtime import keep_memory
from .buffers import PRIMALS


def _cmd_methods(args: argparse.Namespace) -> int:
    from .methods import available, get

    for name, why in available().items():
        m = get(name)
        status = "ok" if why is None else f"unavailable: {why}"
        print(f"{name:12s} needs {sorted(m.needs())}  [{status}]")
    print(f"methods: {sum(w is None for w in available().values())} of {len(available())} available")
    return 0


def _read_options(args: argparse.Namespace) -> dict:
    """`jaxdenoise.io.read_buffers` keywords from ``--repair``, ``--channels`` and ``--spp``."""
    from .io import parse_channels

    return {"repair": "zero" if args.repair else None,
            "channels": parse_channels(args.channels) if args.channels else None, "spp": args.spp}


def _check_output(args: argparse.Namespace) -> None:
    """Refuse a bad ``-o``/``--exposure`` before anything is read or compiled."""
    from .io import DISPLAY_SUFFIXES

    suffix = Path(args.output).suffix.lower()
    if args.frames:
        if args.exposure is not None:
            raise SystemExit("error: --exposure applies to a PNG/JPEG output; with --frames every frame is written as EXR")
        return
    if suffix not in (".exr",) + DISPLAY_SUFFIXES:
        raise SystemExit(f"error: -o {args.output}: unknown output format '{suffix}'; expected .exr (linear HDR) or "
                         f"{'/'.join(DISPLAY_SUFFIXES)} (tone-mapped to sRGB, 8 bits)")
    if suffix == ".exr" and args.exposure is not None:
        raise SystemExit(f"error: --exposure applies to a PNG/JPEG output; {args.output} is written as linear EXR")


def _cmd_denoise(args: argparse.Namespace) -> int:
    import dataclasses

    from .api import AUTO, choose_method, resolve
    from .inference import clamp_note, nonnegative, notes, prepare
    from .methods import get
    from .fsutil import write_json
    from .io import read_buffers, write_output
    from .tiling import infer

    t0 = time.perf_counter()
    _check_output(args)
    if args.frames and (args.tile is not None or args.max_memory_mb is not None):
        raise SystemExit("error: --tile / --max-memory-mb tile one frame; a sequence (--frames) runs whole frames "
                         "through the sequence driver")
    if args.frames:
        return _denoise_frames(args, t0)
    if args.input is None:
        raise SystemExit("error: give an input EXR, or --frames GLOB for a sequence")
    read = _read_options(args)
    inp = Path(args.input)
    buffers, attrs = read_buffers(inp, **read)
    name = choose_method(buffers) if args.method == AUTO else args.method
    if args.weights is None:  # every missing buffer named before the weights load or anything compiles
        prepare(get(name), buffers, where=str(inp))
    m, params = resolve(name, args.weights)
    prepared = prepare(m, buffers, where=str(inp))
    _warn(notes(m, buffers))
    image, clamped = nonnegative(infer(m, params, prepared, tile=args.tile, max_memory_mb=args.max_memory_mb))
    if clamped:
        _warn([clamp_note(m.name, clamped)])
    out = write_output(args.output, image, exposure=args.exposure or 0.0,
                       attrs={"jaxdenoise:method": m.name, "jaxdenoise:input": str(inp),
                              "jaxdenoise:negative_clamped": clamped})
    cfg_path = out.with_name(out.stem + ".config.json")
    write_json(cfg_path, {"method": m.name, "config": dataclasses.asdict(m.config), "input": str(inp),
                          "weights": args.weights, **read, "negative_clamped": clamped,
                          "tile": args.tile, "max_memory_mb": args.max_memory_mb,
                          "exposure": args.exposure, "channels_from": attrs.get("channels_from"),
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
    from .inference import clamp_note, nonnegative, notes, prepare
    from .io import read_sequence, write_image
    from .methods import get
    from .sequence import run

    read = _read_options(args)
    frames, paths = read_sequence(args.frames, **read)
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
    written, clamped = [], []
    for path, name, image in zip(paths, names, run(m, params, frames, names=[str(p) for p in paths])):
        image, n = nonnegative(image)
        clamped.append(n)
        written.append(str(write_image(out_dir / name, image, {"jaxdenoise:method": m.name,
                                                               "jaxdenoise:input": str(path),
                                                               "jaxdenoise:negative_clamped": n})))
    if sum(clamped):
        _warn([clamp_note(m.name, sum(clamped)) + f" over {sum(1 for n in clamped if n)} frame(s)"])
    write_json(out_dir / "denoise.config.json", {
        "method": m.name, "kind": m.temporal, "config": dataclasses.asdict(m.config), "frames": args.frames,
        "inputs": [str(p) for p in paths], "outputs": [Path(w).name for w in written],
        "weights": args.weights, **read, "negative_clamped": clamped})
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
    from .train import TrainConfig, TrainError, train

    # Each option maps onto one TrainConfig field; options left unset keep the method's TRAIN default.
    options = {"steps": args.steps, "seed": args.seed, "resume": args.resume, "init_from": args.init,
               "val_data": args.val_data, "val_spps": args.val_spps, "validate_every": args.validate_every,
               "ema": args.ema, "select": args.select, "progress": not args.quiet}
    method = get(args.method)
    if args.train_spps is not None:
        if not hasattr(method.config, "train_spps"):
            raise TrainError(f"argument --train-spps: method '{args.method}' trains at one fixed rate "
                             "(its config has no train_spps)")
        method = method.with_config(train_spps=tuple(sorted(set(args.train_spps))))
    if args.train_primal is not None:
        if not hasattr(method.config, "train_primal"):
            raise TrainError(f"argument --train-primal: method '{args.method}' reads no gradient-domain base "
                             "(its config has no train_primal)")
        method = method.with_config(train_primal=args.train_primal)
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
    p = argparse.ArgumentParser(prog="jaxdenoise", description=__doc__.split("\n")[0],
                                epilog="Guide: docs/guide.md; architecture and conventions: docs/architecture.md.")
    p.add_argument("--debug", action="store_true", help="show the traceback of every error, bad input included "
                                                        "(default: one line for bad input, a traceback for bugs)")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")

    s = sub.add_parser("methods", help="list registered methods, what they need, and whether they run here",
                       description="List every registered method, the buffers it reads and whether it can run "
                                   "on this machine (OIDN needs its package).")
    s.set_defaults(func=_cmd_methods)

    s = sub.add_parser("denoise", help="denoise one EXR frame, or every frame of a sequence (--frames)",
                       description="Denoise one multi-channel EXR (or a sequence with --frames). Files from other "
                                   "renderers: --channels maps their layer names, --spp gives the sample count. "
                                   "What each method needs: docs/guide.md.")
    s.add_argument("input", nargs="?", help="noisy multi-channel EXR (R G B plus optional buffers, docs/guide.md)")
    s.add_argument("-o", "--output", required=True,
                   help="output file: .exr (linear HDR, read back by the library) or .png/.jpg (tone-mapped to "
                        "sRGB 8 bits, for viewing; see --exposure); with --frames: a folder of EXRs (required)")
    s.add_argument("--method", default="auto",
                   help="registered method (jaxdenoise methods); default 'auto': the best one the frame has "
                        "the buffers for (gradnet on G-PT frames, demc, lbf, oidn, bilateral: docs/guide.md)")
    s.add_argument("--weights", help="folder with params.npz + config.json (default: the method's shipped weights)")
    s.add_argument("--frames", help="glob of a sequence's frames (sorted by path = time order); every frame is "
                                    "denoised through the sequence driver and written into -o (default: one frame)")
    s.add_argument("--repair", action="store_true",
                   help="replace NaN/Inf with 0 and clamp negative radiance and variance to 0, counting what "
                        "changed (default: refuse such a file, naming channel and count)")
    s.add_argument("--channels", metavar="KEY=NAME,...",
                   help="read layers under other names, e.g. N=nn,P=pp,Z=dd for Mitsuba aov output "
                        "(keys: N P Z albedo albedo2 var vis rough dx dy color or a field name; or one channel: "
                        "R=ch00,N.X=ch03). Default: the contract's names, then Mitsuba aov's usual ones "
                        "(nn, sh_normal, pp, position, dd, depth, Z.T)")
    s.add_argument("--spp", type=int, help="samples per pixel of a file whose header has no 'spp' "
                                           "(Mitsuba writes none; lbf, and the trained-regime checks, read it) "
                                           "(default: the header's; a different header value is an error)")
    s.add_argument("--exposure", type=float,
                   help="PNG/JPEG output only: scale the radiance by 2**EXPOSURE before the sRGB curve "
                        "(stops; default 0)")
    s.add_argument("--max-memory-mb", type=float,
                   help="denoise a frame whose program XLA estimates above this many MiB in the largest "
                        "overlapping tiles that fit (networks only; like OIDN's maxMemoryMB) (default: whole)")
    s.add_argument("--tile", type=int, help="denoise in overlapping tiles of at most this side in pixels "
                                            "(networks only) (default: whole, or what --max-memory-mb allows)")
    s.set_defaults(func=_cmd_denoise)

    s = sub.add_parser("bench", help="error against run time of methods on a data folder",
                       description="Run methods on every shot of a data folder (folders holding reference.exr and "
                                   "noisy EXRs with an integer 'spp' header) and write results.json, results.md, "
                                   "error_vs_time.png and viewer.html (protocol: docs/metrics.md).")
    s.add_argument("data", help="folder of shots (folders with reference.exr + noisy EXRs), walked recursively")
    s.add_argument("--methods", default="all", help="comma-separated names (jaxdenoise methods), or 'all' that "
                                                    "run here (default: all)")
    s.add_argument("--out", required=True, help="report folder (required; created if missing)")
    s.add_argument("--runs", type=int, default=5, help="timed runs per frame, after one warm-up (>= 5; default 5)")
    s.add_argument("--weights", action="append", metavar="METHOD=PATH",
                   help="weights folder for one method, repeatable (default: shipped weights)")
    s.add_argument("--quiet", action="store_true", help="no progress bar (default: a progress bar on stderr)")
    s.add_argument("--scheduler", help="score the frames on Dask: 'local', 'local:N' or a scheduler address "
                                       "(cluster extra); timings are then taken on this machine alone, after "
                                       "(default: no Dask)")
    s.add_argument("--no-timing", action="store_true", help="quality columns only: no timed runs, no plot "
                                                            "(default: timed by the protocol)")
    s.set_defaults(func=_cmd_bench)

    s = sub.add_parser("train", help="train a learned method",
                       description="Train a learned method (lbf, demc, rae, gradnet) on a data folder written by "
                                   "python -m data_gen dataset; checkpoints go to --out and --resume continues "
                                   "from the last one (docs/training.md).")
    s.add_argument("method", help="trainable method: lbf, lbf-nlm, demc, rae, gradnet")
    s.add_argument("--data", required=True, help="training data: a data_gen dataset folder or an exported training "
                                                     "cache (.npz, experiments/export_training.py; required)")
    s.add_argument("--out", required=True, help="run folder: checkpoints, best/, weights/, logs (required)")
    s.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --out "
                                                         "(default: start afresh; a later checkpoint replaces OUT's)")
    s.add_argument("--steps", type=int, help="optimizer steps (default: the method's schedule, docs/training.md)")
    s.add_argument("--seed", type=int, default=0, help="seed of the initialisation and the crop order (default 0)")
    s.add_argument("--init", help="weights folder to start from (fine-tuning; default: random init)")
    s.add_argument("--val-data", help="folder of shots scored during training; the best params go to OUT/best "
                                      "(default: no validation)")
    s.add_argument("--val-spps", type=_int_list,
                   help="comma-separated sampling rates of --val-data to score (default: all)")
    s.add_argument("--train-spps", type=_int_list,
                   help="comma-separated sampling rates of the training renders, e.g. 1,4,16,64: crops are drawn "
                        "from the renders at these rates (the method's config train_spps, written into the "
                        "weights' config.json; default: the method's own)")
    s.add_argument("--train-primal", choices=PRIMALS,
                   help="gradnet: what I_b of the training renders must be, the header's primal (the config's "
                        "train_primal; default gpt, the paper's G-PT primal; base for renders without --primal gpt)")
    s.add_argument("--validate-every", type=int, help="steps between validations (default: only at the end)")
    s.add_argument("--select", choices=["mean", "geomean", "geomean_halo", "loss"],
                   help="what picks OUT/best among the validations: the mean RelMSE over the validation frames, "
                        "or its geometric mean, which counts every frame by its ratio (for validation frames at "
                        "several rates, where the mean follows the noisiest), or that geometric mean among the "
                        "validations with no more halo pixels (output above 4x the reference's 9x9 maximum) than "
                        "the run's first, or the method's unsupervised validation loss, which reads no reference "
                        "(gradnet; default: mean)")
    s.add_argument("--ema", type=float, help="validate and save an exponential moving average of the params "
                                             "with this decay, e.g. 0.999 (default: the method's, else off)")
    s.add_argument("--quiet", action="store_true", help="no progress bar (default: a progress bar on stderr)")
    s.set_defaults(func=_cmd_train)

    for ep in entry_points(group="jaxdenoise.commands"):
        ep.load()(sub)
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one ``warning:`` line on stderr (no source location), like the CLI's own."""
    print(f"warning: {message}", file=sys.stderr if file is None else file)


def main(argv: list[str] | None = None) -> int:
    """Run a verb. Input the library refuses (`jaxdenoise.errors.JaxdenoiseError`, a missing file)
    ends in one ``error:`` line and exit code 2; anything else is a bug and keeps its traceback, as
    does everything with ``--debug``."""
    import warnings

    parser = build_parser()
    args = parser.parse_args(argv)
    keep_memory(respect_env=True)  # before anything compiles (jaxdenoise.runtime)
    if not args.debug:
        warnings.showwarning = _show_warning
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
