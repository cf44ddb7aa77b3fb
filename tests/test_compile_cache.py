"""JAX's persistent compilation cache (jaxdenoise.compile_cache): a second process on the same shapes
loads its programs instead of compiling them, and gets bit-identical outputs; the folder is movable
and can be turned off."""
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
    info[name] = {"cache": c.cache, "compile": c.compile_seconds, "trace": c.trace_seconds, "lower": c.lower_seconds}
json.dump({"out": out, "info": info, "status": compile_cache.status()}, open(sys.argv[1], "w"))
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
    assert any(cache.iterdir())
    for name in first["out"]:  # bit-identical: the same executable, loaded instead of compiled
        np.testing.assert_array_equal(np.array(second["out"][name]), np.array(first["out"][name]))
    # a hit skips XLA's compile (IRLS's 20 x 50 CG loop: about a second; loading it, milliseconds)
    assert second["info"]["poisson-l1"]["compile"] < 0.5 * first["info"]["poisson-l1"]["compile"]
    off = _run(tmp_path, "off", "off")
    assert off["status"] == {"enabled": False, "dir": None}
    assert {v["cache"] for v in off["info"].values()} == {"off"}
    np.testing.assert_array_equal(np.array(off["out"]["poisson-l1"]), np.array(first["out"]["poisson-l1"]))
