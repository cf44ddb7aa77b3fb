"""Notebook entry points: `denoise` (one frame or a batch), `denoise_sequence` (a video, through the
sequence driver `jaxdenoise.sequence`) and `load` (a jitted inference function with ``.sequence``).

They resolve a registered method, its parameters (explicit ``params``, a ``weights`` folder, the
shipped weights in ``jaxdenoise/weights/``, or none for methods without parameters), check the
frame carries what the method needs, and feed it nothing else.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from . import checkpoint
from .buffers import Buffers, BuffersError
from .methods import Method, MethodError, get


def resolve(method: str | Method, weights: str | os.PathLike | None = None) -> tuple[Method, Any]:
    """(method with the config its weights were trained with, params).

    ``weights`` is a folder with ``params.npz`` + ``config.json``; without it, the shipped weights
    of a trainable method are used; methods without parameters get ``init``'s empty pytree.
    """
    m = get(method) if isinstance(method, str) else method
    why = m.requirements()
    if why:
        raise MethodError(why)
    folder = Path(weights) if weights is not None else m.weights_dir
    if folder is None:
        if m.trainable:
            raise MethodError(f"method '{m.name}' is trainable but names no shipped weights; pass weights=")
        return m, m.init(jax.random.PRNGKey(0))
    if not (folder / checkpoint.PARAMS_FILE).is_file():
        raise MethodError(
            f"method '{m.name}': no weights at {folder} (expected {checkpoint.PARAMS_FILE}); "
            f"train them with `jaxdenoise train {m.name} --data DIR --out RUN_DIR` and pass --weights RUN_DIR")
    params, meta = checkpoint.load(folder)
    trained_for = meta.get("method")
    if trained_for is not None and trained_for != m.name:
        # a variant of the same module (lbf / lbf-nlm) may load its sibling's weights; nothing else
        if trained_for not in _registered() or get(trained_for).module is not m.module:
            raise checkpoint.WeightsError(f"{folder}: weights are for method '{trained_for}', not '{m.name}'")
    if meta.get("config"):
        try:
            config = checkpoint.config_from_dict(m.module.Config, meta["config"])
        except (TypeError, ValueError) as e:
            raise checkpoint.WeightsError(f"{folder}: config.json does not fit method '{m.name}' ({e})") from None
        m = Method(name=m.name, module=m.module, config=config)
    # The structure, shapes and values the method's init gives: a damaged or foreign file fails here,
    # by name, not deep inside the method.
    template = m.init(jax.random.PRNGKey(0))
    params = checkpoint.restore_like(template, params, where=str(folder), finite=True)
    return m, jax.tree_util.tree_map(np.asarray, params)


def _registered() -> set[str]:
    from .methods import names

    return set(names())


def check_finite(buffers: Buffers, names, *, where: str | None = None) -> None:
    """Raise naming the buffer (and ``where``, e.g. the file) and the count of NaN/Inf values
    (methods are not fed garbage)."""
    for name in sorted(names):
        value = getattr(buffers, name)
        if value is None:
            continue
        bad = int(np.size(value) - np.isfinite(np.asarray(value, dtype=np.float32)).sum())
        if bad:
            raise BuffersError(f"{where + ': ' if where else ''}buffer '{name}' has {bad} NaN/Inf value(s); "
                               f"repair the input first (jaxdenoise.io.read_buffers(..., repair='zero'))")


def available_memory() -> int:
    """Bytes this process may still allocate: the kernel's MemAvailable (Linux), else physical memory."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


class Compiled:
    """A method's jitted inference, compiled ahead of time once per input signature (tree structure,
    shapes, dtypes) so that XLA's memory estimate is known **before** the program runs: a frame whose
    program needs more than the available memory (arguments + outputs + temporaries, from
    ``compiled.memory_analysis()``) is refused with that estimate (a `MethodError`) instead of being
    killed by the operating system. ``compile(params, buffers)`` returns ``(compile seconds, XLA
    bytes)`` (0 seconds when the signature was compiled before)."""

    def __init__(self, m: Method) -> None:
        self.name = m.name
        self._jit = jax.jit(lambda params, buffers: m.module.apply(params, buffers, m.config))
        self._cache: dict = {}

    @staticmethod
    def _key(params: Any, buffers: Any) -> tuple:
        leaves, tree = jax.tree_util.tree_flatten((params, buffers))
        return tree, tuple((np.shape(x), np.dtype(getattr(x, "dtype", type(x))).str) for x in leaves)

    def compile(self, params: Any, buffers: Any) -> tuple[float, int | None]:
        key = self._key(params, buffers)
        if key in self._cache:
            return 0.0, self._cache[key][1]
        import time

        t0 = time.perf_counter()
        exe = self._jit.lower(params, buffers).compile()
        seconds = time.perf_counter() - t0
        ma = exe.memory_analysis()
        need = (ma.argument_size_in_bytes + ma.output_size_in_bytes + ma.temp_size_in_bytes) if ma else None
        free = available_memory()
        if need is not None and need > free:
            shape = getattr(buffers, "shape", None)
            raise MethodError(f"method '{self.name}': this input ({shape}) needs {need / 2**30:.1f} GiB by XLA's "
                              f"estimate (arguments + outputs + temporaries), more than the {free / 2**30:.1f} GiB "
                              f"available; denoise a smaller frame or crop, or free memory")
        self._cache[key] = (exe, need)
        return seconds, need

    def __call__(self, params: Any, buffers: Any) -> Any:
        key = self._key(params, buffers)
        if key not in self._cache:
            self.compile(params, buffers)
        return self._cache[key][0](params, buffers)


