"""Error against run time: the harness behind ``jaxdenoise bench`` (DESIGN.md "Error against run time").

A data folder is walked recursively; every folder holding a ``reference.exr`` is one shot and
every other EXR in it is a noisy render of that shot (its integer ``spp`` header attribute gives
the sample count). Every chosen method runs on every render; each record holds relmse, ssim,
psnr, seconds (median of ``runs`` >= 5 timed calls after a warm-up), compile seconds (XLA
compilation, measured ahead of time and reported separately) and peak memory.

Peak memory: for jitted methods, XLA's compiled memory analysis (arguments + outputs + temporaries,
exact for the compiled program); for foreign code (OIDN) the growth of the process's resident set
from before its warm-up call to the end of the timed runs, sampled every millisecond (``memory_source`` says which).
"""
from __future__ import annotations

import dataclasses
import json
import os
import statistics
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import jax
import numpy as np

from . import metrics
from .api import inference_fn, prepare, resolve
from .buffers import Buffers
from .fsutil import atomic_path, write_json, write_text
from .io import read_buffers, read_image
from .methods import Method, MethodError

REFERENCE = "reference.exr"
SHOT_RECORD = "shot.json"  # data_gen's per-shot manifest (render timings)
MIN_RUNS = 5


@dataclasses.dataclass(frozen=True)
class Render:
    path: Path
    spp: int | None
    render_seconds: float | None


@dataclasses.dataclass(frozen=True)
class Shot:
    folder: Path
    reference: Path
    renders: tuple[Render, ...]

    @property
    def name(self) -> str:
        return self.folder.name


def discover(data_dir: str | os.PathLike) -> list[Shot]:
    """Every shot (folder with ``reference.exr``) under ``data_dir``, sorted by path.

    A render's time comes from its ``render_seconds`` header attribute or, for data_gen output
    (whose EXRs keep no timings so they stay byte-identical across runs), from the ``seconds`` of
    its entry in the shot's ``shot.json``; without either it is unknown (None).
    """
    from .io import read_header

    root = Path(data_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a folder")
    shots = []
    refs = sorted(Path(d) / REFERENCE for d, _, files in os.walk(root, followlinks=True) if REFERENCE in files)
    for ref in refs:  # os.walk with followlinks: shot folders linked into ``root`` count too
        manifest = ref.parent / SHOT_RECORD
        timings = {}
        if manifest.is_file():
            try:
                files = json.loads(manifest.read_text()).get("files", {})
                timings = {k: v.get("seconds") for k, v in files.items() if isinstance(v, dict)}
            except (json.JSONDecodeError, AttributeError) as e:
                raise ValueError(f"{manifest}: not a valid shot record ({e})") from None
        renders = []
        for p in sorted(ref.parent.glob("*.exr")):
            if p.name == REFERENCE or p.name.startswith("."):
                continue
            h = read_header(p)
            rs = h.get("render_seconds", timings.get(p.name))
            renders.append(Render(p, h.get("spp"), float(rs) if rs is not None else None))
        shots.append(Shot(ref.parent, ref, tuple(renders)))
    if not shots:
        raise FileNotFoundError(f"{root}: no shot found (a shot is a folder holding {REFERENCE} and noisy EXRs)")
    return shots


class _RssPeak:
    """Peak growth of the resident set while the block runs (sampled every 1 ms, Linux /proc)."""

    def __enter__(self):
        self.base = self.peak = self._rss()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(0.001)

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._rss())
        self.bytes = self.peak - self.base

    @staticmethod
    def _rss() -> int:
        try:
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            return 0


def _block(x):
    return jax.block_until_ready(x)


def time_method(m: Method, params: Any, buffers: Buffers, *, runs: int = MIN_RUNS,
                cache: dict | None = None) -> dict[str, Any]:
    """Run ``m`` on one frame by the protocol; returns image, seconds, compile_seconds, peak_bytes."""
    if runs < MIN_RUNS:
        raise ValueError(f"runs={runs}; the protocol needs at least {MIN_RUNS} timed runs")
    buffers = jax.device_put(prepare(m, buffers)) if m.jittable else prepare(m, buffers)
    compile_s = 0.0
    if m.jittable:
        key = (m.name, m.config, jax.tree_util.tree_structure(buffers),
               tuple(np.shape(x) for x in jax.tree_util.tree_leaves(buffers)))
        if cache is not None and key in cache:
            compiled, mem = cache[key]
        else:
            t0 = time.perf_counter()
            compiled = inference_fn(m).lower(params, buffers).compile()
            compile_s = time.perf_counter() - t0
            ma = compiled.memory_analysis()
            mem = (ma.argument_size_in_bytes + ma.output_size_in_bytes + ma.temp_size_in_bytes) if ma else None
            if cache is not None:
                cache[key] = (compiled, mem)
        fn: Callable = compiled
        source = "xla"
    else:
        fn = inference_fn(m)
        mem, source = None, "rss"
    times = []
    # The resident-set window opens before the warm-up: foreign code allocates its buffers there.
    with _RssPeak() as rss:
        out = _block(fn(params, buffers))  # warm-up
        for _ in range(runs):
            t0 = time.perf_counter()
            out = _block(fn(params, buffers))
            times.append(time.perf_counter() - t0)
    if mem is None:
        mem = rss.bytes
    return {"image": np.asarray(out, dtype=np.float32), "seconds": statistics.median(times),
            "seconds_all": times, "compile_seconds": compile_s, "peak_bytes": int(mem),
            "memory_source": source}


