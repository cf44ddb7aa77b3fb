"""Shared fixtures: small synthetic frames with every buffer, written through the real EXR path."""
from __future__ import annotations

import contextlib
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

# JAX's persistent compilation cache (jaxdenoise.compile_cache): one fresh folder per test run,
# shared by the run's xdist workers (the same programs compile once for all of them) and removed at
# its end, so no run reads programs an earlier run (or the user's ~/.cache) compiled.
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID") or f"pid{os.getpid()}"
_CACHE = os.path.join(__import__("tempfile").gettempdir(), f"jaxdenoise-test-xla-{_RUN}")
os.environ["JAXDENOISE_CACHE_DIR"] = _CACHE
# The CLI and bench tell glibc to keep freed memory (jaxdenoise.runtime); a test worker runs hundreds
# of programs and would hold its largest heap for the rest of the run. Tests run with the system
# allocator (values do not depend on it: tests/test_runtime.py), except where they ask for it.
os.environ.setdefault("JAXDENOISE_KEEP_MEMORY", "off")

import numpy as np
import pytest

from jaxdenoise.buffers import CHANNELS, Buffers


def synthetic_frame(h: int = 8, w: int = 10, seed: int = 0, spp: int | None = 4,
                    fields=tuple(f for f in CHANNELS if f not in ("spp_map", "emission")),
                    camera: bool = True) -> Buffers:
    """A frame with plausible values in every requested buffer (radiance >= 0, normals unit); by
    default every buffer of a uniformly sampled frame whose gradients hold every contribution (no
    per-pixel ``spp_map``, no ``emission`` layer: tests/test_gradient_emission.py has those)."""
    rng = np.random.default_rng(seed)
    out = {}
    for f in fields:
        c = len(CHANNELS[f])
        if f == "normal":
            n = rng.normal(size=(h, w, 3))
            v = n / np.linalg.norm(n, axis=-1, keepdims=True)
        elif f in ("dx", "dy", "position"):
            v = rng.normal(size=(h, w, c))
        elif f == "depth":
            v = rng.uniform(0.5, 10.0, size=(h, w, 1))
        else:
            v = rng.uniform(0.0, 1.0, size=(h, w, c))
        out[f] = v.astype(np.float32)
    if spp is not None:
        out["spp"] = np.float32(spp)
    if camera:  # 5 units in front of the origin, looking along +z (jaxdenoise.view conventions)
        m = np.eye(4, dtype=np.float32)
        m[2, 3] = 5.0
        out["world_to_camera"] = m
    return Buffers(**out)


@pytest.fixture
def frame() -> Buffers:
    return synthetic_frame()


def make_shot(folder, ref: np.ndarray, renders: dict[int, Buffers], attrs: dict | None = None) -> None:
    """Write one bench shot: reference.exr and spp{spp:04d}_00.exr per render (header ``attrs`` added
    to each, e.g. ``{"primal": "gpt"}`` for gradient frames as data_gen --primal gpt writes them)."""
    from jaxdenoise.io import write_buffers, write_image

    write_image(folder / "reference.exr", ref)
    for spp, b in renders.items():
        write_buffers(folder / f"spp{spp:04d}_00.exr", b.replace(spp=np.float32(spp)),
                      {"render_seconds": 0.01 * spp, **(attrs or {})})


def fit(name: str, data, out, *, config=None, **run):
    """`jaxdenoise.train.train` as the CLI calls it: the method resolved once (``config`` replacing
    its default), the run configured by `TrainConfig.for_method` with ``run``'s fields."""
    from jaxdenoise.methods import get
    from jaxdenoise.train import TrainConfig, train

    method = get(name, config)
    return train(method, data, out, TrainConfig.for_method(method, **run))


@contextlib.contextmanager
def registered(name: str, module: str):
    """A test-only method (a module under tests/) registered for the duration of the block."""
    from jaxdenoise.methods import _REGISTRY, register

    register(name, module)
    try:
        yield
    finally:
        _REGISTRY.pop(name, None)


def pytest_configure(config):
    """The default run (``-m 'not slow'``) has XLA compile at LLVM -O0 instead of -O3: its tests run tiny
    inputs, where XLA's compile is most of their time (the default run took 865 s at -O3, 755 s at -O1,
    612 s at -O0; 2026-12-04, 2 cores, one run each). No test times anything, a comparison of two code
    paths compiles both at the same level, and no tolerance was changed. The slow checks (training,
    fuzzing at scale) keep -O3, and a level the caller set in XLA_FLAGS wins. Runs before any test
    module is imported: the XLA backend reads XLA_FLAGS when it starts, at the first computation."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "not slow" in (config.option.markexpr or "") and "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_backend_optimization_level=0").strip()


def pytest_sessionfinish(session, exitstatus):
    """The controller (not an xdist worker) removes the run's compilation cache."""
    if not hasattr(session.config, "workerinput"):
        import shutil

        shutil.rmtree(_CACHE, ignore_errors=True)
