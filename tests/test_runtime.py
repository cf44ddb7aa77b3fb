"""jaxdenoise.runtime: glibc told to keep freed memory (the CLI's and bench's opt-in) gives bit-identical
outputs and stops a program's second call from faulting its buffers in again; release_memory gives the
kept memory back; $JAXDENOISE_KEEP_MEMORY=off and a C library other than glibc leave the allocator as it
is, and say why. Each case runs in a child process: the settings are process-wide."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

SCRIPT = r"""
import hashlib, json, resource, sys
mode = sys.argv[1]
from jaxdenoise import runtime
if mode == "not-glibc":
    import platform
    platform.libc_ver = lambda *a, **k: ("musl", "1.2")
kept = runtime.keep_memory(respect_env=True) if mode != "default" else None
import jax, jax.numpy as jnp, numpy as np

N = 4096  # 64 MiB per float32 buffer: above glibc's largest mmap threshold (32 MiB), as a network's
# activations at 1280x720 are (118 MB for 32 channels); smaller blocks glibc learns to keep by itself
f = jax.jit(lambda x: (x * 3.0 + x[::-1]) @ x[:, :16])
x = jnp.asarray(np.random.default_rng(0).random((N, N), dtype=np.float32))
outs, faults = [], []
for _ in range(100):  # each output is freed before the next call, as in a denoising loop
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    y = f(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
    outs.append(hashlib.sha256(np.asarray(y).tobytes()).hexdigest())
    del y
rss = lambda: int(open("/proc/self/statm").read().split()[1]) * 4096
big = np.ones(64 * 2**20 // 8)  # 64 MiB, freed: kept by the allocator in the kept mode
del big
before = rss()
released = runtime.release_memory()
print(json.dumps({"kept": kept, "status": runtime.status(), "faults": faults[1:], "out": outs[0],
                  "same": len(set(outs)) == 1, "pages": 3 * N * N * 4 // 4096,
                  "released": released, "rss_drop": before - rss()}))
"""


def _run(mode: str, env: dict | None = None) -> dict:
    env = {"JAXDENOISE_KEEP_MEMORY": "on", **(env or {})}  # conftest turns it off for the test processes
    # XLA's default optimisation level, as users run it (the default test run's -O0, conftest.py, emits
    # code whose temporaries are not the allocator's to keep)
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": "", **(env or {})})
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the allocator settings exist only in glibc")
def test_keep_memory_reuses_buffers_bit_identically_and_release_gives_them_back():
    default, kept = _run("default"), _run("keep")
    assert kept["kept"] is True and kept["status"] == {"kept": True, "why": "glibc malloc: no mmap, no trim, one arena"}
    assert default["status"]["kept"] is None
    assert kept["same"] and default["same"] and kept["out"] == default["out"]  # the allocator never changes a value
    # repeated calls reuse their buffers: the default allocator faults a large buffer's pages in on every
    # call; the kept heap only when it grows, by one buffer now and then as threads free in varying order
    # (measured: 1-8 buffers over 100 calls in 12 runs, up to 9 within the first 30 calls, some growth as
    # late as call 74), so the window is 100 calls: the heap's growth is bounded, the default's is not
    assert min(default["faults"]) > 0.2 * kept["pages"], default["faults"]
    assert sum(kept["faults"]) < 0.3 * sum(default["faults"]), (kept["faults"], default["faults"])
    # the kept 64 MiB (and the program's buffers) go back to the system on release
    assert kept["released"] and kept["rss_drop"] > 32 * 2**20, kept["rss_drop"]


def test_keep_memory_is_left_out_where_asked_or_impossible():
    off = _run("keep", {"JAXDENOISE_KEEP_MEMORY": "off"})
    assert off["kept"] is False and "JAXDENOISE_KEEP_MEMORY" in off["status"]["why"]
    other = _run("not-glibc")
    assert other["kept"] is False and "'musl' is not glibc" in other["status"]["why"]
    assert other["released"] is False  # nothing to call on that C library


def test_the_command_line_keeps_memory_unless_told_not_to():
    """Every CLI verb makes the call before it runs (here `methods`); $JAXDENOISE_KEEP_MEMORY=off leaves
    the allocator alone."""
    code = ("import json; from jaxdenoise import cli, runtime; cli.main(['methods']); "
            "print(json.dumps(runtime.status()))")
    for value, kept in (("on", platform.libc_ver()[0] == "glibc"), ("off", False)):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                              env={**os.environ, "JAX_PLATFORMS": "cpu", "JAXDENOISE_KEEP_MEMORY": value})
        assert done.returncode == 0, done.stderr[-2000:]
        assert json.loads(done.stdout.strip().splitlines()[-1])["kept"] is kept, (value, done.stdout[-500:])
