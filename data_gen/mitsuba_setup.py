"""Choosing a working Mitsuba 3 variant (LLVM when a usable libLLVM exists, else ``scalar_rgb``).

Dr.Jit's LLVM backend loads ``libLLVM`` at run time from ``DRJIT_LIBLLVM_PATH``. LLVM 15 and older
crash or fail with Dr.Jit 1.x, so only 16 and newer are tried (newest first). The variable must be
set before the first ``mi.set_variant`` of an LLVM variant, which is why everything in ``data_gen``
goes through `setup_mitsuba` instead of calling ``mi.set_variant`` directly.
"""
from __future__ import annotations

import glob
import os
import re
import sys
from jaxdenoise.errors import JaxdenoiseError

_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib", "/usr/local/lib")
_MIN_LLVM = 16
_CHOSEN: str | None = None
_WARNED = False


def _llvm_major(path: str) -> int | None:
    m = re.search(r"libLLVM[-.](?:so\.)?(\d+)", os.path.basename(path))
    if m is None:
        # /usr/lib/llvm-19/lib/libLLVM.so
        m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def llvm_candidates() -> list[str]:
    """Existing libLLVM shared objects of version >= 16, newest first (``DRJIT_LIBLLVM_PATH`` first)."""
    found: list[tuple[int, str]] = []
    for d in _LIB_DIRS:
        for p in glob.glob(os.path.join(d, "libLLVM-*.so")) + glob.glob(os.path.join(d, "libLLVM.so.*")):
            v = _llvm_major(p)
            if v is not None and v >= _MIN_LLVM:
                found.append((v, p))
    for p in glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"):
        v = _llvm_major(p)
        if v is not None and v >= _MIN_LLVM and not p.endswith(".a"):
            found.append((v, p))
    found.sort(key=lambda t: -t[0])
    out: list[str] = []
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        v = _llvm_major(env)
        if v is None or v >= _MIN_LLVM:
            out.append(env)
    for _, p in found:
        if p not in out:
            out.append(p)
    return out


def _works(variant: str) -> bool:
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)
    scene = mi.load_dict({"type": "scene", "s": {"type": "sphere"},
                          "sensor": {"type": "perspective",
                                     "film": {"type": "hdrfilm", "width": 2, "height": 2}}})
    if variant.startswith("scalar"):
        return scene is not None
    x = dr.arange(mi.Float, 4) * 2.0
    dr.eval(x)
    return float(dr.sum(x)[0] if hasattr(dr.sum(x), "__getitem__") else dr.sum(x)) == 12.0


def setup_mitsuba(prefer: str = "llvm_ad_rgb") -> str:
    """Set (once) and return a working Mitsuba variant, preferring ``prefer``.

    For an LLVM variant, ``DRJIT_LIBLLVM_PATH`` is pointed at the newest libLLVM >= 16 found (an
    existing setting is honoured unless it names LLVM <= 15). If none works, falls back to
    ``scalar_rgb`` and prints one message saying what was tried and how to fix it. Idempotent: a
    second call returns the variant chosen by the first.
    """
    global _CHOSEN, _WARNED
    import mitsuba as mi

    if _CHOSEN is not None:
        if mi.variant() != _CHOSEN:
            mi.set_variant(_CHOSEN)
        return _CHOSEN
    if prefer not in mi.variants():
        raise JaxdenoiseError(f"setup_mitsuba: prefer={prefer!r} is not a compiled Mitsuba variant; "
                         f"available: {mi.variants()}")
    tried: list[str] = []
    if prefer.startswith("llvm"):
        cands = llvm_candidates()
        for path in cands:
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            try:
                if _works(prefer):
                    _CHOSEN = prefer
                    return prefer
                tried.append(f"{path} (test render gave a wrong result)")
            except Exception as exc:  # noqa: BLE001 - any failure means "this LLVM does not work"
                tried.append(f"{path} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})")
        if not cands:
            tried.append("no libLLVM >= 16 in " + ", ".join(_LIB_DIRS + ("/usr/lib/llvm-*/lib",)))
    else:
        try:
            if _works(prefer):
                _CHOSEN = prefer
                return prefer
        except Exception as exc:  # noqa: BLE001
            tried.append(f"{prefer} ({type(exc).__name__}: {exc})")
    fallback = "scalar_rgb"
    _works(fallback)
    _CHOSEN = fallback
    if not _WARNED:
        _WARNED = True
        print(f"data_gen: Mitsuba variant {prefer!r} is unavailable (tried: {'; '.join(tried)}); "
              f"falling back to the slow 'scalar_rgb'. Fix: install LLVM >= 16 (apt-get install "
              f"libllvm19) or set DRJIT_LIBLLVM_PATH to a libLLVM-16+ .so.", file=sys.stderr)
    return fallback


def is_vectorized() -> bool:
    import mitsuba as mi

    return not mi.variant().startswith("scalar")


class RenderTimer:
    """Wall seconds of a render with Dr.Jit's one-off kernel compilation taken out (docs/architecture.md
    "Error against run time": render time excludes one-off compilation, so equal-time curves are true).

    Use as ``with RenderTimer() as t: ...``; afterwards ``t.seconds`` is the wall time minus the
    LLVM back-end time of every kernel compiled inside the block (Dr.Jit's kernel history,
    ``backend_time``, which is zero for a kernel found in its in-memory or on-disk cache) and
    ``t.compile_seconds`` that compilation time. Dr.Jit's per-launch code generation
    (``codegen_time``) is paid on every render, so it stays in ``seconds``. The history costs about
    1-2 % of a 64-spp 128x128 render (measured). On ``scalar_rgb`` nothing is compiled and the two
    are the wall time and 0.
    """

    def __enter__(self) -> "RenderTimer":
        import time

        self.seconds = self.compile_seconds = 0.0
        self._dr = None
        if is_vectorized():
            import drjit as dr

            self._dr = dr
            self._flag = dr.flag(dr.JitFlag.KernelHistory)
            dr.kernel_history_clear()
            dr.set_flag(dr.JitFlag.KernelHistory, True)
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        import time

        wall = time.perf_counter() - self._t0
        dr = self._dr
        if dr is not None:
            history = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, self._flag)
            self.compile_seconds = sum(float(k.get("backend_time", 0.0)) for k in history
                                       if k.get("type") == dr.KernelType.JIT) / 1e3
        # Guard: the two clocks differ slightly; a render never takes negative time.
        self.seconds = max(0.0, wall - self.compile_seconds)
