"""``jaxdenoise demo``: the main job on the embedded default scene.

Renders `data_gen.default_scene()` at low spp with the buffers the available methods need, plus a
reference (cached: a second run renders nothing), then runs ``jaxdenoise bench`` on it with every
available method and prints the table and where the plot is. It lives in ``data_gen`` (the library
never imports data_gen) and is plugged into the ``jaxdenoise`` CLI through the
``jaxdenoise.commands`` entry point.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxdenoise" / "demo"


def register(sub) -> None:
    s = sub.add_parser("demo", help="render the built-in scene (cached) and bench every available method on it")
    s.add_argument("--out", default="jaxdenoise-demo", help="report folder (default: ./jaxdenoise-demo)")
    s.add_argument("--cache", default=str(DEFAULT_CACHE), help=f"render cache (default: {DEFAULT_CACHE})")
    s.add_argument("--spp", default="4,16", help="comma-separated noisy sample counts (default: 4,16)")
    s.add_argument("--ref-spp", type=int, default=1024, help="reference sample count (default: 1024)")
    s.add_argument("--size", type=int, default=128, help="image width and height (default: 128)")
    s.add_argument("--methods", default="all",
                   help="comma-separated method names, or 'all' available (default: all)")
    s.add_argument("--runs", type=int, default=5, help="timed runs per frame, at least 5 (default: 5)")
    s.add_argument("--quiet", action="store_true", help="no progress bars (default: show them)")
    s.set_defaults(func=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    from jaxdenoise import bench
    from jaxdenoise.fsutil import report_path, write_json
    from jaxdenoise.methods import parse_list

    import data_gen

    t0 = time.perf_counter()
    variant = data_gen.setup_mitsuba()
    methods = parse_list(args.methods)
    spp = tuple(int(s) for s in args.spp.split(","))
    shot_dir = Path(args.cache) / f"default_{args.size}px_ref{args.ref_spp}"
    before = _snapshot(shot_dir)
    t_render = time.perf_counter()
    record = data_gen.render_shot(data_gen.default_scene(width=args.size, height=args.size), shot_dir,
                                  spp=spp, ref_spp=args.ref_spp, methods=methods, seed=0,
                                  progress=not args.quiet)
    render_s = time.perf_counter() - t_render
    rendered = sorted(k for k, v in _snapshot(shot_dir).items() if before.get(k) != v)
    report = bench.run(shot_dir, methods, args.out, runs=args.runs, progress=not args.quiet)
    total = time.perf_counter() - t0
    write_json(Path(args.out) / "demo.json", {
        "variant": variant, "scene": "data_gen.default_scene", "size": args.size, "spp": list(spp),
        "ref_spp": args.ref_spp, "methods": methods, "cache": report_path(shot_dir), "render_seconds": render_s,
        "total_seconds": total, "rendered_now": rendered, "left_out": record.get("left_out", {}),
    })
    print(bench.markdown_table(bench.summarize(report["records"])))
    for s in report["skipped"]:
        print(f"not run: {s['method']}: {s['reason']}")
    print(f"plot: {Path(args.out) / 'error_vs_time.png'}  viewer: {Path(args.out) / 'viewer.html'}  "
          f"table: {Path(args.out) / 'results.md'}")
    print(f"demo: {variant}, {args.size}x{args.size}, spp {list(spp)}, reference {args.ref_spp} spp; "
          f"render {render_s:.1f} s ({f'{len(rendered)} file(s) rendered' if rendered else 'all cached'}), "
          f"total {total:.1f} s; {bench.one_line(report)}")
    return 0


def _snapshot(folder: Path) -> dict[str, float]:
    """EXR name -> modification time, to tell what a call rendered from what was cached."""
    return {p.name: p.stat().st_mtime_ns for p in folder.glob("*.exr")} if folder.is_dir() else {}
