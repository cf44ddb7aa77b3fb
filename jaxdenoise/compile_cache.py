"""JAX's persistent compilation cache, on by default for every program the library compiles.

A second ``jaxdenoise demo``, ``bench`` or ``denoise`` on the same shapes, and a notebook re-run,
then load compiled programs from disk instead of paying XLA's compile again (tracing and lowering
still run: they are Python). One folder, shared by the API, the CLI and bench:

- ``$JAXDENOISE_CACHE_DIR`` when set (``off`` or an empty value: no cache);
- else ``$XDG_CACHE_HOME/jaxdenoise/xla``, else ``~/.cache/jaxdenoise/xla``.

`enable` is called before the library's first compile (`inference.Compiled`, the sequence driver's
per-frame programs, `train`); it changes JAX's process-wide cache setting only when the process has
none (``jax_compilation_cache_dir`` set by the user wins, and is reported as the folder in use). Entries are keyed by JAX on the program, the
jaxlib version, the device and the XLA flags, so a stale entry is never loaded; the folder may be
deleted at any time. Programs whose compile takes at least `MIN_COMPILE_SECONDS` are written
(JAX's default, 1 s, would leave out most filters and solvers, whose compiles add up); the tiny
programs of eager operations (milliseconds each, hundreds in a network's init) are looked up but
not written.

`CacheCounter` counts JAX's own cache hit / miss events around a compile, so bench can report
whether a program came from the cache.
"""
from __future__ import annotations

import os
import threading
from pathlib import Path

import jax

__all__ = ["ENV", "MIN_COMPILE_SECONDS", "CacheCounter", "cache_dir", "enable", "status"]

ENV = "JAXDENOISE_CACHE_DIR"
_OFF = {"", "off", "0", "none", "false"}
MIN_COMPILE_SECONDS = 0.1
_lock = threading.Lock()
_state: dict = {"enabled": None, "dir": None}


def cache_dir() -> Path | None:
    """The folder the library would use (``None``: turned off by ``$JAXDENOISE_CACHE_DIR``)."""
    value = os.environ.get(ENV)
    if value is not None:
        return None if value.strip().lower() in _OFF else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxdenoise" / "xla"


def enable() -> Path | None:
    """Turn the persistent cache on (once per process; later calls return the folder in use).

    Returns the folder, or ``None`` when the cache is off. A folder that cannot be created (a
    read-only home) leaves the cache off rather than failing the caller's denoise."""
    with _lock:
        if _state["enabled"] is not None:
            return _state["dir"]
        current = jax.config.jax_compilation_cache_dir
        if current:  # the user's own setting wins
            _state.update(enabled=True, dir=Path(current))
            return _state["dir"]
        folder = cache_dir()
        if folder is None:
            _state.update(enabled=False, dir=None)
            return None
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            _state.update(enabled=False, dir=None)
            return None
        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        _state.update(enabled=True, dir=folder)
        return folder


def status() -> dict:
    """``{"enabled": bool | None (not yet asked), "dir": str | None}``, for reports."""
    return {"enabled": _state["enabled"], "dir": None if _state["dir"] is None else str(_state["dir"])}


class CacheCounter:
    """``with CacheCounter() as c: ...compile...``; then ``c.hits`` / ``c.misses`` are the persistent
    cache's hit and miss events JAX recorded inside the block (this thread's and any other's: the
    library compiles on one thread at a time)."""

    _installed = False
    _counts = {"hits": 0, "misses": 0}

    @classmethod
    def _install(cls) -> None:
        if cls._installed:
            return

        def listener(event: str, **kwargs) -> None:
            if event == "/jax/compilation_cache/cache_hits":
                cls._counts["hits"] += 1
            elif event == "/jax/compilation_cache/cache_misses":
                cls._counts["misses"] += 1

        jax.monitoring.register_event_listener(listener)
        cls._installed = True

    def __enter__(self) -> "CacheCounter":
        self._install()
        self._start = dict(self._counts)
        self.hits = self.misses = 0
        return self

    def __exit__(self, *exc) -> None:
        self.hits = self._counts["hits"] - self._start["hits"]
        self.misses = self._counts["misses"] - self._start["misses"]
