"""The one sequence driver (docs/architecture.md "Methods": sequences): every method over a stream of frames.

`run(method, params, frames)` yields the denoised frames in order, whatever the method's kind
(`Method.temporal`, from the hooks of `jaxdenoise.methods.protocol`):

- ``"causal"`` (recurrent networks): ``state = init_state(frame 0)``, then
  ``state, out = step(params, state, frame)`` for every frame; frame t is emitted as soon as it
  arrives;
- ``"windowed"`` (LBF's 7-frame spatio-temporal filter, ``window = (back, ahead)``):
  ``prepare_frame`` runs once per frame; frame t is emitted once frame ``t + ahead`` has arrived
  (or the stream has ended) from the prepared frames ``max(0, t - back) .. min(T - 1, t + ahead)``:
  at the ends of a sequence the window is clipped, never padded with repeated frames. Only the
  frames still inside some pending window are kept;
- ``"frame"``: each frame on its own, through the same jitted inference as `jaxdenoise.denoise`.

Time and memory are O(T): no frame is denoised twice, nothing re-runs from frame 0, and the Python
loop over frames stays outside ``jit`` (each per-frame function is compiled once per shape, so T is
never unrolled into a program). Every frame is checked and reduced to what the method reads by
`jaxdenoise.inference.prepare` (frame metadata such as ``spp`` included), with its name in any error.
"""
from __future__ import annotations

import collections
import functools
from typing import Any, Callable, Iterable, Iterator, Sequence

import jax
import numpy as np

from . import compile_cache
from .inference import inference_fn, prepare
from .buffers import Buffers, BuffersError
from .methods import Method

__all__ = ["run", "run_all"]


@functools.lru_cache(maxsize=32)
def _jitted_step(module, config) -> Callable:
    return compile_cache.CachedJit(lambda params, state, buffers: module.step(params, state, buffers, config),
                                   "step", config, module=module.__name__)


@functools.lru_cache(maxsize=32)
def _jitted_prepare_frame(module, config) -> Callable:
    return compile_cache.CachedJit(lambda params, buffers: module.prepare_frame(params, buffers, config),
                                   "prepare_frame", config, module=module.__name__)


@functools.lru_cache(maxsize=256)
def _jitted_window_at(module, config, center: int) -> Callable:
    return compile_cache.CachedJit(lambda params, prepared: module.apply_window(params, prepared, center, config),
                                   f"apply_window@{center}", config, module=module.__name__)


def _jitted_window(module, config) -> Callable:
    """``(params, prepared, center)`` -> the window's output; one program per centre (a static index)."""
    return lambda params, prepared, center: _jitted_window_at(module, config, int(center))(params, prepared)


def run(m: Method, params: Any, frames: Iterable[Buffers], *,
        names: Sequence[str] | None = None) -> Iterator[np.ndarray]:
    """Yield ``m``'s denoised frames (float32 numpy ``(H, W, 3)``) in order, streaming.

    ``frames`` is any iterable of single-frame `Buffers` (a list, or a generator reading files);
    ``names`` (e.g. file names) label the frames in errors.
    """
    label = (lambda i: names[i] if names is not None and i < len(names) else f"frame {i}")

    def checked(i: int, frame: Buffers) -> Buffers:
        if not isinstance(frame, Buffers):
            raise BuffersError(f"{label(i)}: expected a jaxdenoise.Buffers, got {type(frame).__name__}")
        if np.ndim(frame.color) != 3:
            raise BuffersError(f"{label(i)}: a sequence frame must be one (H, W, 3) frame; 'color' has shape "
                               f"{np.shape(frame.color)} (stacked frames: pass them one by one)")
        return prepare(m, frame, where=label(i))

    kind = m.temporal
    if kind == "causal":
        step = _jitted_step(m.module, m.config) if m.jittable else \
            (lambda p, s, b: m.module.step(p, s, b, m.config))
        state = None
        for i, frame in enumerate(frames):
            b = checked(i, frame)
            if state is None:
                state = m.module.init_state(b, m.config)
            state, out = step(params, state, b)
            yield np.asarray(out, dtype=np.float32)
    elif kind == "windowed":
        yield from _run_windowed(m, params, frames, checked)
    else:
        fn = inference_fn(m)
        for i, frame in enumerate(frames):
            yield np.asarray(fn(params, checked(i, frame)), dtype=np.float32)


def _run_windowed(m: Method, params: Any, frames: Iterable[Buffers], checked) -> Iterator[np.ndarray]:
    back, ahead = (int(x) for x in m.module.window(m.config))
    if back < 0 or ahead < 0:
        raise ValueError(f"method '{m.name}': window() returned ({back}, {ahead}); expected two counts >= 0")
    prep = _jitted_prepare_frame(m.module, m.config) if m.jittable else \
        (lambda p, b: m.module.prepare_frame(p, b, m.config))
    win = _jitted_window(m.module, m.config) if m.jittable else \
        (lambda p, w, c: m.module.apply_window(p, w, c, m.config))
    kept: collections.deque = collections.deque()  # prepared frames first .. last arrived
    first = 0  # index of kept[0]
    t = 0  # next frame to emit

    def emit(last: int) -> np.ndarray:
        nonlocal first, t
        lo, hi = max(0, t - back), min(last, t + ahead)
        window = tuple(kept[j - first] for j in range(lo, hi + 1))
        out = np.asarray(win(params, window, t - lo), dtype=np.float32)
        t += 1
        while first < t - back:  # frames no pending window reads any more
            kept.popleft()
            first += 1
        return out

    last = -1
    for i, frame in enumerate(frames):
        kept.append(prep(params, checked(i, frame)))
        last = i
        while t + ahead <= last:
            yield emit(last)
    while t <= last:  # end of the stream: the remaining windows are clipped
        yield emit(last)


def run_all(m: Method, params: Any, frames: Iterable[Buffers], *, names: Sequence[str] | None = None) -> np.ndarray:
    """Every denoised frame of `run`, stacked ``(T, H, W, 3)``."""
    out = list(run(m, params, frames, names=names))
    if not out:
        raise BuffersError(f"method '{m.name}': the sequence has no frames")
    return np.stack(out)