@functools.lru_cache(maxsize=64)
def _compiled(module, config, name) -> Compiled:
    return Compiled(Method(name=name, module=module, config=config))


def inference_fn(m: Method) -> Callable[[Any, Buffers], Any]:
    """``fn(params, buffers) -> image``: a `Compiled` (cached per method and config: compiled once per
    input signature, memory checked first) unless the method is foreign code (``JITTABLE = False``)."""
    if m.jittable:
        return _compiled(m.module, m.config, m.name)
    return lambda params, buffers: m.module.apply(params, buffers, m.config)


def prepare(m: Method, buffers: Buffers, *, where: str | None = None) -> Buffers:
    """Validate ``buffers`` for ``m`` and keep only what it reads (required + present optional ones)
    and the frame's metadata (``spp``; `Buffers.only` never drops it). ``where`` (e.g. the file
    name) goes into every error."""
    if not isinstance(buffers, Buffers):
        raise BuffersError(f"{where + ': ' if where else ''}expected a jaxdenoise.Buffers, got {type(buffers).__name__}")
    buffers.check_needs(m.required(), m.name, where=where)
    used = m.needs() & buffers.present()
    check_finite(buffers, used, where=where)
    return buffers.only(used)


def denoise(buffers: Buffers, method: str = "gaussian", params: Any = None, *,
            weights: str | os.PathLike | None = None) -> np.ndarray:
    """Denoise one frame (or a batch) with a registered method; returns a float32 numpy image."""
    if params is not None:
        m = get(method) if isinstance(method, str) else method
    else:
        m, params = resolve(method, weights)
    out = inference_fn(m)(params, prepare(m, buffers))
    return np.asarray(out, dtype=np.float32)


def denoise_sequence(frames, method: str = "gaussian", params: Any = None, *,
                     weights: str | os.PathLike | None = None) -> np.ndarray:
    """Denoise a video: ``frames`` is an iterable of single-frame `Buffers` in time order (or one
    `Buffers` with a leading time axis). Recurrent methods carry their state, windowed ones (LBF)
    read their neighbours, others run frame by frame (`jaxdenoise.sequence`). Returns
    ``(T, H, W, 3)`` float32."""
    from .sequence import run_all

    if params is not None:
        m = get(method) if isinstance(method, str) else method
    else:
        m, params = resolve(method, weights)
    return run_all(m, params, unstack(frames))


def unstack(frames) -> list[Buffers]:
    """A list of single frames from a list of frames or one `Buffers` with a leading time axis."""
    if isinstance(frames, Buffers):
        if np.ndim(frames.color) != 4:
            raise BuffersError(f"a sequence as one Buffers needs a leading time axis: (T, H, W, 3); "
                               f"'color' has shape {np.shape(frames.color)}")
        t_len = np.shape(frames.color)[0]

        def frame(t: int) -> Buffers:
            d = frames.to_dict()
            spp = d.pop("spp", None)
            if spp is not None and np.ndim(spp) > 0:
                spp = spp[t]
            return Buffers(**{k: v[t] for k, v in d.items()}, spp=spp)

        return [frame(t) for t in range(t_len)]
    return list(frames)


def load(method: str, path: str | os.PathLike | None = None) -> Callable[[Buffers], Any]:
    """A jitted ``fn(buffers) -> image`` with the method's parameters bound (shipped, or ``path``).

    ``fn.sequence(frames)`` runs the same method and parameters over a video through the sequence
    driver (a generator of denoised frames, in order; see `denoise_sequence`)."""
    m, params = resolve(method, path)
    fn = inference_fn(m)

    def infer(buffers: Buffers):
        return fn(params, prepare(m, buffers))

    def sequence(frames):
        from .sequence import run

        return run(m, params, unstack(frames))

    infer.method = m  # type: ignore[attr-defined]
    infer.params = params  # type: ignore[attr-defined]
    infer.sequence = sequence  # type: ignore[attr-defined]
    return infer
