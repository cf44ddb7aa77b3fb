"""Helpers the experiment scripts share (one place each): timing a jitted call by the bench
protocol, the plain U-Net the convolution experiments build, and packing run folders for `$OUT`.

Scripts put ``experiments/`` on ``sys.path`` (they run as ``python experiments/NAME.py``) and
``from common import ...``.
"""
from __future__ import annotations

import json
import math
import statistics
import tarfile
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["tar_folders", "timed", "unet"]


def timed(fn: Callable, *args: Any, runs: int) -> tuple[Any, dict]:
    """``(output, stats)`` of ``jax.jit(fn)(*args)``: compiled ahead of time (``compile_s``), one
    warm-up, then ``runs`` timed calls (``median_s``, ``runs_s`` wall; ``median_cpu_s``, ``cpu_s``
    process CPU time; ``median_sys_s`` its part spent in the kernel, ``median_faults`` the page faults
    per call), with XLA's cost analysis (``gflop``, ``gflops`` at the median) and its temporary memory
    (``temp_bytes``)."""
    import resource

    import jax

    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flops = float(cost.get("flops", float("nan"))) if cost else float("nan")
    ma = compiled.memory_analysis()
    out = jax.block_until_ready(compiled(*args))  # warm-up
    ts, cpu, sys_s, faults = [], [], [], []
    for _ in range(runs):
        r0, t0, c0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter(), time.process_time()
        out = jax.block_until_ready(compiled(*args))
        ts.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        sys_s.append(r1.ru_stime - r0.ru_stime)
        faults.append(r1.ru_minflt + r1.ru_majflt - r0.ru_minflt - r0.ru_majflt)
    med = statistics.median(ts)
    return out, {"median_s": med, "runs_s": ts, "compile_s": compile_s, "median_cpu_s": statistics.median(cpu),
                 "cpu_s": cpu, "median_sys_s": statistics.median(sys_s), "median_faults": statistics.median(faults),
                 "gflop": flops / 1e9, "gflops": flops / 1e9 / med,
                 "temp_bytes": int(ma.temp_size_in_bytes) if ma else None}


def unet(widths, out: int = 3, slope: float = 0.1):
    """A plain U-Net of `jaxdenoise.nn` (two 3x3 convs and a leaky ReLU per stage, max pooling,
    nearest up-sampling, a 3x3 output conv): ``(init, apply)``."""
    from jaxdenoise import nn

    act = nn.LeakyRelu(slope)
    stage = lambda c: nn.serial(nn.Conv(c, 3), act, nn.Conv(c, 3), act)  # noqa: E731
    return nn.UNet([stage(c) for c in widths], nn.MaxPool(2), stage(widths[-1]), nn.Upsample(2, "nearest"),
                   [nn.serial(stage(c), *([nn.Conv(out, 3)] if i == 0 else [])) for i, c in enumerate(widths)])


def tar_folders(out: Path, name: str, folders: dict[str, Path]) -> None:
    """``out/name``: a tar of ``{arcname: folder}`` (missing folders left out), written atomically."""
    tmp = out / f".{name}.tmp"
    with tarfile.open(tmp, "w") as t:
        for arc, folder in folders.items():
            if folder.is_dir():
                t.add(folder, arcname=arc)
    tmp.rename(out / name)


def box_mean(x, size: int = 15):
    """The ``size x size`` box mean of an (H, W, C) array per channel (edges reflected): the colour
    level studies' local average (issues 15, 33)."""
    from scipy.ndimage import uniform_filter

    return uniform_filter(x, (size, size, 1))


def num(value, spec: str = ".4g") -> str:
    """One measured number as a result page shows it (the experiments' ``page`` functions and
    scripts/results.py); a missing (None) or non-finite value is an error, so a page never prints
    a hole or "nan"."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"expected a finite number, found {value!r}")
    return format(value, spec)


def heldout_scenes(n_proc: int, n_lib: int, width: int) -> list[tuple]:
    """Scenes no network here trained on: ``n_proc`` held-out draws of the procedural families
    (``mixed``, seeds 100000+, the generator and seeds of ``data/heldout``) at ``width`` x ``width``
    and the first ``n_lib`` scenes of the scene library's evaluation split, ``width`` wide. Each is
    ``(label, scene, width, height, seed)``: a scene dict (its size set, ``width``/``height`` None) or
    ``library:NAME`` (for `data_gen.scenes.load_scene` with that size), and a seed of its own."""
    from data_gen import library
    from data_gen.scenes import build_scene

    out = [(f"mixed@{100000 + k}", build_scene("mixed", 100000 + k, width=width, height=width), None, None,
            100000 + k) for k in range(n_proc)]
    for k, name in enumerate(library.scene_names("eval")[:n_lib]):
        w, h = library.film_size(name, width, None)
        out.append((f"library:{name}", f"library:{name}", w, h, 500000 + k))
    return out


def all_measured(res: dict, name: str) -> None:
    """Raise when the result ``res`` (of the JSON ``name``) holds a NaN or an infinity anywhere: a
    value that was not measured, which a page must not print."""
    try:
        json.dumps(res, allow_nan=False)
    except ValueError:
        raise ValueError(f"{name} holds a NaN or an infinity: a value that was not measured") from None


def write_study(out: Path, json_name: str, page_name: str, res: dict, page: Callable[[dict], str]) -> Path:
    """Write an experiment's result JSON, then its page from that JSON as written (what
    scripts/results.py checks the committed page against); returns the page's path."""
    from jaxdenoise.fsutil import write_json, write_text

    write_json(out / json_name, res)
    write_text(out / page_name, page(json.loads((out / json_name).read_text())))
    return out / page_name
