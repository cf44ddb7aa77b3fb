"""A method's inference on frames, below every entry point (`api`, `sequence`, `bench`, `train`):
`prepare` validates a frame for a method and keeps what it reads; `inference_fn` is its jitted
function, compiled once per input signature with XLA's memory estimate checked first (`Compiled`);
`nonnegative` applies the output policy (`OUTPUT_POLICY`) where an image leaves the library.
"""
from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Callable

import jax
import numpy as np

from .buffers import Buffers, BuffersError
from .methods import Method, MethodError

__all__ = ["CompileInfo", "Compiled", "OUTPUT_POLICY", "available_memory", "check_finite", "inference_fn", "prepare",
           "buffers_read", "missing_optional", "nonnegative", "clamp_note", "notes", "regime"]

OUTPUT_POLICY = (
    "every denoised image leaves the library as radiance, which is never negative: a negative sample "
    "of a method's output is set to 0 and the pixels changed are counted (the API warns, the CLI writes "
    "the count into the output's header as 'jaxdenoise:negative_clamped' and into its config, bench "
    "records it as 'negative_clamped'). Only the screened-Poisson solvers produce such samples: an "
    "unconstrained least-squares solve overshoots below 0 beside strong edges (docs/guide.md)")


def nonnegative(image: Any) -> tuple[np.ndarray, int]:
    """``(image as float32 numpy with negative samples set to 0, pixels changed)``: `OUTPUT_POLICY`,
    applied where a denoised image leaves the library (the API, the CLI, bench), never inside a
    method (a method's own output, and its gradients, stay what the paper defines)."""
    image = np.asarray(image, dtype=np.float32)
    negative = image < 0
    if not negative.any():
        return image, 0
    changed = int(negative.any(axis=-1).sum()) if image.ndim >= 3 else int(negative.sum())
    return np.where(negative, np.float32(0), image), changed


def clamp_note(name: str, count: int) -> str:
    """The one-line remark on ``count`` pixels of ``name``'s output set to 0 (`OUTPUT_POLICY`)."""
    return (f"{name}: {count} pixel(s) of the output had negative radiance and were set to 0 "
            f"(the output policy: docs/guide.md, \"Outputs\")")


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
                               f"repair the input first (jaxdenoise.io.read_buffers(..., repair='zero'), CLI --repair)")


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


@dataclasses.dataclass(frozen=True)
class CompileInfo:
    """What compiling one input signature cost (`Compiled.compile`): JAX's tracing (Python: the
    method traced and lowered to StableHLO by `jax.export`, or that program read back from disk), the
    lowering of the call that runs it, XLA's compile (near 0 when the executable came from the
    persistent cache), where the executable came from (``"memory"``: compiled before in this
    process; ``"hit"`` / ``"miss"``: XLA's persistent cache, `jaxdenoise.compile_cache`; ``"off"``:
    no persistent cache), where the traced program came from (``program``: ``"hit"``, read back;
    ``"miss"``, traced now and stored; ``"off"``; ``"memory"``) and XLA's memory estimate
    (arguments + outputs + temporaries, bytes)."""

    trace_seconds: float
    lower_seconds: float
    compile_seconds: float
    cache: str
    xla_bytes: int | None
    program: str = "off"

    @property
    def seconds(self) -> float:
        return self.trace_seconds + self.lower_seconds + self.compile_seconds


