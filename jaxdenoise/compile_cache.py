"""JAX's persistent compilation cache, on by default for every program the library compiles.

A second ``jaxdenoise demo``, ``bench`` or ``denoise`` on the same shapes, and a notebook re-run,
then load compiled programs from disk instead of paying XLA's compile again. One folder, shared by
the API, the CLI and bench:

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

**Traced programs.** XLA's cache skips the compile, not JAX's tracing and lowering, which are Python
and for the filters cost more than the compile itself (the demo's second run spent about 11 of its
34 s tracing programs whose executables it then loaded). A method's inference program
(`jaxdenoise.inference.Compiled`) and the sequence driver's per-frame programs (`CachedJit`) are
therefore traced through `jax.export` (`exported_program`) and kept in the same folder as
``jaxdenoise-program-<key>.bin`` (the serialized StableHLO; `store_program` / `load_program`); a
later process on the same signature deserializes it instead of tracing. The key
(`program_key`) holds everything a trace depends on: the method, its config, the tree structure,
shapes and dtypes of its arguments (parameters included: weights are arguments, not constants), the
digest of the library's source files (any edit makes new keys), the jax / jaxlib versions, the
backend and the JAX settings that change a trace. Both calls, fresh or loaded, run the same program
(``Exported.call``), so their outputs are bit-identical (tested); a file that cannot be read is
ignored and replaced. Only the library's own modules' programs are kept: a method registered from a
user's module (`jaxdenoise.methods.register`) is traced in every process, since the digest cannot see
edits to it. What the key cannot see either is code changed at run time (a monkeypatched module
attribute read while tracing); turn the cache off (``JAXDENOISE_CACHE_DIR=off``) for such
experiments, as one would clear the in-process compile cache.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import threading
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

__all__ = ["ENV", "MIN_COMPILE_SECONDS", "CacheCounter", "CachedJit", "cache_dir", "enable", "status",
           "program_key", "load_program", "store_program", "exported_program", "signature"]

ENV = "JAXDENOISE_CACHE_DIR"
_OFF = {"", "off", "0", "none", "false"}
MIN_COMPILE_SECONDS = 0.1
_lock = threading.Lock()
_state: dict = {"enabled": None, "dir": None}
PROGRAM_FORMAT = 1  # bump when the key or the file layout changes
# JAX settings that change what a trace produces (the others change how XLA compiles it, which
# XLA's own cache key covers).
_TRACE_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_rank_promotion",
                   "jax_numpy_dtype_promotion", "jax_default_prng_impl")


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


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """SHA-256 over the library's Python sources (relative path and bytes of every ``.py`` file)."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()


def _leaf_signature(x: Any) -> list:
    if isinstance(x, (bool, int, float, complex)):  # a Python scalar: traced weakly typed
        return [type(x).__name__]
    return [list(np.shape(x)), np.dtype(x.dtype).str, bool(getattr(x, "weak_type", False))]


def program_key(name: str, config: Any, tree: Any, leaves: list, *, module: str) -> str | None:
    """The file key of the traced program ``name`` (e.g. a method's ``apply``) of ``module`` with
    ``config`` for these arguments (``tree``, ``leaves``: the flattened arguments); ``None`` when the
    cache is off, or when ``module`` is not part of this library: a method registered from the
    user's own module is traced in every process, since the key's source digest cannot see edits
    to that module."""
    if enable() is None or not module.startswith(__package__ + "."):
        return None
    import jaxlib

    parts = {"format": PROGRAM_FORMAT, "module": module, "name": name, "config": repr(config), "tree": str(tree),
             "leaves": [_leaf_signature(x) for x in leaves], "source": _source_digest(),
             "jax": jax.__version__, "jaxlib": jaxlib.__version__, "backend": jax.default_backend(),
             "settings": {k: str(getattr(jax.config, k, None)) for k in _TRACE_SETTINGS}}
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


def _program_path(key: str) -> Path:
    return Path(_state["dir"]) / f"jaxdenoise-program-{key}.bin"


def load_program(key: str | None):
    """The `jax.export.Exported` stored under ``key``, or ``None`` (no key, no file, or a file that
    does not deserialize: it is then ignored and overwritten by the next store)."""
    if key is None:
        return None
    path = _program_path(key)
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        return jax.export.deserialize(bytearray(data))
    except Exception:  # a truncated or foreign file: trace again
        return None


def store_program(key: str | None, exported) -> bool:
    """Write ``exported`` under ``key`` (temporary name, then rename); False when it could not be
    (no key, a read-only folder, or no serializer: jax.export needs the ``flatbuffers`` package)."""
    if key is None:
        return False
    from .fsutil import atomic_path

    try:
        data = exported.serialize()
    except Exception:  # no flatbuffers, or an output pytree jax.export cannot serialize
        return False
    try:
        with atomic_path(_program_path(key)) as tmp:
            tmp.write_bytes(data)
    except OSError:
        return False
    return True


def exported_program(fn: Callable, name: str, config: Any, args: tuple, *, module: str) -> tuple[Any, str]:
    """The traced program of ``fn(*args)``, taking the flattened ``args`` (`jax.export.Exported`),
    and where it came from: ``"hit"`` (read back), ``"miss"`` (traced now and stored) or ``"off"``
    (traced now, not stored: the cache is off, the module is not this library's, or the program
    could not be written). ``module``, ``name`` and ``config`` say what ``fn`` is (with the
    arguments' signature, the program's key, `program_key`); ``fn`` must be a function of ``args``
    alone, everything else fixed by them."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    key = program_key(name, config, tree, leaves, module=module)
    exported = load_program(key)
    if exported is not None:
        return exported, "hit"
    flat = jax.jit(lambda *xs: fn(*jax.tree_util.tree_unflatten(tree, xs)))
    exported = jax.export.export(flat)(*leaves)
    return exported, ("miss" if store_program(key, exported) else "off")


def signature(leaves: list) -> tuple:
    """Shapes and dtypes of flattened arguments: what one compiled program is specialised to."""
    return tuple((np.shape(x), np.dtype(getattr(x, "dtype", type(x))).str) for x in leaves)


class CachedJit:
    """``jax.jit(fn)`` whose programs come from `exported_program` (read back, or traced and stored)
    and are compiled once per argument signature, in JAX's persistent cache like every program.
    ``origins`` lists, in compile order, where each signature's traced program came from."""

    def __init__(self, fn: Callable, name: str, config: Any, *, module: str) -> None:
        enable()
        self._fn, self._name, self._config, self._module = fn, name, config, module
        self._exes: dict = {}
        self.origins: list[str] = []

    def __call__(self, *args: Any) -> Any:
        leaves, tree = jax.tree_util.tree_flatten(args)
        sig = (tree, signature(leaves))
        exe = self._exes.get(sig)
        if exe is None:
            exported, origin = exported_program(self._fn, self._name, self._config, args, module=self._module)
            exe = self._exes[sig] = jax.jit(exported.call).trace(*leaves).lower().compile()
            self.origins.append(origin)
        return exe(*leaves)
