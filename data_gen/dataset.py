"""Datasets: one folder per scene (``scene_0000/``...) in the bench layout plus a top-level
``manifest.json`` (scene, seed, settings, spp list, files, checksums, render seconds, reference noise),
of procedural scenes (a family) or of one split of the scene library (`data_gen.library`).

Resumable: each scene's files are skipped when finished (`render_shot`), and the manifest is rewritten
atomically after every scene. Scenes render in parallel with ``workers`` processes (spawned: Dr.Jit
state must not be forked), or on a Dask cluster with ``scheduler`` (`data_gen.cluster`: one task per
scene, the client assembles the manifest).
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path
from typing import Iterable, Sequence

from jaxdenoise.errors import JaxdenoiseError

from .jobs import render_job

MANIFEST = "manifest.json"


def generate_dataset(family: str | None, count: int | None, out: str | os.PathLike, *, width: int | None = None,
                     height: int | None = None, spp: Sequence[int] = (4,), instances: int = 1,
                     ref_spp: int = 1024, seed: int = 0, start: int = 0, workers: int = 1, max_depth: int = 8,
                     methods: Iterable[str] | None = None, buffers: Iterable[str] | None = None,
                     progress: bool = True, samples_per_pass: int = 1 << 20, command: str | None = None,
                     note: str | None = None, scheduler: str | None = None, frames: int = 0,
                     shift: str | None = None, primal: str = "base", gradient_emission: str = "separate",
                     library: str | None = None,
                     _stop_after: int | None = None,
                     _die_once: str | None = None) -> dict:
    """Render ``count`` procedural scenes of ``family`` (scene k uses seed ``seed + start + k`` and
    folder ``scene_{start + k:04d}``) into ``out``; returns the manifest. ``width`` x ``height``:
    default 128 x ``width``.

    ``library`` (a split of the scene library: ``train``, ``val`` or ``eval``; then ``family`` is
    None) renders that split's scenes instead, in split-file order: scene k of the split goes to
    ``scene_{k:04d}`` with seed ``seed + k``; ``count`` (None = the rest of the split) and ``start``
    select a slice. Each library scene renders at its own size unless ``width`` / ``height`` are
    given (one alone keeps the scene's aspect ratio), its fly-throughs follow its own camera (``split.json``), and its record names it
    (``library_scene``, ``split``; ``scene`` = ``library:<name>@<digest>``, so an edited scene is
    re-rendered on resume instead of skipped). ``scheduler`` (``local``,
    ``local:N`` or a Dask scheduler address) renders one Dask task per scene instead of local
    ``workers`` (`data_gen.cluster`); the output is the same files. ``frames > 0`` renders each
    scene as a camera fly-through of that many frames (`data_gen.sequences.render_sequence`:
    ``scene_XXXX/frame_XXXX/``, every frame with ``instances`` noisy renders per spp and its own
    reference). ``shift``/``primal``/``gradient_emission``: the gradient frames' shift mapping, colour and
    directly seen emission (`render_shot`)."""
    import json

    from jaxdenoise.fsutil import remove_stale_temporaries, write_json

    from .scenes import ALL_FAMILIES

    names: list[str | None]
    if library is not None:
        from .library import scene_names

        if family is not None:
            raise JaxdenoiseError(f"give either a family ({family!r}) or a library split ({library!r}), not both")
        split = scene_names(library)  # raises for an unknown split, naming the splits
        if not isinstance(start, int) or not 0 <= start < len(split):
            raise JaxdenoiseError(f"start: library split {library!r} has {len(split)} scenes "
                                  f"(indices 0..{len(split) - 1}), got start={start!r}")
        count = len(split) - start if count is None else count
        if not isinstance(count, int) or count < 1 or start + count > len(split):
            raise JaxdenoiseError(f"count: library split {library!r} has {len(split)} scenes {split}; "
                                  f"start={start} + count={count!r} runs past its end")
        names = split[start:start + count]
    else:
        if family not in ALL_FAMILIES:
            raise JaxdenoiseError(f"family must be one of {list(ALL_FAMILIES)}, got {family!r} "
                                  "(or give library= a split of the scene library)")
        if not isinstance(count, int) or count < 1:
            raise JaxdenoiseError(f"count must be an int >= 1, got {count!r}")
        names = [None] * count
        width = 128 if width is None else width
    if not isinstance(workers, int) or workers < 1:
        raise JaxdenoiseError(f"workers must be an int >= 1, got {workers!r}")
    if scheduler is not None and workers != 1:
        raise JaxdenoiseError("give either workers (local processes) or scheduler (a Dask cluster), not both")
    height = width if height is None and library is None else height
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out)  # a manifest temporary of a killed run
    mpath = out / MANIFEST
    manifest = json.loads(mpath.read_text()) if mpath.exists() else {}
    manifest.setdefault("scenes", {})
    manifest.setdefault("runs", [])
    run = {"family": family, "count": count, "start": start, "seed": seed, "width": width, "height": height,
           "spp": list(spp), "instances": instances, "ref_spp": ref_spp, "max_depth": max_depth,
           "methods": list(methods) if methods is not None else None,
           "buffers": list(buffers) if buffers is not None else None, "command": command, "note": note,
           "scheduler": scheduler, "frames": int(frames), "shift": shift, "primal": primal,
           "gradient_emission": gradient_emission, "library": library}
    run_id = f"{os.getpid()}-{time.time_ns()}"
    jobs = []
    for k, lib_scene in enumerate(names):
        idx = start + k
        name = f"scene_{idx:04d}"
        jobs.append({"name": name, "dir": os.fspath(out / name), "family": family, "library": lib_scene,
                     "scene_seed": seed + idx,
                     "width": width, "height": height, "spp": list(spp), "instances": instances,
                     "ref_spp": ref_spp, "methods": list(methods) if methods is not None else None,
                     "buffers": list(buffers) if buffers is not None else None, "max_depth": max_depth,
                     "progress": progress and workers == 1 and scheduler is None,
                     "samples_per_pass": samples_per_pass, "_stop_after": _stop_after, "run_id": run_id,
                     "frames": int(frames), "shift": shift, "primal": primal, "gradient_emission": gradient_emission,
                     "_die_once": _die_once})
    run["status"] = "running"
    manifest["runs"].append(run)  # recorded before rendering, so an interrupted run is listed too
    write_json(mpath, manifest)
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), unit="scene", desc=f"dataset {out.name}", file=sys.stderr)

    def done(name: str, rec: dict) -> None:
        manifest["scenes"][name] = rec
        manifest["total_render_seconds"] = float(sum(r.get("render_seconds", 0.0) for r in manifest["scenes"].values()))
        write_json(mpath, manifest)
        if bar is not None:
            bar.update(1)

    try:
        if scheduler is not None:
            from .cluster import run_jobs

            for name, rec in run_jobs(jobs, scheduler):
                run["workers"] = rec.pop("cluster_workers")
                run["retries"] = run.get("retries", 0) + rec.pop("attempts") - 1
                run["drjit_threads"] = max(run.get("drjit_threads", 0), rec.pop("drjit_threads"))
                done(name, rec)
        elif workers == 1:
            for job in jobs:
                done(*render_job(job))
        else:
            ctx = mp.get_context("spawn")
            with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as ex:
                futs = [ex.submit(render_job, j) for j in jobs]
                for f in cf.as_completed(futs):
                    done(*f.result())
    finally:
        if bar is not None:
            bar.close()
    run["wall_seconds"] = time.perf_counter() - t0
    run["status"] = "finished"
    manifest["scenes"] = dict(sorted(manifest["scenes"].items()))
    write_json(mpath, manifest)
    return manifest


def dataset_size_bytes(out: str | os.PathLike) -> int:
    return sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file())
