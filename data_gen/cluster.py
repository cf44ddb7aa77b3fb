"""Rendering datasets on a Dask cluster (``python -m data_gen dataset ... --scheduler ADDRESS|local[:N]``).

Dask (``dask.distributed``, the ``cluster`` extra: ``pip install 'jaxdenoise[cluster]'``, from a clone
``pip install -e '.[cluster]'``) schedules one task per shot; this module submits and collects
(connecting is `jaxdenoise.cluster.connect`, shared with `bench --scheduler`):

- ``local[:N]`` starts a `distributed.LocalCluster` of N single-threaded worker processes (default:
  one per core) on this machine; any other value is the address of a running scheduler
  (``tcp://host:8786``), whose workers the user started (``dask scheduler`` / ``dask worker``, or a
  Kubernetes / SLURM deployment).
- Every worker renders with its own Mitsuba variant (`setup_mitsuba`, once per worker process) and
  writes through the same atomic writer as the serial path (`render_shot`): a shot is a set of
  files each written under a temporary name and renamed, so a worker that dies mid-shot leaves
  only finished files, and the task that runs again elsewhere (Dask's ``allowed-failures`` for
  dead workers, ``retries`` for exceptions) skips them. The client assembles the manifest.
- **Threads**: a task sets Dr.Jit's thread count to its worker's Dask thread count, and the local
  cluster starts its workers with XLA single-threaded per Dask thread (``XLA_FLAGS``) and
  ``OMP_NUM_THREADS`` = threads, so N workers never run more threads than they were given. Remote
  workers: start them with ``dask worker ADDRESS --nthreads T`` and the same environment (see
  docs/data_gen.md).
- **Shared storage**: the output folder is a path every worker and the client see (a network file
  system or a volume mounted at the same path); fsspec URLs are not supported.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

from jaxdenoise.cluster import EXTRA_HINT, connect, distributed_module

from .jobs import render_job

__all__ = ["connect", "run_jobs", "EXTRA_HINT"]


def _task(job: dict) -> tuple[str, dict]:
    """Render one shot on a worker (module docstring); counts its attempts in the shot folder."""
    import drjit as dr
    from distributed import get_worker

    threads = max(1, int(get_worker().state.nthreads))
    dr.set_thread_count(threads)
    folder = Path(job["dir"])
    folder.mkdir(parents=True, exist_ok=True)
    counter = folder / f".attempts-{job['run_id']}"
    attempts = int(counter.read_text()) + 1 if counter.exists() else 1
    counter.write_text(str(attempts))
    die = job.get("_die_once")
    if die and not Path(die).exists():  # test hook: this worker process dies in the middle of the shot
        Path(die).touch()
        try:
            render_job({**job, "_stop_after": 1})
        except KeyboardInterrupt:
            pass
        os._exit(1)
    name, rec = render_job(job)
    rec["attempts"] = attempts
    rec["drjit_threads"] = int(dr.thread_count())  # what the render ran with (= the worker's threads)
    counter.unlink(missing_ok=True)
    return name, rec


def run_jobs(jobs: list[dict], spec: str) -> Iterator[tuple[str, dict]]:
    """Submit one task per job to the cluster ``spec``; yield ``(name, record)`` as shots finish.
    The records carry ``attempts`` (1 when the shot rendered on its first try)."""
    distributed = distributed_module()
    client, cluster = connect(spec)
    try:
        info = client.scheduler_info(n_workers=-1) if "n_workers" in _params(client.scheduler_info) \
            else client.scheduler_info()
        workers = len(info.get("workers", {}))
        futures = client.map(_task, jobs, pure=False, retries=2, key=[f"render-{j['name']}-{j['run_id']}" for j in jobs])
        for fut in distributed.as_completed(futures):
            name, rec = fut.result()
            rec["cluster_workers"] = workers
            yield name, rec
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _params(fn) -> set[str]:
    import inspect

    try:
        return set(inspect.signature(fn).parameters)
    except (TypeError, ValueError):
        return set()
