"""Notebook entry points: `denoise` (one call) and `load` (a jitted inference function).

Both resolve a registered method, its parameters (explicit ``params``, a ``weights`` folder, the
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
    if meta.get("config"):
        m = Method(name=m.name, module=m.module,
                   config=checkpoint.config_from_dict(m.module.Config, meta["config"]))
    return m, jax.tree_util.tree_map(np.asarray, params)


def check_finite(buffers: Buffers, names) -> None:
    """Raise naming the buffer and the count of NaN/Inf values (methods are not fed garbage)."""
    for name in sorted(names):
        value = getattr(buffers, name)
        if value is None:
            continue
        bad = int(np.size(value) - np.isfinite(np.asarray(value, dtype=np.float32)).sum())
        if bad:
            raise BuffersError(f"buffer '{name}' has {bad} NaN/Inf value(s); repair the input first "
                               f"(jaxdenoise.io.read_buffers(..., repair='zero'))")


@functools.lru_cache(maxsize=64)
def _jitted(module, config) -> Callable:
    return jax.jit(lambda params, buffers: module.apply(params, buffers, config))


def inference_fn(m: Method) -> Callable[[Any, Buffers], Any]:
    """``fn(params, buffers) -> image``: jitted (cached per method and config) unless the method is
    foreign code (``JITTABLE = False``)."""
    if m.jittable:
        return _jitted(m.module, m.config)
    return lambda params, buffers: m.module.apply(params, buffers, m.config)


def prepare(m: Method, buffers: Buffers) -> Buffers:
    """Validate ``buffers`` for ``m`` and keep only what it reads (required + present optional ones)."""
    buffers.check_needs(m.required(), m.name)
    used = m.needs() & buffers.present()
    check_finite(buffers, used)
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


def load(method: str, path: str | os.PathLike | None = None) -> Callable[[Buffers], Any]:
    """A jitted ``fn(buffers) -> image`` with the method's parameters bound (shipped, or ``path``)."""
    m, params = resolve(method, path)
    fn = inference_fn(m)

    def infer(buffers: Buffers):
        return fn(params, prepare(m, buffers))

    infer.method = m  # type: ignore[attr-defined]
    infer.params = params  # type: ignore[attr-defined]
    return infer
