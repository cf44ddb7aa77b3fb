"""Connecting to Dask (the ``cluster`` extra: ``pip install 'jaxdenoise[cluster]'``, from a clone
``pip install -e '.[cluster]'``), the one place that does: `bench --scheduler` here and
`python -m data_gen dataset --scheduler` (`data_gen.cluster`).

``local[:N]`` starts a `distributed.LocalCluster` of N single-threaded worker processes (default:
one per core) whose XLA runs single-threaded (``XLA_FLAGS``, ``OMP_NUM_THREADS``), so N workers never
use more than N cores; any other value is the address of a running scheduler (``tcp://host:8786``).
"""
from __future__ import annotations

import os
from .errors import JaxdenoiseError, MissingDependency

__all__ = ["connect", "distributed_module", "EXTRA_HINT"]

EXTRA_HINT = "pip install 'jaxdenoise[cluster]' (from a clone: pip install -e '.[cluster]')"
_WORKER_ENV = {"OMP_NUM_THREADS": "1", "JAX_PLATFORMS": "cpu",
               "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}


def distributed_module():
    """``dask.distributed``, or an ImportError naming the extra to install."""
    try:
        import distributed
    except ImportError as e:
        raise MissingDependency(f"--scheduler needs Dask, which is not installed ({e}); install the cluster extra: "
                          f"{EXTRA_HINT}") from None
    return distributed


def connect(spec: str):
    """(client, local cluster or None) for ``local``, ``local:N`` or a scheduler address."""
    distributed = distributed_module()
    if spec == "local" or spec.startswith("local:"):
        n = spec.partition(":")[2]
        try:
            workers = int(n) if n else (os.cpu_count() or 1)
        except ValueError:
            raise JaxdenoiseError(f"--scheduler {spec!r}: expected local or local:N with N an integer") from None
        if workers < 1:
            raise JaxdenoiseError(f"--scheduler {spec!r}: N must be >= 1")
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40, env=dict(_WORKER_ENV))
        return distributed.Client(cluster), cluster
    return distributed.Client(spec), None
