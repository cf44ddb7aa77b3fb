"""Process-wide settings that make the library's compiled programs faster without changing a value.

One opt-in call, `keep_memory`, which the command line and `jaxdenoise.bench` make first; an API user
who wants the same speed calls it once, before the first denoise (``jaxdenoise.runtime.keep_memory()``).
It is not made behind a user's back on import: it changes how the whole process allocates memory.

**Why.** XLA:CPU allocates every buffer a compiled program needs anew on each call and frees it
afterwards. glibc's ``malloc`` serves blocks above its mmap threshold (at most 32 MiB; a 1280x720
activation of 32 float32 channels is 118 MB) with a fresh ``mmap`` and returns them with ``munmap``,
and trims the top of its heap back to the system when it is freed; so every call touches its
activations' pages for the first time again, and the kernel zero-fills each one. On this project's
2-core machine a `demc` forward pass at 1280x720 took about 200 000 page faults and 0.3-0.5 s of
kernel time per call (of 0.9-2.3 s, as fast as the machine ran), a training step of `demc` 350 000
faults (docs/results/memory_reuse/xla_flags.md and docs/training.md "Speed on this CPU" measure it).

**What.** Three ``mallopt`` settings (glibc's own tunables, also reachable as the ``MALLOC_*``
environment variables when set before a process starts): no block is served by ``mmap``
(``M_MMAP_MAX`` 0), the heap is never trimmed (``M_TRIM_THRESHOLD`` 2^31 - 1), and every thread
allocates from the one main heap (``M_ARENA_MAX`` 1; only the main heap grows without ``mmap``). Freed
buffers then stay in the process and the next call reuses them: the results are bit-identical (the
allocator decides where a buffer lives, never what is computed; tested), the cost is that the
process keeps its peak memory (the page above measures peak resident memory with and without) until
`release_memory` gives the free part back (a long-lived process calls it between jobs; bench calls it
before each method's memory measurement, so one method's kept peak does not hide the next one's).

Only glibc has these settings; elsewhere (macOS, musl) `keep_memory` does nothing and says so.
``JAXDENOISE_KEEP_MEMORY=off`` turns the CLI's and bench's call off.
"""
from __future__ import annotations

import ctypes
import os
import platform
import threading

__all__ = ["ENV", "keep_memory", "release_memory", "status"]

ENV = "JAXDENOISE_KEEP_MEMORY"
_OFF = {"off", "0", "no", "false"}
# glibc's malloc.h parameter numbers
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8
_SETTINGS = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1))
_lock = threading.Lock()
_state: dict = {"kept": None, "why": "not asked"}


def keep_memory(*, respect_env: bool = False) -> bool:
    """Keep freed memory in the process for reuse (glibc ``malloc``; see the module's docstring).

    Call it once, early (before the first compile is best: threads that allocated before it keep
    their own heaps); later calls return the first call's answer. Returns ``True`` when the settings
    are in force, ``False`` when this C library has none (the reason in `status`).
    ``respect_env=True`` (the CLI's and bench's call) first reads ``$JAXDENOISE_KEEP_MEMORY``: ``off``
    leaves the allocator as it is."""
    with _lock:
        if _state["kept"] is not None:
            return _state["kept"]
        if respect_env and os.environ.get(ENV, "").strip().lower() in _OFF:
            _state.update(kept=False, why=f"turned off by ${ENV}")
            return False
        libc, _ = platform.libc_ver()
        if libc != "glibc":
            _state.update(kept=False, why=f"C library {libc or 'unknown'!r} is not glibc; allocator unchanged")
            return False
        mallopt = ctypes.CDLL(None).mallopt
        mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
        failed = [param for param, value in _SETTINGS if mallopt(param, value) != 1]
        if failed:  # mallopt refuses only values out of range; say which, keep what was set
            _state.update(kept=False, why=f"glibc mallopt refused parameters {failed}")
            return False
        _state.update(kept=True, why="glibc malloc: no mmap, no trim, one arena")
        return True


def status() -> dict:
    """``{"kept": bool | None (not yet asked), "why": str}``, for reports."""
    return dict(_state)


def release_memory() -> bool:
    """Give the free memory the allocator holds back to the system (glibc ``malloc_trim(0)``: the
    heap's top and every free page inside it); the next call of a program faults its pages in again.
    Returns whether anything was released (``False`` on a C library without it)."""
    if platform.libc_ver()[0] != "glibc":
        return False
    trim = ctypes.CDLL(None).malloc_trim
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    return bool(trim(0))
