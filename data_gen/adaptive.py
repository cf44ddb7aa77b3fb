"""Adaptive sampling in data_gen's own integrator: a uniform pilot pass, then passes whose per-pixel
sample counts follow a map made from everything rendered so far (issue 40; the estimates and the
map are `jaxdenoise.adaptive`, the choices docs/methods/adaptive.md).

**Unbiased pooling with fixed weights.** Pass ``k`` (0 = the pilot) gives each pixel ``c_k`` samples
with mean ``m_k``; ``c_k`` depends on the passes before it, so the count-weighted mean of all samples
is biased (a pixel whose pilot came out bright gets more samples, which then outweigh that pilot).
The frame is instead ``sum_k w_k m_k`` with ``w_k = B_k / B`` the pass's share of the whole sample
budget, the same constants for every pixel. Given the passes before it, ``m_k`` is an unbiased
mean with fixed counts, so ``E[sum_k w_k m_k] = mu sum_k w_k = mu``. That needs ``c_k >= 1`` in every
pass (the map's floor). Every buffer (features too) is pooled the same way, so the buffers stay
consistent. The variance of that mean is ``s^2 sum_k w_k^2 / c_k`` with ``s^2`` the per-sample
variance pooled over the passes (each pass's squares around its own mean, ``sum_k (c_k - 1)``
degrees of freedom). The ``spp`` layer holds the samples each pixel got (``sum_k c_k``), the header's
``spp`` their mean (the budget).

**Maps.** Each pass is one wavefront whose samples form two independent halves per pixel
(``ceil(c/2)`` and ``floor(c/2)`` samples, `data_gen.render.render_counts`); the halves are pooled by count for the map only (its bias does not reach the
frame). ``relvar``: the classic relative variance of the pixel mean; ``METHOD:relvar``: the same
with the METHOD-denoised frame as the denominator; ``METHOD:halves`` (``METHOD`` alone): each half
denoised by METHOD, `jaxdenoise.adaptive.halves_error`. The map's wall time (half buffers,
denoising, estimate, allocation) is reported beside the render time.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Iterable

import numpy as np

from .integrator import FEATURE_DIMS, FEATURES, PathSettings, derive_seed
from .mitsuba_setup import RenderTimer
from .render import DEFAULT_SAMPLES_PER_PASS, VERTICES, film_size, render_counts
from jaxdenoise.adaptive import SMOOTH
from jaxdenoise.errors import JaxdenoiseError

ESTIMATORS = ("relvar", "halves")
FLOOR_FRACTION = 0.1    # no pixel gets fewer than this fraction of a pass's mean (at least 1 sample)
CAP = 8.0               # nor more than this multiple of it
COST_AWARE = True       # allocate for error per time: a pixel's share over its samples' mean path length


@dataclasses.dataclass(frozen=True)
class Spec:
    """What drives the map: ``estimator`` in ESTIMATORS, with the denoiser ``method`` (None: the
    classic relative variance of the noisy mean)."""

    method: str | None
    estimator: str

    @property
    def label(self) -> str:
        return self.estimator if self.method is None else f"{self.method}:{self.estimator}"


def parse_spec(text: str) -> Spec:
    """``relvar`` | ``METHOD`` (= ``METHOD:halves``) | ``METHOD:relvar`` | ``METHOD:halves``."""
    from jaxdenoise.methods import names

    text = str(text).strip()
    method, _, est = text.partition(":")
    if not _ and method in ESTIMATORS:
        method, est = "", method
    if method == "":
        if est != "relvar":
            raise JaxdenoiseError(f"--adaptive {text!r}: the estimator '{est}' needs a denoiser (METHOD:{est})")
        return Spec(None, "relvar")
    est = est or "halves"
    if est not in ESTIMATORS:
        raise JaxdenoiseError(f"--adaptive {text!r}: unknown estimator '{est}'; expected one of {list(ESTIMATORS)}")
    if method not in names():
        raise JaxdenoiseError(f"--adaptive {text!r}: unknown method '{method}'; registered: {names()}")
    return Spec(method, est)


def plan(spp: int, passes: int, initial: int | None, npix: int) -> tuple[int, list[int]]:
    """(pilot spp, total samples of each adaptive pass): the pilot ``initial`` (default a quarter of
    the budget, at least 2: a variance and two halves) uniform, the rest split evenly over ``passes``."""
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 3:
        raise JaxdenoiseError(f"adaptive sampling: spp is {spp!r}; expected an integer >= 3 (a pilot of 2 and more)")
    if isinstance(passes, bool) or not isinstance(passes, (int, np.integer)) or passes < 1:
        raise JaxdenoiseError(f"adaptive sampling: passes is {passes!r}; expected an integer >= 1")
    n0 = max(2, int(spp) // 4) if initial is None else int(initial)
    if n0 < 2 or n0 > spp - passes:
        raise JaxdenoiseError(f"adaptive sampling: the pilot has {n0} spp; expected 2 .. spp - passes = {spp - passes} "
                              "(every adaptive pass needs at least 1 sample per pixel)")
    rest = (int(spp) - n0) * npix
    per = [rest // passes] * passes
    per[-1] += rest - sum(per)
    return n0, per


def _split(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = (c + 1) // 2
    return a, c - a


def _buffers_from(acc: dict, n: np.ndarray, s2: dict, camera: dict):
    """`Buffers` of the count-pooled mean ``acc[name] / n`` with variance ``s2 / n`` (maps only)."""
    from jaxdenoise.buffers import Buffers

    nn = np.maximum(n, 1)[..., None]
    f = {"color": acc["color"] / nn, "color_var": s2["color"] / nn}
    for name in acc:
        if name != "color":
            f[name] = acc[name] / nn
            f[f"{name}_var"] = np.mean(s2[name], -1, keepdims=True) / nn
    f = {k: np.asarray(v, np.float32) for k, v in f.items()}
    return Buffers(**f, spp_map=n.astype(np.float32)[..., None], spp=float(max(1, round(float(np.mean(n))))),
                   **camera)


def render_adaptive(scene, *, spp: int, adaptive: str | Spec = "relvar", passes: int = 1,
                    initial: int | None = None, seed: int = 0, settings: PathSettings = PathSettings(),
                    record: Iterable[str] = (), samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS,
                    denoise: Callable[[Any], Any] | None = None, camera: dict | None = None,
                    floor_fraction: float = FLOOR_FRACTION, cap: float = CAP, smooth: int = SMOOTH,
                    cost_aware: bool = COST_AWARE,
                    on_pass: Callable[[float], None] | None = None) -> tuple[dict, dict]:
    """Render one frame with ``spp`` samples per pixel on average, adaptively.

    Returns ``(buffers, info)``: ``buffers`` as `data_gen.render.moments_to_buffers` returns them
    (``color``, ``color_var``, the recorded features and their variances) plus ``spp_map`` (H, W, 1);
    ``info`` the plan, the pass weights, and the seconds spent rendering (Dr.Jit compilation apart)
    and making maps. ``denoise(buffers) -> image`` is the map's denoiser (``jaxdenoise.load(method)``
    when None and the spec names one); ``camera`` the frame's camera matrices (RAE reads them).
    ``floor_fraction``, ``cap``: each adaptive pass gives a pixel between ``max(1, floor_fraction m)``
    and ``cap m`` samples (``m`` the pass's mean); ``smooth``: the box the error map is averaged over;
    ``cost_aware``: divide each pixel's share by its samples' cost, the mean path vertices of its
    pilot samples (`jaxdenoise.adaptive.allocate`'s ``cost``), so the map minimizes error per time.
    """
    import jax

    from jaxdenoise import adaptive as ad

    spec = adaptive if isinstance(adaptive, Spec) else parse_spec(adaptive)
    width, height = film_size(scene)
    npix = width * height
    n0, budgets = plan(spp, passes, initial, npix)
    weights = [n0 / spp] + [b / (spp * npix) for b in budgets]   # each pass's share of the budget
    wanted = set(record)
    if spec.method is not None:
        from jaxdenoise.methods import get

        wanted |= {f for f in get(spec.method).needs() if f in FEATURES}   # what the map's denoiser reads
        if denoise is None:
            from jaxdenoise.api import load

            denoise = load(spec.method)
    record = [f for f in FEATURES if f in wanted]
    names = ["color"] + record
    chans = {k: 3 if k == "color" else FEATURE_DIMS[k] for k in names}
    zeros = lambda: {k: np.zeros((height, width, chans[k])) for k in names}
    passes_out = []                                   # per pass: (counts, sums, sumsq)
    half_sum = [zeros(), zeros()]
    half_n = [np.zeros((height, width)), np.zeros((height, width))]
    info = {"spec": spec.label, "spp": int(spp), "pilot_spp": n0, "passes": int(passes), "weights": weights,
            "cost_aware": bool(cost_aware),
            "render_seconds": 0.0, "compile_seconds": 0.0, "map_seconds": 0.0, "pass_counts": []}
    counts = np.full((height, width), n0, np.int64)
    for k in range(passes + 1):
        sums, sq = zeros(), zeros()
        halves = _split(counts)
        with RenderTimer() as timer:
            moments = render_counts(scene, parts=halves, seed=derive_seed(seed, "adaptive", k), settings=settings,
                                    record=record, samples_per_pass=samples_per_pass, on_pass=on_pass,
                                    vertices=cost_aware and k == 0)
        if cost_aware and k == 0:                     # the pilot's mean path length: a sample's cost
            verts = (moments[0][VERTICES][0] + moments[1][VERTICES][0])[..., 0] / np.maximum(counts, 1)
            cost = np.maximum(np.asarray(ad.smooth(verts, size=smooth), np.float64), 1.0)
        info["render_seconds"] += timer.seconds
        info["compile_seconds"] += timer.compile_seconds
        for h, (m, c) in enumerate(zip(moments, halves)):
            for name in names:
                s, q = m[name]
                sums[name] += s
                sq[name] += q
                half_sum[h][name] += s
            half_n[h] += c
        passes_out.append((counts, sums, sq))
        info["pass_counts"].append({"min": int(counts.min()), "max": int(counts.max()),
                                    "mean": float(counts.mean())})
        if k == passes:
            break
        t0 = time.perf_counter()
        s2 = _pooled_variance(passes_out, names)
        n_all = half_n[0] + half_n[1]
        if spec.method is None:
            err = ad.relative_variance((half_sum[0]["color"] + half_sum[1]["color"]) / n_all[..., None],
                                       s2["color"] / n_all[..., None])
        elif spec.estimator == "halves":
            bufs = [_buffers_from(half_sum[h], half_n[h], s2, camera or {}) for h in (0, 1)]
            da, db = (np.asarray(denoise(b)) for b in bufs)
            err = ad.halves_error(da, db)
        else:
            full = {name: half_sum[0][name] + half_sum[1][name] for name in names}
            b = _buffers_from(full, n_all, s2, camera or {})
            err = ad.relative_variance(b.color, b.color_var, denoised=np.asarray(denoise(b)))
        err = np.asarray(jax.block_until_ready(ad.smooth(err, size=smooth)), np.float64)
        floor = max(1, int(floor_fraction * budgets[k] / npix))
        counts = ad.allocate(err, n_all, budgets[k], floor=floor, cap=cap, cost=cost if cost_aware else None)
        info["map_seconds"] += time.perf_counter() - t0
    return _pool(passes_out, names, weights), info


def _pooled_variance(passes_out, names) -> dict:
    """Per-sample variance of each buffer, pooled over the passes (squares around each pass's mean)."""
    dof = sum(np.maximum(c - 1, 0) for c, _, _ in passes_out)
    out = {}
    for name in names:
        ss = sum(q[name] - s[name] ** 2 / np.maximum(c, 1)[..., None] for c, s, q in passes_out)
        out[name] = np.maximum(ss, 0.0) / np.maximum(dof, 1)[..., None]
    return out


def _pool(passes_out, names, weights) -> dict:
    """The frame: ``sum_k w_k m_k`` per buffer, its variance of the mean, and ``spp_map``."""
    s2 = _pooled_variance(passes_out, names)
    eff = sum(w * w / c for w, (c, _, _) in zip(weights, passes_out))            # sum_k w_k^2 / c_k
    out = {}
    for name in names:
        mean = sum(w * s[name] / c[..., None] for w, (c, s, _) in zip(weights, passes_out))
        var = s2[name] * eff[..., None]
        out[name] = mean.astype(np.float32)
        if name == "color":
            out["color_var"] = var.astype(np.float32)
        else:
            out[f"{name}_var"] = var.mean(-1, keepdims=True).astype(np.float32)
    out["spp_map"] = sum(c for c, _, _ in passes_out).astype(np.float32)[..., None]
    return out
