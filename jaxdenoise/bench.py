"""Error against run time: the harness behind ``jaxdenoise bench`` (docs/architecture.md "Error against run time").

A data folder is read by `jaxdenoise.data` (shots, renders with their header ``spp``, and
``frame_XXXX/`` sequences). Every chosen method runs on every render (its output is kept, as half
floats, for ``viewer.html``: `jaxdenoise.viewer`); each record holds relmse,
ssim, psnr, seconds (median of ``runs`` >= 5 timed calls after a warm-up call of the program, which a
later frame of the same signature does not repeat), compile seconds (XLA
compilation, measured ahead of time and reported separately) and memory. Sequences go through the
one sequence driver (`jaxdenoise.sequence`): recurrent methods carry their state, windowed ones
(LBF) read their neighbours, others run frame by frame; each frame gets a record, and each
(sequence, render, method) a temporal record with the temporal error (`metrics.temporal_error`)
and the mean RelMSE / SSIM over its frames.

Render time, per method (the equal-time axis): a method is charged the passes that made what it
read (`charged_render_seconds`). data_gen renders a frame in one pass (the colour and every
auxiliary buffer come out of it together, so every method pays that pass whole); a gradient frame's
pass makes ``dx``, ``dy`` beside them (with ``--primal gpt`` the colour is G-PT's primal), and a
buffer-only render of the same frame is timed beside it (``buffer_seconds``, `jaxdenoise.data`). A
method that reads ``dx``/``dy``, or the colour of a frame whose colour is the G-PT primal, is
charged the gradient frame's time; any other method the buffer-only render's. Each record also
keeps the whole frame's time (``frame_render_seconds``) and the raw input's error on that frame
(``input_relmse``), so every table row shows the error it started from and flags a method that
made the image worse.

Output policy (`inference.OUTPUT_POLICY`): every image is scored as the user gets it, negative
samples set to 0; each record counts the pixels changed (``negative_clamped``), its notes say so
(`CLAMP_NOTE`) and each summary row sums them. The policy is applied on the host after the timed calls
(outside the measured time).

Memory, one quantity per column (docs/metrics.md):

- ``rss_peak_bytes``: the growth of the process's resident set from just before the warm-up call
  to the end of the timed runs, sampled every millisecond, for every method alike (JAX or foreign);
- ``xla_bytes``: XLA's compiled memory analysis of a jitted method's program (arguments + outputs
  + temporaries), exact for that program; ``None`` for foreign code and for sequences (the driver
  runs several programs).
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

from . import metrics, runtime
from .api import resolve
from .inference import buffers_read, inference_fn, nonnegative, notes, prepare
from .buffers import EMISSION_FIELD, GRADIENT_FIELDS, Buffers
from .data import Render, Shot, discover, sequences
from .fsutil import atomic_path, report_path, write_json, write_text
from .io import read_buffers, read_image
from .methods import Method, MethodError
from .viewer import ImageStore, write_viewer
from .errors import JaxdenoiseError

MIN_RUNS = 5
# what the gradient pass of a frame makes (dx, dy and the emission they leave out)
GRADIENT_BUFFERS = frozenset(GRADIENT_FIELDS) | {EMISSION_FIELD}


def charged_render_seconds(render: Render, read: Iterable[str]) -> float | None:
    """The render time a method that read the buffers ``read`` of ``render`` is charged (module
    docstring); None when the frame's time is unknown."""
    if render.render_seconds is None:
        return None
    read = set(read)
    if render.buffer_seconds is None or read & GRADIENT_BUFFERS or (render.primal == "gpt" and "color" in read):
        return render.render_seconds
    return render.buffer_seconds


class _RssPeak:
    """Peak growth of the resident set while the block runs (sampled every 1 ms, Linux /proc). Free
    memory the allocator keeps (`runtime.keep_memory`) is given back first, so a method's growth is its
    own and not hidden by an earlier method's kept peak."""

    def __enter__(self):
        runtime.release_memory()
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


CLAMP_NOTE = "negative output radiance set to 0 (output policy; pixels counted in negative_clamped)"


def _block(x):
    return jax.block_until_ready(x)


