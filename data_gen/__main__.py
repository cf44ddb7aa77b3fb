"""``python -m data_gen render SCENE.xml|library:NAME|default ...`` and ``python -m data_gen dataset
--family rooms ...`` / ``dataset --library train ...`` (a split of the scene library)."""
from __future__ import annotations

import argparse
import shlex
import sys
import time

from jaxdenoise.errors import JaxdenoiseError

from .gradient import DEFAULT_SHIFT, DIRECT_EMISSION, PRIMALS, SHIFTS


def _spp_list(text: str) -> list[int]:
    try:
        vals = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--spp expects comma-separated integers, got {text!r}") from None
    if not vals or any(v < 1 for v in vals):
        raise argparse.ArgumentTypeError(f"--spp expects integers >= 1, got {text!r}")
    return vals


def _names(text: str | None) -> list[str] | None:
    return None if text is None else [t.strip() for t in text.split(",") if t.strip()]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="python -m data_gen", description=__doc__)
    p.add_argument("--debug", action="store_true", help="show the traceback of every error, bad input included "
                                                        "(default: one line for bad input, a traceback for bugs)")
    sub = p.add_subparsers(dest="verb", required=True)

    def common(q):
        q.add_argument("--spp", type=_spp_list, default=[4], help="noisy sample counts, e.g. 1,4,16 (default: 4)")
        q.add_argument("--instances", type=int, default=1, help="independent noisy renders per spp (default: 1)")
        q.add_argument("--ref-spp", type=int, default=1024, help="reference spp, 0 = none (default: 1024)")
        q.add_argument("--max-depth", type=int, default=8, help="max path depth, Mitsuba meaning (default: 8)")
        q.add_argument("--methods", default=None,
                       help="render only the buffers these methods need (comma list; default: every buffer the "
                            "scene can vary, gradients excepted)")
        q.add_argument("--buffers", default=None,
                       help="render exactly these buffers, colour always included (comma list; overrides --methods; "
                            "default: none, --methods decides)")
        q.add_argument("--seed", type=int, default=0, help="base random seed (default: 0)")
        q.add_argument("--shift", choices=SHIFTS, default=None,
                       help=f"shift mapping of the gradient buffers dx, dy (default: {DEFAULT_SHIFT})")
        q.add_argument("--primal", choices=PRIMALS, default="base",
                       help="colour of gradient frames: the plain base paths or, with --shift reconnect, the "
                            "G-PT primal (MIS over each pixel's neighbour pairs) (default: base)")
        q.add_argument("--gradient-emission", choices=DIRECT_EMISSION, default="separate",
                       help="directly seen emission of gradient frames: kept out of dx, dy in a layer of its own "
                            "that reconstruction adds back, as Kettunen et al.'s tracer (separate), or in the "
                            "gradients as data_gen did before 0.7.0 (included) (default: separate)")
        q.add_argument("--out", required=True, help="output folder (required)")
        q.add_argument("--variant", default="llvm_ad_rgb",
                       help="preferred Mitsuba variant; scalar_rgb if it does not work (default: llvm_ad_rgb)")
        q.add_argument("--no-progress", action="store_true", help="no progress bar (default: show one)")

    r = sub.add_parser("render", help="render one Mitsuba 3 XML scene (or 'default') into the bench layout")
    r.add_argument("scene", help="scene XML file, library:NAME (a scene of the scene library, data_gen/library), "
                                 "or 'default' for the built-in scene")
    r.add_argument("--width", type=int, default=None,
                   help="film width (default: the scene's own; any XML: through its resx/resy parameters when it "
                        "declares both, else its <film>'s width is replaced; 'default': 128; a library scene given "
                        "one of width/height keeps its aspect)")
    r.add_argument("--height", type=int, default=None,
                   help="film height (default: the scene's own; 'default': the width; see --width)")
    r.add_argument("--frames", type=int, default=0,
                   help="render a camera fly-through of N frames instead (default: 0, one still shot)")
    r.add_argument("--adaptive", default=None, metavar="METHOD[:ESTIMATOR][/K]",
                   help="sample adaptively: a uniform pilot, then --passes passes whose per-pixel counts follow a "
                        "map of the estimated error: 'relvar' (relative variance of the pixel mean), METHOD or "
                        "METHOD:halves (METHOD's error from two denoised half-buffers), METHOD:relvar (relative "
                        "variance over the METHOD-denoised frame); /K: METHOD runs on the map's buffers pooled "
                        "over KxK pixel blocks (K^2 times fewer pixels to denoise); the frame gets an 'spp' layer "
                        "(default: none, uniform sampling)")
    r.add_argument("--passes", type=int, default=1, help="adaptive passes after the pilot (default: 1)")
    r.add_argument("--initial-spp", type=int, default=None,
                   help="spp of the uniform pilot (default: a quarter of --spp, at least 2)")
    r.add_argument("--map-spp", type=int, default=None,
                   help="samples per pixel of the pilot that feed the map (default: half the pilot, at least 2); "
                        "the rest are pooled by count with the last pass (docs/methods/adaptive.md)")
    common(r)
    d = sub.add_parser("dataset", help="render procedural scenes, or a split of the scene library, into "
                                       "DIR/scene_XXXX + manifest.json")
    d.add_argument("--family", default=None,
                   help="procedural family: rooms, objects, dof, thin, fireflies, envmap or mixed "
                        "(default: mixed, unless --library is given)")
    d.add_argument("--library", default=None, metavar="SPLIT",
                   help="render the scenes of this split of the scene library instead: train, val or eval "
                        "(default: none, a procedural family)")
    d.add_argument("--count", type=int, default=None,
                   help="number of scenes (required for a family; default for a library split: all)")
    d.add_argument("--start", type=int, default=0, help="index of the first scene folder (default: 0)")
    d.add_argument("--res", type=int, default=None,
                   help="square resolution (default: 128; library scenes: their own size)")
    d.add_argument("--width", type=int, default=None, help="film width, overrides --res (default: --res)")
    d.add_argument("--height", type=int, default=None, help="film height, overrides --res (default: --res)")
    d.add_argument("--workers", type=int, default=1, help="local worker processes (default: 1)")
    d.add_argument("--scheduler", default=None,
                   help="render on Dask: 'local', 'local:N' (a local cluster of N workers) or a scheduler "
                        "address such as tcp://host:8786 (needs the cluster extra; default: none, local "
                        "processes, see --workers)")
    d.add_argument("--note", default=None, help="free text stored in the manifest (default: none)")
    d.add_argument("--frames", type=int, default=0,
                   help="render each scene as a camera fly-through of N frames (frame_XXXX/ folders; "
                        "default: 0, one still shot per scene)")
    common(d)
    a = p.parse_args(argv)
    # Input the project refuses (its own error type, a missing file) is one line and exit code 2; a
    # bug keeps its traceback, as does everything with --debug.
    try:
        return _run(a, argv)
    except (JaxdenoiseError, FileNotFoundError) as exc:
        if a.debug:
            raise
        print(f"data_gen: error: {exc}", file=sys.stderr)
        return 2