def score(image: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    return {"relmse": float(metrics.relmse(image, ref)), "ssim": float(metrics.ssim(image, ref)),
            "psnr": float(metrics.psnr(image, ref))}


def run(data_dir: str | os.PathLike, methods: Iterable[str], out_dir: str | os.PathLike, *,
        runs: int = MIN_RUNS, weights: dict[str, str] | None = None, progress: bool = True) -> dict:
    """Benchmark ``methods`` on every render under ``data_dir``; writes the three reports into
    ``out_dir`` and returns ``{"records": [...], "skipped": [...], "config": {...}}``."""
    from tqdm import tqdm

    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    shots = discover(data_dir)
    resolved: dict[str, tuple[Method, Any]] = {}
    skipped: list[dict] = []
    for name in methods:
        try:
            resolved[name] = resolve(name, (weights or {}).get(name))
        except MethodError as e:
            skipped.append({"method": name, "reason": str(e)})
    if not resolved:
        raise MethodError("no method can run: " + "; ".join(s["reason"] for s in skipped))
    config = {"data_dir": str(Path(data_dir).resolve()), "methods": list(methods), "runs": runs,
              "weights": weights or {}, "shots": len(shots),
              "renders": sum(len(s.renders) for s in shots),
              "method_configs": {n: dataclasses.asdict(m.config) for n, (m, _) in resolved.items()},
              "jax": jax.__version__, "device": str(jax.devices()[0]), "cpu_count": os.cpu_count()}
    records: list[dict] = []
    cache: dict = {}
    total = sum(len(s.renders) for s in shots) * len(resolved)
    bar = tqdm(total=total, desc="bench", unit="run", disable=not progress, leave=False)
    for shot in shots:
        ref = read_image(shot.reference)
        for render in shot.renders:
            buffers, _ = read_buffers(render.path)
            if buffers.shape != ref.shape[:-1]:
                raise ValueError(f"{render.path}: size {buffers.shape} differs from {shot.reference} {ref.shape[:-1]}")
            for name, (m, params) in resolved.items():
                bar.set_postfix_str(f"{shot.name}/{render.path.name} {name}")
                missing = sorted(m.required() - buffers.present())
                if missing:
                    skipped.append({"method": name, "file": str(render.path),
                                    "reason": f"frame lacks buffer(s) {missing}"})
                    bar.update(1)
                    continue
                r = time_method(m, params, buffers, runs=runs, cache=cache)
                rec = {"shot": shot.name, "file": str(render.path.relative_to(Path(data_dir))),
                       "spp": render.spp, "render_seconds": render.render_seconds, "method": name,
                       "seconds": r["seconds"], "seconds_all": r["seconds_all"],
                       "compile_seconds": r["compile_seconds"], "peak_bytes": r["peak_bytes"],
                       "memory_source": r["memory_source"], "height": int(ref.shape[0]),
                       "width": int(ref.shape[1])}
                rec.update(score(r["image"], ref))
                records.append(rec)
                bar.update(1)
    bar.close()
    config["wall_seconds"] = time.perf_counter() - t_start
    report = {"records": records, "skipped": skipped, "config": config}
    write_reports(report, out_dir)
    return report


# -- reports -----------------------------------------------------------------------------------------

def summarize(records: list[dict]) -> list[dict]:
    """One row per (method, spp): mean relmse/ssim/psnr over frames, median seconds, etc."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        groups.setdefault((r["method"], r["spp"]), []).append(r)
    order = {m: i for i, m in enumerate(dict.fromkeys(r["method"] for r in records))}
    # Resident-set growth (foreign code) shows only where the process first allocates: report the
    # method's maximum over all its frames, not over one spp's frames.
    rss_peak: dict[str, int] = {}
    for r in records:
        if r.get("memory_source") == "rss":
            rss_peak[r["method"]] = max(rss_peak.get(r["method"], 0), r["peak_bytes"])
    rows = []
    for (method, spp), rs in sorted(groups.items(), key=lambda kv: (order[kv[0][0]], kv[0][1] or 0)):
        render = [r["render_seconds"] for r in rs]
        rows.append({
            "method": method, "spp": spp, "frames": len(rs),
            "relmse": float(np.mean([r["relmse"] for r in rs])),
            "ssim": float(np.mean([r["ssim"] for r in rs])),
            "psnr": float(np.mean([r["psnr"] for r in rs])),
            "seconds": float(np.median([r["seconds"] for r in rs])),
            "compile_seconds": float(max(r["compile_seconds"] for r in rs)),
            "peak_mb": float(rss_peak.get(method, max(r["peak_bytes"] for r in rs))) / 2**20,
            "render_seconds": float(np.median(render)) if all(x is not None for x in render) else None,
        })
    return rows


def markdown_table(rows: list[dict]) -> str:
    lines = ["| method | spp | frames | RelMSE | SSIM | PSNR (dB) | time (ms, median) | compile (s) | peak MB |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['spp'] if r['spp'] is not None else '?'} | {r['frames']} | "
                     f"{r['relmse']:.4g} | {r['ssim']:.4f} | {r['psnr']:.2f} | {1e3 * r['seconds']:.2f} | "
                     f"{r['compile_seconds']:.2f} | {r['peak_mb']:.1f} |")
    return "\n".join(lines)


def load_report(out_dir: str | os.PathLike) -> dict:
    """Read back what `write_reports` wrote (to re-render tables and plots without re-running)."""
    out_dir = Path(out_dir)
    res = json.loads((out_dir / "results.json").read_text())
    return {"records": res["records"], "skipped": res["skipped"],
            "config": json.loads((out_dir / "config.json").read_text())}


def write_reports(report: dict, out_dir: str | os.PathLike) -> None:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = summarize(report["records"])
    write_json(out_dir / "results.json", {"records": report["records"], "summary": rows,
                                          "skipped": report["skipped"]})
    write_json(out_dir / "config.json", report["config"])
    cfg = report["config"]
    md = ["# Error against run time\n",
          f"Data: `{cfg['data_dir']}` ({cfg['shots']} shot(s), {cfg['renders']} render(s)); "
          f"device: {cfg['device']}, {cfg['cpu_count']} cores; jax {cfg['jax']}.",
          f"RelMSE = mean((x - ref)^2 / (ref^2 + 0.01)); SSIM and PSNR on clip(x, 0, 1)^(1/2.2); "
          f"time = median of {cfg['runs']} runs after a warm-up, compile time separate "
          f"(see docs/metrics.md).\n", markdown_table(rows), ""]
    if report["skipped"]:
        md.append("Not run:\n")
        seen = set()
        for s in report["skipped"]:
            line = f"- `{s['method']}`: {s['reason']}"
            if line not in seen:
                seen.add(line)
                md.append(line)
    write_text(out_dir / "results.md", "\n".join(md) + "\n")
    plot(rows, out_dir / "error_vs_time.png")


def plot(rows: list[dict], path: str | os.PathLike) -> Path:
    """Log-log RelMSE against seconds, one point per method and spp (joined per method).

    When every render carries its ``render_seconds``, the x axis is the total time (render +
    denoise) and the raw Monte Carlo input draws the equal-time curve; otherwise it is the
    denoising time alone and the curve is left out (the legend says so).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    total_time = all(r["render_seconds"] is not None for r in rows)
    fig, ax = plt.subplots(figsize=(6.5, 4.5), dpi=120)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    floor = 1e-6  # the raw input's denoise time is ~0; keep it on a log axis
    for method in methods:
        rs = [r for r in rows if r["method"] == method]
        xs = [max(floor, r["seconds"] + (r["render_seconds"] if total_time else 0.0)) for r in rs]
        ys = [max(r["relmse"], 1e-12) for r in rs]
        if method == "input" and total_time and len(rs) > 1:
            ax.plot(xs, ys, "k--", marker="o", label="raw Monte Carlo (equal time)")
        else:
            ax.plot(xs, ys, marker="o", label=method)
        for x, y, r in zip(xs, ys, rs):
            if r["spp"] is not None and len(rs) > 1:
                ax.annotate(f"{r['spp']}", (x, y), textcoords="offset points", xytext=(3, 3), fontsize=6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for axis in (ax.xaxis, ax.yaxis):  # 1-2-5 ticks with plain labels: readable over short and long spans
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("render + denoise time (s)" if total_time else "denoise time (s, median)")
    ax.set_ylabel("RelMSE")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("error against run time" + ("" if total_time else " (render times unknown)"), fontsize=9)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def one_line(report: dict) -> str:
    rows = summarize(report["records"])
    if not rows:
        return "bench: no records"
    best = min(rows, key=lambda r: r["relmse"])
    return (f"bench: {len(report['records'])} record(s), {report['config']['shots']} shot(s), "
            f"{len({r['method'] for r in rows})} method(s) in {report['config']['wall_seconds']:.1f} s; "
            f"lowest RelMSE {best['relmse']:.4g} by {best['method']} at {best['spp']} spp"
            + (f"; {len(report['skipped'])} skipped" if report["skipped"] else ""))