def time_method(m: Method, params: Any, buffers: Buffers, *, runs: int = MIN_RUNS,
                where: str | None = None) -> dict[str, Any]:
    """Run ``m`` on one frame by the protocol; returns image, seconds, compile_seconds,
    rss_peak_bytes, xla_bytes (module docstring)."""
    if runs < MIN_RUNS:
        raise JaxdenoiseError(f"runs={runs}; the protocol needs at least {MIN_RUNS} timed runs")
    buffers = prepare(m, buffers, where=where)
    buffers = jax.device_put(buffers) if m.jittable else buffers
    fn: Callable = inference_fn(m)
    info = fn.compile(params, buffers) if m.jittable else None
    # The warm-up is per program: one that already ran in this process (an earlier frame of the same
    # signature) has paid its first-call costs, and its warm-up would only repeat a timed run.
    warm = m.jittable and fn.has_run(params, buffers)
    times = []
    # The resident-set window opens before the warm-up: foreign code allocates its buffers there.
    with _RssPeak() as rss:
        if not warm:
            out = _block(fn(params, buffers))  # warm-up
        for _ in range(runs):
            t0 = time.perf_counter()
            out = _block(fn(params, buffers))
            times.append(time.perf_counter() - t0)
    image, clamped = nonnegative(out)  # what the user gets (inference.OUTPUT_POLICY); not timed
    return {"image": image, "negative_clamped": clamped, "seconds": statistics.median(times),
            "seconds_all": times, **_compile_fields(info), "rss_peak_bytes": int(rss.bytes),
            "xla_bytes": None if info is None or info.xla_bytes is None else int(info.xla_bytes)}


def _compile_fields(info) -> dict[str, Any]:
    """A record's compile columns from an `inference.CompileInfo` (``None``: foreign code, nothing
    compiled): XLA's compile (``compile_seconds``, near 0 on a persistent-cache hit), tracing and
    lowering apart, and where the executable came from (``compile_cache``: hit, miss, memory, off) and
    the traced program (``program_cache``: the same values, `jaxdenoise.compile_cache`)."""
    if info is None:
        return {"compile_seconds": 0.0, "trace_seconds": None, "lower_seconds": None, "compile_cache": None,
                "program_cache": None}
    return {"compile_seconds": info.compile_seconds, "trace_seconds": info.trace_seconds,
            "lower_seconds": info.lower_seconds, "compile_cache": info.cache, "program_cache": info.program}


def time_sequence(m: Method, params: Any, frames: list[Buffers], *, runs: int = MIN_RUNS,
                  names: list[str] | None = None) -> dict[str, Any]:
    """Run ``m`` over a whole sequence through the sequence driver by the protocol: one warm-up pass
    (compiles every per-frame program), then ``runs`` timed passes. ``seconds`` is the median pass
    divided by the number of frames (the per-frame cost in a stream); ``compile_seconds`` is the
    warm-up pass minus the median pass (the one-off part)."""
    from .sequence import run_all

    if runs < MIN_RUNS:
        raise JaxdenoiseError(f"runs={runs}; the protocol needs at least {MIN_RUNS} timed runs")
    t_len = len(frames)
    times = []
    with _RssPeak() as rss:
        t0 = time.perf_counter()
        out = run_all(m, params, frames, names=names)  # warm-up (numpy out: every frame finished)
        warm = time.perf_counter() - t0
        for _ in range(runs):
            t0 = time.perf_counter()
            out = run_all(m, params, frames, names=names)
            times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {**_finished_frames(out), "seconds": med / t_len, "seconds_all": [t / t_len for t in times],
            "compile_seconds": max(0.0, warm - med), "rss_peak_bytes": int(rss.bytes), "xla_bytes": None}