def _run(a: argparse.Namespace, argv: list[str]) -> int:
    from .mitsuba_setup import setup_mitsuba

    variant = setup_mitsuba(a.variant)
    command = "python -m data_gen " + " ".join(shlex.quote(x) for x in argv)
    t0 = time.perf_counter()
    if a.verb == "render":
        from . import library
        from .scenes import default_scene
        from .sequences import render_sequence
        from .shot import render_shot

        if a.scene == "default":
            scene = default_scene(width=a.width or 128, height=a.height or a.width or 128)
            a.width = a.height = None
        else:
            scene = a.scene
            name = library.resolve(scene)  # library:NAME or the path of a library XML (unknown names raise)
            if name is not None:
                a.width, a.height = library.film_size(name, a.width, a.height)
        if a.frames and a.adaptive:
            raise JaxdenoiseError("--adaptive renders still shots; drop --frames (or --adaptive)")
        if a.frames:
            rec = render_sequence(scene, a.out, n_frames=a.frames, spp=a.spp, instances=a.instances,
                                  ref_spp=a.ref_spp, seed=a.seed, buffers=_names(a.buffers),
                                  progress=not a.no_progress, max_depth=a.max_depth, methods=_names(a.methods),
                                  shift=a.shift, primal=a.primal, gradient_emission=a.gradient_emission,
                                  width=a.width, height=a.height)
            frames = rec.get("frames", [])
            n = sum(len(f.get("files", {})) for f in frames)
            secs = sum(f.get("render_seconds", 0.0) for f in frames)
            print(f"data_gen render: {a.frames} frames, {n} files -> {a.out} ({secs:.1f} s rendering, "
                  f"{time.perf_counter() - t0:.1f} s wall, variant {variant})")
            return 0
        rec = render_shot(scene, a.out, spp=a.spp, ref_spp=a.ref_spp, instances=a.instances,
                          methods=_names(a.methods), buffers=_names(a.buffers), max_depth=a.max_depth,
                          seed=a.seed, progress=not a.no_progress, width=a.width, height=a.height,
                          shift=a.shift, primal=a.primal, gradient_emission=a.gradient_emission,
                          adaptive=a.adaptive, passes=a.passes,
                          initial_spp=a.initial_spp, map_spp=a.map_spp)
        rec["command"] = command
        ref = rec.get("reference") or {}
        noise = f", reference RelMSE(halves) {ref['relmse_halves']:.2e}" if ref else ""
        print(f"data_gen render: {len(rec['files'])} files -> {a.out} ({rec['width']}x{rec['height']}, "
              f"{rec['render_seconds']:.1f} s rendering, {time.perf_counter() - t0:.1f} s wall{noise}, variant {variant})")
        return 0
    from .dataset import dataset_size_bytes, generate_dataset

    if a.library is not None and a.family is not None:
        raise JaxdenoiseError(f"dataset: give --family ({a.family}) or --library ({a.library}), not both")
    if a.library is None and a.count is None:
        raise JaxdenoiseError("dataset: --count is required with a procedural family (--family)")
    family = None if a.library is not None else (a.family or "mixed")
    width = a.width if a.width is not None else a.res
    height = a.height if a.height is not None else a.res
    m = generate_dataset(family, a.count, a.out, width=width, height=height, library=a.library,
                         spp=a.spp, instances=a.instances,
                         ref_spp=a.ref_spp, seed=a.seed, start=a.start, workers=a.workers, max_depth=a.max_depth,
                         methods=_names(a.methods), buffers=_names(a.buffers), progress=not a.no_progress,
                         command=command, note=a.note, scheduler=a.scheduler, frames=a.frames,
                         shift=a.shift, primal=a.primal, gradient_emission=a.gradient_emission)
    size = dataset_size_bytes(a.out) / 2**20
    last = m["runs"][-1]
    where = (f", Dask {a.scheduler}: {last.get('workers', '?')} worker(s), {last.get('retries', 0)} retried shot(s)"
             if a.scheduler else "")
    print(f"data_gen dataset: {len(m['scenes'])} scenes in {a.out} ({size:.0f} MiB, "
          f"{m['total_render_seconds']:.0f} s rendering in total, this run {last['wall_seconds']:.0f} s wall, "
          f"variant {variant}{where})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