class Compiled:
    """A method's jitted inference, compiled ahead of time once per input signature (tree structure,
    shapes, dtypes) so that XLA's memory estimate is known **before** the program runs: a frame whose
    program needs more than the available memory (arguments + outputs + temporaries, from
    ``compiled.memory_analysis()``) is refused with that estimate (a `MethodError`) instead of being
    killed by the operating system. ``compile(params, buffers)`` returns a `CompileInfo` (all zeros,
    ``cache="memory"``, when the signature was compiled before).

    The program is traced through `jax.export` over the flattened ``(params, buffers)`` and run as
    ``Exported.call``: the traced program (StableHLO) and the executable are both kept on disk
    (`jaxdenoise.compile_cache`), so a later process on the same signature neither traces nor
    compiles; a fresh trace and a loaded one run the same program, bit for bit."""

    def __init__(self, m: Method) -> None:
        from . import compile_cache

        compile_cache.enable()
        self.name = m.name
        self._method = m
        self._cache: dict = {}
        self._ran: set = set()

    @staticmethod
    def _key(params: Any, buffers: Any) -> tuple:
        from .compile_cache import signature

        leaves, tree = jax.tree_util.tree_flatten((params, buffers))
        return tree, signature(leaves)

    def compile(self, params: Any, buffers: Any, *, check: bool = True) -> CompileInfo:
        """Compile this input signature (once) and return what it cost; ``check=False`` returns XLA's
        estimate of a program over the available memory instead of refusing it (`tiling.plan`)."""
        key = self._key(params, buffers)
        if key in self._cache:
            return CompileInfo(0.0, 0.0, 0.0, "memory", self._cache[key][1], "memory")
        import time

        from .compile_cache import CacheCounter, exported_program, status

        m = self._method
        leaves = jax.tree_util.tree_leaves((params, buffers))
        t0 = time.perf_counter()
        exported, program = exported_program(lambda p, b: m.module.apply(p, b, m.config), f"apply:{m.name}",
                                             m.config, (params, buffers), module=m.module.__name__)
        t1 = time.perf_counter()
        lowered = jax.jit(exported.call).trace(*leaves).lower()
        t2 = time.perf_counter()
        with CacheCounter() as counter:
            exe = lowered.compile()
        t3 = time.perf_counter()
        cache = "off" if not status()["enabled"] else ("hit" if counter.hits and not counter.misses else "miss")
        ma = exe.memory_analysis()
        need = (ma.argument_size_in_bytes + ma.output_size_in_bytes + ma.temp_size_in_bytes) if ma else None
        free = available_memory()
        if check and need is not None and need > free:
            shape = getattr(buffers, "shape", None)
            raise MethodError(f"method '{self.name}': this input ({shape}) needs {need / 2**30:.1f} GiB by XLA's "
                              f"estimate (arguments + outputs + temporaries), more than the {free / 2**30:.1f} GiB "
                              f"available; denoise it in tiles under a memory budget (jaxdenoise.denoise(..., "
                              f"max_memory_mb=N), CLI --max-memory-mb N), a smaller frame or crop, or free memory")
        self._cache[key] = (exe, need)
        return CompileInfo(t1 - t0, t2 - t1, t3 - t2, cache, need, program)

    def __call__(self, params: Any, buffers: Any) -> Any:
        from .compile_cache import signature

        leaves, tree = jax.tree_util.tree_flatten((params, buffers))  # once per call: the key and the arguments
        key = (tree, signature(leaves))
        if key not in self._cache:
            self.compile(params, buffers)
        out = self._cache[key][0](*leaves)
        self._ran.add(key)
        return out

    def has_run(self, params: Any, buffers: Any) -> bool:
        """Whether this input signature's program has already run in this process (bench's warm-up
        is per program: a later frame of the same signature needs none)."""
        return self._key(params, buffers) in self._ran


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
        raise BuffersError(f"{where + ': ' if where else ''}expected a jaxdenoise.Buffers, got {type(buffers).__name__}: "
                           f"wrap the image, jd.Buffers(color=image) (HxWx3 float32 linear radiance; add albedo=, "
                           f"normal=, ... for the methods that read them), or read a file with jd.read_buffers(path)")
    buffers.check_needs(m.required(), m.name, where=where)
    used = buffers_read(m, buffers)
    check_finite(buffers, used, where=where)
    return buffers.only(used)


def buffers_read(m: Method, buffers: Buffers) -> list[str]:
    """The buffers ``m`` reads from this frame: what it needs and the frame has (what `prepare` keeps)."""
    return sorted(m.needs() & buffers.present())


def missing_optional(m: Method, buffers: Buffers) -> list[str]:
    """The optional buffers ``m`` can use that this frame lacks: it runs without them (OIDN and the
    bilateral filters on colour alone, `rae` with roughness 1, ...), which changes its result. A
    variance (``*_var``) is not counted on a frame of one sample per pixel, which cannot have one."""
    lacking = (m.needs() - m.required()) - buffers.present()
    if buffers.spp is not None and float(np.max(np.asarray(buffers.spp))) < 2:
        lacking = {f for f in lacking if not f.endswith("_var")}
    return sorted(lacking)


def notes(m: Method, buffers: Buffers, *, sequence: bool = False) -> list[str]:
    """Remarks on running ``m`` on this frame, for the API's warnings and each bench record's
    ``notes`` (one list per record): the optional buffers it runs without, and where the frame lies
    outside what its weights were trained on (`regime`). ``sequence``: the frame is part of a video
    run through the sequence driver (a recurrent method then carries its state)."""
    lacking = missing_optional(m, buffers)
    out = [f"{m.name} ran without optional buffer(s) {lacking} it can use"] if lacking else []
    return out + regime(m, buffers, sequence=sequence)


def regime(m: Method, buffers: Buffers, *, sequence: bool = False) -> list[str]:
    """Where running ``m`` here leaves the regime its configuration says it was trained in: a
    sampling rate outside ``config.train_spps``'s range (a network trained at one rate learns that
    rate's noise: docs/results/demc.md, rae.md), or a recurrent method trained on sequences
    (``config.train_frames``) run on a single frame, its state starting from zero. Methods without
    those fields (the filters, the solvers) have no trained regime."""
    out = []
    rates = getattr(m.config, "train_spps", None)
    spp = buffers.spp
    if rates and spp is not None and np.ndim(spp) == 0:
        spp, lo, hi = float(spp), min(rates), max(rates)
        if not lo <= spp <= hi:
            trained = f"{lo} spp" if lo == hi else f"{lo}-{hi} spp"
            out.append(f"{m.name} was trained at {trained}; this frame has {spp:g} spp, outside its trained rates")
    frames = getattr(m.config, "train_frames", None)
    if frames and frames > 1 and m.temporal == "causal" and not sequence:
        out.append(f"{m.name} was trained on {frames}-frame sequences; run on a single frame, its recurrent "
                   f"state starts from zero (denoise the video with the sequence driver to carry it)")
    return out