def score(image: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    return {"relmse": float(metrics.relmse(image, ref)), "ssim": float(metrics.ssim(image, ref)),
            "psnr": float(metrics.psnr(image, ref))}


def _score_task(render: str, reference: str, methods: list[str], weights: dict) -> list[dict]:
    """One single-frame render scored by every method on a Dask worker (no timing)."""
    ref = read_image(reference)
    buffers, _ = read_buffers(render)
    out = []
    for name in methods:
        try:
            m, params = resolve(name, weights.get(name))
            missing = sorted(m.required() - buffers.present())
            if missing:
                out.append({"method": name, "skipped": f"frame lacks buffer(s) {missing}"})
                continue
            image, clamped = nonnegative(inference_fn(m)(params, prepare(m, buffers, where=render)))
        except MethodError as e:
            out.append({"method": name, "skipped": str(e)})
            continue
        out.append({"method": name, "negative_clamped": clamped, **score(image, ref)})
    return out


def _distributed_scores(singles: list[Shot], methods: list[str], weights: dict, spec: str, progress: bool) -> dict:
    """{(render path, method): scores or {"skipped": why}} computed on the Dask cluster ``spec``
    (``local[:N]`` or an address; every worker must see the data folder and the weights)."""
    from tqdm import tqdm

    from .cluster import connect, distributed_module

    distributed = distributed_module()
    client, cluster = connect(spec)
    jobs = [(str(r.path), str(s.reference)) for s in singles for r in s.renders]
    out = {}
    try:
        futures = client.map(_score_task, [j[0] for j in jobs], [j[1] for j in jobs], methods=methods,
                             weights=weights, pure=False, retries=1)
        index = {f.key: j for f, j in zip(futures, jobs)}
        for f in tqdm(distributed.as_completed(futures), total=len(futures), desc="bench (scoring on Dask)",
                      disable=not progress, leave=False):
            render = index[f.key][0]
            for rec in f.result():
                out[(render, rec["method"])] = rec
        out["__workers__"] = len(client.scheduler_info().get("workers", {}))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return out


def run(data_dir: str | os.PathLike, methods: Iterable[str], out_dir: str | os.PathLike, *,
        runs: int = MIN_RUNS, weights: dict[str, str] | None = None, progress: bool = True,
        scheduler: str | None = None, timing: bool = True) -> dict:
    """Benchmark ``methods`` on every render under ``data_dir``; writes the three reports into
    ``out_dir`` and returns ``{"records": [...], "temporal": [...], "skipped": [...], "config": {...}}``.

    ``scheduler`` (``local[:N]`` or a Dask scheduler address, the cluster extra) computes the quality
    columns of the single-frame renders on the cluster's workers, in parallel. Timings are never taken
    concurrently with other work: after the distributed scoring (and after a local cluster has shut
    down) the client times every method on every frame alone, as without a scheduler; ``timing=False``
    leaves the time columns empty (quality only) and the plot out. Sequences are run on the client.
    """
    from tqdm import tqdm

    t_start = time.perf_counter()
    # the library's fast path is what bench measures: the allocator keeps freed memory (the CLI has
    # made this call already; an API caller gets it here; $JAXDENOISE_KEEP_MEMORY=off leaves it out)
    runtime.keep_memory(respect_env=True)
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    shots = discover(data_dir)
    seqs, singles = sequences(shots)
    resolved: dict[str, tuple[Method, Any]] = {}
    skipped: list[dict] = []
    for name in methods:
        try:
            resolved[name] = resolve(name, (weights or {}).get(name))
        except MethodError as e:
            skipped.append({"method": name, "reason": str(e)})
    if not resolved:
        raise MethodError("no method can run: " + "; ".join(s["reason"] for s in skipped))
    out_dir.mkdir(parents=True, exist_ok=True)
    dist = _distributed_scores(singles, list(resolved), {k: str(v) for k, v in (weights or {}).items()},
                               scheduler, progress) if scheduler is not None else None
    config = {"data_dir": report_path(data_dir, out_dir), "methods": list(methods), "runs": runs,
              "scheduler": scheduler, "dask_workers": dist.pop("__workers__") if dist else None,
              "timing": ("on the client alone, after the distributed scoring" if scheduler else "on this machine")
              if timing else "none (quality only)",
              "weights": {k: report_path(v, out_dir) for k, v in (weights or {}).items()}, "shots": len(shots),
              "sequences": len(seqs), "renders": sum(len(s.renders) for s in shots),
              "method_configs": {n: dataclasses.asdict(m.config) for n, (m, _) in resolved.items()},
              "jax": jax.__version__, "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
              "compile_cache": _cache_status(), "allocator": runtime.status()}
    records: list[dict] = []
    temporal: list[dict] = []
    store = ImageStore()  # every image shown by viewer.html (float16, base64)
    total = (sum(len(s.renders) for s in singles) + sum(len(q.render_names()) for q in seqs)) * len(resolved)
    bar = tqdm(total=total, desc="bench", unit="run", disable=not progress, leave=False)
    for shot in singles:
        ref = read_image(shot.reference)
        for render in shot.renders:
            buffers, _ = read_buffers(render.path)
            if buffers.shape != ref.shape[:-1]:
                raise JaxdenoiseError(f"{render.path}: size {buffers.shape} differs from {shot.reference} {ref.shape[:-1]}")
            for name, (m, params) in resolved.items():
                bar.set_postfix_str(f"{shot.name}/{render.path.name} {name}")
                missing = sorted(m.required() - buffers.present())
                if missing:
                    skipped.append({"method": name, "file": str(render.path.relative_to(data_dir)),
                                    "reason": f"frame lacks buffer(s) {missing}"})
                    bar.update(1)
                    continue
                d = dist.get((str(render.path), name)) if dist is not None else None
                if d is not None and "skipped" in d:
                    skipped.append({"method": name, "file": str(render.path.relative_to(data_dir)), "reason": d["skipped"]})
                    bar.update(1)
                    continue
                try:
                    r = time_method(m, params, buffers, runs=runs, where=str(render.path)) if timing else \
                        _untimed(m, params, buffers, str(render.path), d)
                except MethodError as e:  # e.g. the frame needs more memory than there is (XLA's estimate)
                    skipped.append({"method": name, "file": str(render.path.relative_to(data_dir)), "reason": str(e)})
                    bar.update(1)
                    continue
                clamped = r["negative_clamped"]
                rec = _record(shot, render, name, r, r["image"], ref, data_dir, buffers, buffers_read(m, buffers),
                              negative_clamped=clamped,
                              notes=notes(m, buffers) + ([CLAMP_NOTE] if clamped else []))
                if d is not None:  # the quality columns as the workers computed them
                    rec.update({k: d[k] for k in ("relmse", "ssim", "psnr")})
                rec["reference_image"] = store.add(f"ref:{rec['shot']}:{shot.reference.name}", ref)
                if r["image"] is not None:
                    rec["image_id"] = store.add(f"{rec['file']}|{name}", r["image"])
                records.append(rec)
                bar.update(1)
    for seq in seqs:
        refs = [read_image(s.reference) for s in seq.shots]
        for rname in seq.render_names():
            renders = [next(r for r in s.renders if r.path.name == rname) for s in seq.shots]
            frames = [read_buffers(r.path)[0] for r in renders]
            for r, b, ref in zip(renders, frames, refs):
                if b.shape != ref.shape[:-1]:
                    raise JaxdenoiseError(f"{r.path}: size {b.shape} differs from its reference {ref.shape[:-1]}")
            for name, (m, params) in resolved.items():
                bar.set_postfix_str(f"{seq.name}/{rname} {name}")
                lacking = {str(r.path.relative_to(data_dir)): sorted(m.required() - b.present())
                           for r, b in zip(renders, frames) if m.required() - b.present()}
                if lacking:
                    first = next(iter(lacking))
                    skipped.append({"method": name, "file": first,
                                    "reason": f"sequence frame lacks buffer(s) {lacking[first]}"})
                    bar.update(1)
                    continue
                r = time_sequence(m, params, frames, runs=runs, names=[str(x.path) for x in renders]) if timing \
                    else _untimed_sequence(m, params, frames, [str(x.path) for x in renders])
                recs = [_record(s, x, name, r, img, ref, data_dir, b, buffers_read(m, b),
                                sequence=report_path(seq.folder, data_dir), frame=s.frame, negative_clamped=c,
                                notes=notes(m, b, sequence=True) + ([CLAMP_NOTE] if c else []))
                        for s, x, img, ref, b, c in zip(seq.shots, renders, r["images"], refs, frames,
                                                        r["negative_clamped"])]
                for rec, img, ref, s in zip(recs, r["images"], refs, seq.shots):
                    rec["reference_image"] = store.add(f"ref:{rec['sequence']}/{s.name}", ref)
                    rec["image_id"] = store.add(f"{rec['file']}|{name}", img)
                records.extend(recs)
                temporal.append({
                    "sequence": report_path(seq.folder, data_dir), "render": rname, "method": name,
                    "spp": renders[0].spp, "frames": len(frames), "kind": m.temporal,
                    "temporal_error": float(metrics.temporal_error(r["images"], np.stack(refs))) if len(frames) > 1 else None,
                    "relmse": float(np.mean([x["relmse"] for x in recs])),
                    "ssim": float(np.mean([x["ssim"] for x in recs])),
                    "seconds_per_frame": r["seconds"]})
                bar.update(1)
    bar.close()
    config["wall_seconds"] = time.perf_counter() - t_start
    report = {"records": records, "temporal": temporal, "skipped": skipped, "config": config}
    write_reports(report, out_dir)
    write_viewer(report, store, out_dir)
    return report


def _untimed(m: Method, params: Any, buffers: Buffers, where: str, scored: dict | None) -> dict:
    """The record fields of an untimed run (``timing=False``): the image (unless the workers scored
    it already), no seconds, no memory."""
    image, clamped = None, None
    if scored is None:
        image, clamped = nonnegative(inference_fn(m)(params, prepare(m, buffers, where=where)))
    else:
        clamped = scored.get("negative_clamped")
    return {"image": image, "negative_clamped": clamped, "seconds": None, "seconds_all": [], "compile_seconds": None, "rss_peak_bytes": None,
            "xla_bytes": None}


def _finished_frames(images) -> dict:
    """A sequence's frames under the output policy (`inference.OUTPUT_POLICY`), each frame's count."""
    finished = [nonnegative(x) for x in images]
    return {"images": np.stack([x[0] for x in finished]), "negative_clamped": [x[1] for x in finished]}


def _untimed_sequence(m: Method, params: Any, frames: list[Buffers], names: list[str]) -> dict:
    """`time_sequence`'s fields for an untimed run (``timing=False``): one pass, no seconds, no memory."""
    from .sequence import run_all

    return {**_finished_frames(run_all(m, params, frames, names=names)), "seconds": None, "seconds_all": [], "compile_seconds": None, "rss_peak_bytes": None, "xla_bytes": None}


def _record(shot: Shot, render: Render, method: str, r: dict, image: np.ndarray, ref: np.ndarray, data_dir: Path,
            buffers: Buffers, read: list[str], **extra: Any) -> dict:
    rec = {"shot": shot.name, "file": str(render.path.relative_to(data_dir)), "spp": render.spp,
           "render_seconds": charged_render_seconds(render, read), "frame_render_seconds": render.render_seconds,
           "method": method, "seconds": r["seconds"],
           "seconds_all": r["seconds_all"], "compile_seconds": r["compile_seconds"],
           **{k: r[k] for k in ("trace_seconds", "lower_seconds", "compile_cache", "program_cache") if k in r},
           "rss_peak_bytes": r["rss_peak_bytes"], "xla_bytes": r["xla_bytes"],
           "height": int(ref.shape[0]), "width": int(ref.shape[1]), "buffers": read,
           "input_relmse": float(metrics.relmse(np.asarray(buffers.color, np.float32), ref)), **extra}
    if render.sampling:
        rec["sampling"] = render.sampling
    if image is not None:
        rec.update(score(image, ref))
    return rec


# -- reports -----------------------------------------------------------------------------------------

def summarize(records: list[dict]) -> list[dict]:
    """One row per (method, spp): mean relmse/ssim/psnr over frames, median seconds, memory.

    ``rss_peak_mb`` is the method's largest resident-set growth over **all** its frames (growth
    shows only where the process first allocates, so a per-spp maximum would depend on the order
    of the frames); ``xla_mb`` is the largest compiled estimate among the row's frames (None when no
    frame of the row has one)."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        groups.setdefault((series(r), r["spp"]), []).append(r)
    order = {m: i for i, m in enumerate(dict.fromkeys(series(r) for r in records))}
    rss_peak: dict[str, int] = {}
    for r in records:
        if r.get("rss_peak_bytes") is not None:
            rss_peak[r["method"]] = max(rss_peak.get(r["method"], 0), int(r["rss_peak_bytes"]))
    timed = lambda rs, k: [r[k] for r in rs if r.get(k) is not None]  # None: an untimed (quality-only) run
    rows = []
    for (label, spp), rs in sorted(groups.items(), key=lambda kv: (order[kv[0][0]], kv[0][1] or 0)):
        method = rs[0]["method"]
        render = [r["render_seconds"] for r in rs]
        xla = [r["xla_bytes"] for r in rs if r.get("xla_bytes") is not None]
        rows.append({
            "method": label, "spp": spp, "frames": len(rs),
            "relmse": float(np.mean([r["relmse"] for r in rs])),
            "ssim": float(np.mean([r["ssim"] for r in rs])),
            "psnr": float(np.mean([r["psnr"] for r in rs])),
            "seconds": float(np.median(timed(rs, "seconds"))) if timed(rs, "seconds") else None,
            "compile_seconds": float(max(timed(rs, "compile_seconds"))) if timed(rs, "compile_seconds") else None,
            "compile_cache": "+".join(sorted({r["compile_cache"] for r in rs if r.get("compile_cache")})) or None,
            "rss_peak_mb": rss_peak[method] / 2**20 if method in rss_peak else None,
            "xla_mb": max(xla) / 2**20 if xla else None,
            "render_seconds": float(np.median(render)) if all(x is not None for x in render) else None,
            "input_relmse": float(np.mean([r["input_relmse"] for r in rs])),
            "buffers": sorted({b for r in rs for b in r.get("buffers", [])}),
            "negative_clamped": sum(int(r.get("negative_clamped") or 0) for r in rs),
            "notes": _row_notes(rs),
        })
    return rows


def series(record: dict) -> str:
    """A record's row label: the method, and for an adaptively sampled frame (data_gen's
    ``--adaptive``, whose render time includes the map's) the sampling, e.g. ``demc (adaptive
    relvar)``: adaptive and uniform frames are separate rows and separate curves."""
    return record["method"] + (f" (adaptive {record['sampling']})" if record.get("sampling") else "")


def _row_notes(rs: list[dict]) -> list[str]:
    """Each distinct remark of a row's records, with how many of its frames it concerns (a row can
    mix frames that had an optional buffer with frames that had not)."""
    counts: dict[str, int] = {}
    for r in rs:
        for n in r.get("notes", []):
            counts[n] = counts.get(n, 0) + 1
    return [f"{n} ({k} of {len(rs)} frame(s))" for n, k in counts.items()]


def _cache_mark(cache: str | None) -> str:
    """The compile column's mark of a program loaded from the persistent cache (rows of reports
    written before the cache was recorded carry none)."""
    return {"hit": " (cached)", "hit+memory": " (cached)"}.get(cache or "", " (partly cached)" if cache and "hit" in cache else "")


def markdown_table(rows: list[dict]) -> str:
    lines = ["| method | spp | frames | RelMSE | input RelMSE | vs input | SSIM | PSNR (dB) | time (ms, median) "
             "| compile (s) | RSS peak MB | XLA MB | notes |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    fmt = lambda v, f, scale=1.0: "-" if v is None else format(scale * v, f)
    for r in rows:
        ratio = r["relmse"] / r["input_relmse"] if r["input_relmse"] > 0 else float("inf")
        vs = f"**{ratio:.3g}x: worse**" if ratio > 1 else f"{ratio:.3g}x"
        lines.append(f"| {r['method']} | {r['spp'] if r['spp'] is not None else '?'} | {r['frames']} | "
                     f"{r['relmse']:.4g} | {r['input_relmse']:.4g} | {vs} | "
                     f"{r['ssim']:.4f} | {r['psnr']:.2f} | {fmt(r['seconds'], '.2f', 1e3)} | "
                     f"{fmt(r['compile_seconds'], '.2f')}{_cache_mark(r.get('compile_cache'))} | {fmt(r['rss_peak_mb'], '.1f')} | {fmt(r.get('xla_mb'), '.1f')} | "
                     f"{'; '.join(r.get('notes', []))} |")
    return "\n".join(lines)


def temporal_table(temporal: list[dict]) -> str:
    """Markdown table of the per-sequence records (temporal error beside the per-frame errors)."""
    lines = ["| sequence | render | spp | method | kind | frames | temporal error | RelMSE (mean) | SSIM (mean) "
             "| time per frame (ms) |", "|---|---|---:|---|---|---:|---:|---:|---:|---:|"]
    for t in temporal:
        te = f"{t['temporal_error']:.4g}" if t["temporal_error"] is not None else "-"
        lines.append(f"| {t['sequence']} | {t['render']} | {t['spp']} | {t['method']} | {t['kind']} | "
                     f"{t['frames']} | {te} | {t['relmse']:.4g} | {t['ssim']:.4f} | "
                     f"{'-' if t['seconds_per_frame'] is None else format(1e3 * t['seconds_per_frame'], '.1f')} |")
    return "\n".join(lines)


def load_report(out_dir: str | os.PathLike) -> dict:
    """Read back what `write_reports` wrote (to re-render tables and plots without re-running)."""
    out_dir = Path(out_dir)
    res = json.loads((out_dir / "results.json").read_text())
    return {"records": res["records"], "temporal": res.get("temporal", []), "skipped": res["skipped"],
            "config": json.loads((out_dir / "config.json").read_text())}


def report_markdown(report: dict) -> str:
    """``results.md`` of a report (`load_report`'s dict, or `run`'s): the summary table, the
    sequences and what was not run, read from the records alone (``scripts/results.py`` checks the
    committed reports against it)."""
    rows = summarize(report["records"])
    temporal = report.get("temporal", [])
    cfg = report["config"]
    md = ["# Error against run time\n",
          f"Data: `{cfg['data_dir']}` (relative to this report; {cfg['shots']} shot(s), "
          f"{cfg.get('sequences', 0)} sequence(s), {cfg['renders']} render(s)); "
          f"device: {cfg['device']}, {cfg['cpu_count']} cores; jax {cfg['jax']}.",
          f"RelMSE = mean((x - ref)^2 / (ref^2 + 0.01)); input RelMSE = the raw input's on the same frames, "
          f"vs input = their ratio (**worse**: the method made the image worse); SSIM and PSNR on clip(x, 0, 1)^(1/2.2); "
          f"time = median of {cfg['runs']} runs after a warm-up ({cfg.get('timing', 'on this machine')}), compile "
          f"time separate; RSS peak = the "
          f"method's largest resident-set growth over its frames, XLA = compiled program footprint "
          f"(see docs/metrics.md).\n", markdown_table(rows), ""]
    if temporal:
        md += ["## Sequences\n", "Every method through the sequence driver (kind: causal = recurrent "
               "state, windowed = reads neighbouring frames, frame = frame by frame); temporal error = "
               "`metrics.temporal_error` over consecutive frames.\n", temporal_table(temporal), ""]
    if report["skipped"]:
        md.append("Not run:\n")
        seen = set()
        for s in report["skipped"]:
            line = f"- `{s['method']}`: {s['reason']}"
            if line not in seen:
                seen.add(line)
                md.append(line)
    if any(r["seconds"] is None for r in rows):
        md.append("\nNo `error_vs_time.png`: this run took no timings (quality only).")
    return "\n".join(md) + "\n"


def write_reports(report: dict, out_dir: str | os.PathLike) -> None:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = summarize(report["records"])
    write_json(out_dir / "results.json", {"records": report["records"], "summary": rows,
                                          "temporal": report.get("temporal", []), "skipped": report["skipped"]})
    write_json(out_dir / "config.json", report["config"])
    write_text(out_dir / "results.md", report_markdown(report))
    if all(r["seconds"] is not None for r in rows):
        plot(rows, out_dir / "error_vs_time.png")


def plot(rows: list[dict], path: str | os.PathLike) -> Path:
    """Log-log RelMSE against seconds, one point per method and spp (joined per method).

    When every render carries its ``render_seconds``, the x axis is the total time (render +
    denoise) and the raw Monte Carlo input draws the equal-time curve; otherwise it is the
    denoising time alone and the curve is left out (the legend says so).
    """
    # A bare Figure with the Agg canvas: no pyplot state, and no switch of the process's backend
    # (matplotlib.use would break plotting in the user's notebook).
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    total_time = all(r["render_seconds"] is not None for r in rows)
    fig = Figure(figsize=(8.0, 4.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    methods = list(dict.fromkeys(r["method"] for r in rows))
    style = plot_styles(methods)
    floor = 1e-6  # the raw input's denoise time is ~0; keep it on a log axis
    dropped = []
    for method in methods:
        # A non-finite error (a method's output overflowed) cannot sit on a log axis; the table
        # keeps it, the legend says the point is left out.
        rs = [r for r in rows if r["method"] == method and np.isfinite(r["relmse"])]
        dropped += [f"{method} @ {r['spp']}" for r in rows if r["method"] == method and not np.isfinite(r["relmse"])]
        if not rs:
            continue
        xs = [max(floor, r["seconds"] + (r["render_seconds"] if total_time else 0.0)) for r in rs]
        ys = [max(r["relmse"], 1e-12) for r in rs]
        if method == "input" and total_time and len(rs) > 1:
            ax.plot(xs, ys, "k--", marker="o", label="raw Monte Carlo (equal time)")
        else:
            ax.plot(xs, ys, label=method, **style[method])
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
    if dropped:
        ax.plot([], [], " ", label="not finite (table only): " + ", ".join(dropped))
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)  # outside the data
    ax.set_title("error against run time" + ("" if total_time else " (render times unknown)"), fontsize=9)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    return path


MARKERS = ("o", "s", "^", "D", "v", "P", "X")


def plot_styles(methods: list[str]) -> dict[str, dict]:
    """A colour and a marker per method, no two methods alike: 20 colours (tab20, the dark shade of
    each hue first) against 7 markers, whose pairs repeat only after 140 methods."""
    from matplotlib import colormaps

    cmap = colormaps["tab20"]
    order = [2 * i for i in range(10)] + [2 * i + 1 for i in range(10)]
    return {m: {"color": cmap(order[i % 20]), "marker": MARKERS[i % len(MARKERS)]} for i, m in enumerate(methods)}


def one_line(report: dict) -> str:
    rows = summarize(report["records"])
    if not rows:
        return "bench: no records"
    best = min(rows, key=lambda r: r["relmse"])
    return (f"bench: {len(report['records'])} record(s), {report['config']['shots']} shot(s), "
            f"{len({r['method'] for r in rows})} method(s) in {report['config']['wall_seconds']:.1f} s; "
            f"lowest RelMSE {best['relmse']:.4g} by {best['method']} at {best['spp']} spp"
            + (f"; scored on Dask {report['config']['scheduler']} ({report['config']['dask_workers']} worker(s)), "
               f"timed {report['config']['timing']}" if report["config"].get("scheduler") else "")
            + _cache_line(report)
            + (f"; {len(report['skipped'])} skipped" if report["skipped"] else ""))


def _cache_status() -> dict:
    """The compile cache's state for the report's config, its folder under the home written ``~/...``
    (reports never carry this machine's absolute paths)."""
    from . import compile_cache

    compile_cache.enable()
    status = compile_cache.status()
    if status["dir"]:
        status["dir"] = report_path(status["dir"])
    return status


def _cache_line(report: dict) -> str:
    """``; compile cache: H of N programs loaded from DIR (T of N traced programs read back)`` where the
    records say (`compile_cache`, `program_cache`)."""
    seen = [r["compile_cache"] for r in report["records"] if r.get("compile_cache") in ("hit", "miss")]
    if not seen:
        return ""
    where = (report["config"].get("compile_cache") or {}).get("dir")
    traced = [r["program_cache"] for r in report["records"] if r.get("program_cache") in ("hit", "miss")]
    read = f" ({traced.count('hit')} of {len(traced)} traced program(s) read back)" if traced else ""
    return f"; compile cache: {seen.count('hit')} of {len(seen)} program(s) loaded from {where}{read}"