"""JAX's persistent compilation cache (jaxdenoise.compile_cache): a second process on the same shapes
loads its programs (the traced program and the executable) instead of tracing and compiling them, and
gets bit-identical outputs; a damaged program file is ignored and replaced; the folder is movable and
can be turned off."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

SCRIPT = r"""
import json, sys
import numpy as np
import jaxdenoise as jd
from jaxdenoise import compile_cache
# Every program is written, whatever its compile took: at the default threshold (0.1 s) the
# gaussian's program, which compiles in less on an idle machine, would not be, and this test
# (loading what was written) would depend on the machine's load.
compile_cache.MIN_COMPILE_SECONDS = 0.0
from jaxdenoise.inference import inference_fn, prepare
from jaxdenoise.methods import get
rng = np.random.default_rng(3)
img = lambda: rng.random((24, 20, 3), dtype=np.float32)
b = jd.Buffers(color=img(), dx=img() - 0.5, dy=img() - 0.5)
out, info = {}, {}
for name in ("gaussian", "poisson-l1"):
    m, params = jd.api.resolve(name)
    fn = inference_fn(m)
    c = fn.compile(params, prepare(m, b))
    out[name] = np.asarray(fn(params, prepare(m, b))).tolist()
    info[name] = {"cache": c.cache, "program": c.program, "compile": c.compile_seconds, "trace": c.trace_seconds,
                  "lower": c.lower_seconds}
# the sequence driver's programs (compile_cache.CachedJit): a pytree in and out, one per signature
import jax.numpy as jnp
toy = compile_cache.CachedJit(lambda x, s: {"y": jnp.cumsum(x * s[0], axis=0)}, "tests.toy", {"k": 1},
                              module="jaxdenoise.sequence")
y = toy(np.arange(12, dtype=np.float32).reshape(3, 4), (np.float32(2.0),))
toy(np.ones((3, 4), np.float32), (np.float32(3.0),))  # the same signature: compiled once
json.dump({"out": out, "info": info, "status": compile_cache.status(), "toy": np.asarray(y["y"]).tolist(),
           "toy_origins": toy.origins}, open(sys.argv[1], "w"))
"""


def _run(tmp_path, cache, tag):
    env = dict(os.environ, JAXDENOISE_CACHE_DIR=str(cache))
    result = tmp_path / f"{tag}.json"
    subprocess.run([sys.executable, "-c", SCRIPT, str(result)], env=env, check=True, timeout=300)
    return json.loads(result.read_text())


def test_second_process_loads_the_programs_and_gets_identical_outputs(tmp_path):
    cache = tmp_path / "xla"
    first = _run(tmp_path, cache, "first")
    second = _run(tmp_path, cache, "second")
    assert first["status"] == {"enabled": True, "dir": str(cache)}
    assert {v["cache"] for v in first["info"].values()} == {"miss"}
    assert {v["cache"] for v in second["info"].values()} == {"hit"}
    # the traced programs: written by the first process, read back (not traced) by the second
    assert {v["program"] for v in first["info"].values()} == {"miss"}
    assert {v["program"] for v in second["info"].values()} == {"hit"}
    assert first["toy_origins"] == ["miss"] and second["toy_origins"] == ["hit"]
    np.testing.assert_array_equal(np.array(second["toy"]), np.array(first["toy"]))
    np.testing.assert_array_equal(np.array(first["toy"]), 2 * np.cumsum(np.arange(12).reshape(3, 4), axis=0))
    programs = sorted(cache.glob("jaxdenoise-program-*.bin"))
    assert len(programs) == 3
    for name in first["out"]:  # bit-identical: the same executable, loaded instead of compiled
        np.testing.assert_array_equal(np.array(second["out"][name]), np.array(first["out"][name]))
    # a hit skips XLA's compile (IRLS's 20 x 50 CG loop: about a second; loading it, milliseconds)
    assert second["info"]["poisson-l1"]["compile"] < 0.5 * first["info"]["poisson-l1"]["compile"]
    # a damaged program file is ignored: that method is traced again, its file rewritten, same output
    programs[0].write_bytes(b"not a program")
    third = _run(tmp_path, cache, "third")
    assert sorted([v["program"] for v in third["info"].values()] + third["toy_origins"]) == ["hit", "hit", "miss"]
    assert programs[0].read_bytes() != b"not a program"
    for name in first["out"]:
        np.testing.assert_array_equal(np.array(third["out"][name]), np.array(first["out"][name]))
    off = _run(tmp_path, "off", "off")
    assert off["status"] == {"enabled": False, "dir": None}
    assert {v["cache"] for v in off["info"].values()} == {"off"}
    assert {v["program"] for v in off["info"].values()} == {"off"} and off["toy_origins"] == ["off"]
    np.testing.assert_array_equal(np.array(off["out"]["poisson-l1"]), np.array(first["out"]["poisson-l1"]))


def test_a_program_key_changes_with_everything_a_trace_depends_on(monkeypatch):
    """The traced-program key (compile_cache.program_key) tells apart the program, its module, its
    config, the arguments' tree, shapes and dtypes, and the library's sources; the same inputs give
    the same key; a module outside the library gets none (traced in every process)."""
    import jax

    from jaxdenoise import compile_cache
    from jaxdenoise.methods import get

    cfg = get("gaussian").config
    args = ({}, {"color": np.zeros((4, 5, 3), np.float32), "spp": 4.0})
    leaves, tree = jax.tree_util.tree_flatten(args)
    mod = "jaxdenoise.methods.gaussian"
    key = compile_cache.program_key("gaussian", cfg, tree, leaves, module=mod)
    assert key is not None and key == compile_cache.program_key("gaussian", cfg, tree, leaves, module=mod)
    # a method from the user's own module is never kept: the source digest cannot see its edits
    assert compile_cache.program_key("gaussian", cfg, tree, leaves, module="my_methods.gaussian") is None
    other_leaves, other_tree = jax.tree_util.tree_flatten(({}, {"color": np.zeros((4, 6, 3), np.float32)}))
    others = [
        compile_cache.program_key("bilateral", cfg, tree, leaves, module=mod),
        compile_cache.program_key("gaussian", cfg, tree, leaves, module="jaxdenoise.methods.bilateral"),
        compile_cache.program_key("gaussian", type(cfg)(**{**cfg.__dict__, "sigma": cfg.sigma * 2}), tree, leaves,
                                  module=mod),
        compile_cache.program_key("gaussian", cfg, tree, [leaves[0].astype(np.float16), leaves[1]], module=mod),
        compile_cache.program_key("gaussian", cfg, other_tree, other_leaves, module=mod),
    ]
    monkeypatch.setattr(compile_cache, "_source_digest", lambda: "an edited library")
    others.append(compile_cache.program_key("gaussian", cfg, tree, leaves, module=mod))
    assert len({key, *others}) == 1 + len(others)
