"""Notebook entry points: `denoise` (one frame or a batch), `denoise_sequence` (a video, through the
sequence driver `jaxdenoise.sequence`) and `load` (a jitted inference function with ``.sequence``).

They resolve a registered method, its parameters (explicit ``params``, a ``weights`` folder, the
shipped weights in ``jaxdenoise/weights/``, or none for methods without parameters), check the
frame carries what the method needs, and feed it nothing else.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from . import checkpoint
from .buffers import Buffers, BuffersError
from .errors import JaxdenoiseWarning
from .inference import clamp_note, inference_fn, nonnegative, notes, prepare
from .methods import Method, MethodError, get
from .tiling import infer


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
    # The structure, shapes and dtypes the method's init gives: a damaged or foreign file fails here,
    # by name, not deep inside the method. Abstract (jax.eval_shape): running a network's init only
    # to read its shapes took 14 s for demc, more than loading and compiling it.
    template = jax.eval_shape(m.init, jax.random.PRNGKey(0))
    params = checkpoint.restore_like(template, params, where=str(folder), finite=True)
    return m, jax.tree_util.tree_map(np.asarray, params)


def _registered() -> set[str]:
    from .methods import names

    return set(names())


AUTO = "auto"
# What ``method="auto"`` picks, best first (measured on the demo frame and the held-out sets:
# docs/results/demo.md, demc.md, lbf.md); a blur is never picked. Each entry is taken only when
# the frame has every buffer it requires and it can run here (OIDN's package).
PREFERENCE = ("gradnet", "demc", "lbf", "oidn", "bilateral")


def choose_method(buffers: Buffers) -> str:
    """The method ``method="auto"`` (the default of `denoise`, `denoise_sequence` and the CLI) runs
    on this frame: the first of `PREFERENCE` whose required buffers the frame holds (a G-PT frame:
    ``gradnet``; a frame with data_gen's auxiliary buffers: ``demc``; with variances and ``spp``:
    ``lbf``; colour with or without albedo/normal: ``oidn``, else the cross-``bilateral`` filter)."""
    have = buffers.present()
    for name in PREFERENCE:
        m = get(name)
        if m.required() <= have and m.requirements() is None:
            return name
    raise MethodError(f"method 'auto': no method of {list(PREFERENCE)} runs on a frame with {sorted(have)}; "
                      f"name one (jaxdenoise methods lists them and what they need), install OIDN (pip install 'jaxdenoise[oidn]'; from a clone: pip install -e '.[oidn]'), "
                      f"or render the buffers a method needs (python -m data_gen render SCENE --methods NAME)")


def denoise(buffers: Buffers, method: str = AUTO, params: Any = None, *,
            weights: str | os.PathLike | None = None, max_memory_mb: float | None = None,
            tile: int | None = None) -> np.ndarray:
    """Denoise one frame (or a batch) with a registered method (default: `choose_method`'s pick for
    the frame); returns a float32 numpy image, non-negative (`inference.OUTPUT_POLICY`: a warning
    counts the pixels set to 0).

    ``max_memory_mb``: a frame whose program XLA estimates above this many MiB is denoised in the
    largest overlapping tiles that fit (one frame; the networks only: `jaxdenoise.tiling`), like OIDN's
    ``maxMemoryMB``; ``tile``: tiles of at most this side in pixels, whatever the memory."""
    if method == AUTO and isinstance(buffers, Buffers):
        method = choose_method(buffers)
    if isinstance(method, str) and params is None and weights is None:
        prepare(get(method), buffers)  # every missing buffer named before the shipped weights load
    if params is not None:
        m = get(method) if isinstance(method, str) else method
    else:
        m, params = resolve(method, weights)
    prepared = prepare(m, buffers)
    warn_notes(m, buffers)
    return _finished(m, infer(m, params, prepared, tile=tile, max_memory_mb=max_memory_mb))


def _finished(m: Method, image: Any) -> np.ndarray:
    """``image`` under the output policy, with one warning when it changed pixels."""
    image, clamped = nonnegative(image)
    if clamped:
        warnings.warn(clamp_note(m.name, clamped), JaxdenoiseWarning, stacklevel=3)
    return image


def warn_notes(m: Method, buffers: Buffers, *, sequence: bool = False) -> None:
    """One `JaxdenoiseWarning` per remark on running ``m`` on ``buffers`` (`inference.notes`)."""
    for note in notes(m, buffers, sequence=sequence):
        warnings.warn(note, JaxdenoiseWarning, stacklevel=3)


def denoise_sequence(frames, method: str = AUTO, params: Any = None, *,
                     weights: str | os.PathLike | None = None) -> np.ndarray:
    """Denoise a video: ``frames`` is an iterable of single-frame `Buffers` in time order (or one
    `Buffers` with a leading time axis). Recurrent methods carry their state, windowed ones (LBF)
    read their neighbours, others run frame by frame (`jaxdenoise.sequence`). Returns
    ``(T, H, W, 3)`` float32, non-negative (`inference.OUTPUT_POLICY`, one warning per call)."""
    from .sequence import run_all

    frames = unstack(frames)
    if method == AUTO and frames and isinstance(frames[0], Buffers):
        method = choose_method(frames[0])
    if params is not None:
        m = get(method) if isinstance(method, str) else method
    else:
        m, params = resolve(method, weights)
    if frames and isinstance(frames[0], Buffers):
        warn_notes(m, frames[0], sequence=True)  # once per call: the first frame's
    return _finished(m, run_all(m, params, frames))


def _finished_stream(m: Method, images):
    """The frames of a sequence under the output policy, with one warning at the end of the stream."""
    clamped = 0
    for image in images:
        image, n = nonnegative(image)
        clamped += n
        yield image
    if clamped:
        warnings.warn(clamp_note(m.name, clamped), JaxdenoiseWarning, stacklevel=2)


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
    """A jitted ``fn(buffers) -> image`` with the method's parameters bound (shipped, or ``path``);
    the image is float32 numpy under the output policy, as `denoise` returns it.

    ``fn.sequence(frames)`` runs the same method and parameters over a video through the sequence
    driver (a generator of denoised frames, in order; see `denoise_sequence`; one warning at the
    end when the policy changed pixels)."""
    m, params = resolve(method, path)
    fn = inference_fn(m)

    def infer(buffers: Buffers):
        prepared = prepare(m, buffers)
        warn_notes(m, buffers)
        return _finished(m, fn(params, prepared))

    def sequence(frames):
        from .sequence import run

        frames = unstack(frames)
        if frames:
            warn_notes(m, frames[0], sequence=True)  # once per video: the first frame's
        return _finished_stream(m, run(m, params, frames))

    infer.method = m  # type: ignore[attr-defined]
    infer.params = params  # type: ignore[attr-defined]
    infer.sequence = sequence  # type: ignore[attr-defined]
    return infer
