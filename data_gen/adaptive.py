"""Adaptive sampling in data_gen's own integrator: a uniform pilot pass, then passes whose per-pixel
sample counts follow a map made from everything rendered so far (issue 40; the estimates and the
map are `jaxdenoise.adaptive`, the choices docs/methods/adaptive.md).

**Unbiased pooling: the map's samples at fixed weights, the others by count.** Pass ``k`` (0 = the
pilot) gives each pixel ``c_k`` samples with mean ``m_k``; ``c_k`` depends on what the map read, so
the count-weighted mean of *all* samples is biased (a pixel whose map samples came out bright gets
more samples, which then outweigh those bright samples: the classic downward bias of adaptive
sampling on fireflies). The samples are therefore kept in two kinds of groups. The *map's* groups
(the pilot's first ``map_spp`` samples per pixel, and every adaptive pass but the last, each as two
independent halves) are everything any map reads; each gets a fixed weight ``w_g = B_g / B``, its
share of the frame's sample budget, the same constant for every pixel (given the groups before it,
``m_g`` is an unbiased mean over a fixed count, so ``E[w_g m_g] = w_g mu``; this needs ``c_g >= 1``,
the map's floor). The *frame's* groups (the rest of the pilot and the last pass) are never read by
a map, so their counts are independent of their values: their count-weighted mean ``m_F`` is
unbiased, and gets the remaining weight ``w_F = 1 - sum_g w_g``. The frame is
``sum_g w_g m_g + w_F m_F``, ``E = mu``. Against fixed weights for every pass (``map_spp`` equal to
the pilot), a pixel the map starves keeps its uniform pilot samples at their full count weight
instead of putting the last pass's whole weight on its few samples. Every buffer (features too) is
pooled the same way, so the buffers stay consistent. The variance of that mean is
``s^2 (sum_g w_g^2 / c_g + w_F^2 / c_F)`` with ``s^2`` the per-sample variance pooled over the
groups (each group's squares around its own mean, ``sum (c - 1)`` degrees of freedom). The ``spp``
layer holds the samples each pixel got, the header's ``spp`` their mean (the budget).

**Maps.** Each map group forms two independent halves per pixel (``ceil(c/2)`` and ``floor(c/2)``
samples, one wavefront with the pass's frame part, `data_gen.render.render_counts`); the halves
are pooled by count for the map only (its bias does not reach the frame). ``relvar``: the classic
relative variance of the pixel mean; ``METHOD:relvar``: the same with the METHOD-denoised frame as
the denominator; ``METHOD:halves`` (``METHOD`` alone): each half denoised by METHOD,
`jaxdenoise.adaptive.halves_error`. The last pass tops each pixel up over the frame samples it
already has (`jaxdenoise.adaptive.allocate`'s ``base``). The map's wall time
(half buffers, denoising, estimate, allocation) is reported beside the render time.
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
    classic relative variance of the noisy mean); ``scale``: the map's denoiser runs on the map's
    buffers pooled over ``scale`` x ``scale`` pixel blocks (1: full resolution), its map repeated back."""

    method: str | None
    estimator: str
    scale: int = 1

    @property
    def label(self) -> str:
        base = self.estimator if self.method is None else f"{self.method}:{self.estimator}"
        return base if self.scale == 1 else f"{base}/{self.scale}"


def parse_spec(text: str) -> Spec:
    """``relvar`` | ``METHOD`` (= ``METHOD:halves``) | ``METHOD:relvar`` | ``METHOD:halves``, each
    with a denoiser optionally followed by ``/K``: the denoiser's map at 1/K of the resolution
    (``oidn:halves/2``)."""
    from jaxdenoise.methods import names

    text = str(text).strip()
    body, slash, k = text.partition("/")
    scale = 1
    if slash:
        if not k.isdigit() or int(k) < 1:
            raise JaxdenoiseError(f"--adaptive {text!r}: '/{k}' should be a positive integer, the factor the map's "
                                  "denoiser reduces the resolution by (e.g. oidn:halves/2)")
        scale = int(k)
    method, _, est = body.partition(":")
    if not _ and method in ESTIMATORS:
        method, est = "", method
    if method == "":
        if est != "relvar":
            raise JaxdenoiseError(f"--adaptive {text!r}: the estimator '{est}' needs a denoiser (METHOD:{est})")
        if scale != 1:
            raise JaxdenoiseError(f"--adaptive {text!r}: '/{scale}' sets the resolution of a denoiser's map; "
                                  "'relvar' has no denoiser")
        return Spec(None, "relvar")
    est = est or "halves"
    if est not in ESTIMATORS:
        raise JaxdenoiseError(f"--adaptive {text!r}: unknown estimator '{est}'; expected one of {list(ESTIMATORS)}")
    if method not in names():
        raise JaxdenoiseError(f"--adaptive {text!r}: unknown method '{method}'; registered: {names()}")
    return Spec(method, est, scale)


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


def _buffers_from(acc: dict, n: np.ndarray, s2: dict, camera: dict, scale: int = 1):
    """`Buffers` of the count-pooled mean ``acc[name] / n`` with variance ``s2 / n`` (maps only). With
    ``scale`` > 1, over ``scale`` x ``scale`` pixel blocks (edge-replicated to a whole number of
    blocks): sums and counts add up, the per-sample variance is the block's mean."""
    from jaxdenoise.buffers import Buffers

    if scale > 1:
        acc = {k: _blocks(v, scale, np.sum) for k, v in acc.items()}
        s2 = {k: _blocks(v, scale, np.mean) for k, v in s2.items()}
        n = _blocks(n[..., None], scale, np.sum)[..., 0]
    nn = np.maximum(n, 1)[..., None]
    f = {"color": acc["color"] / nn, "color_var": s2["color"] / nn}
    for name in acc:
        if name != "color":
            f[name] = acc[name] / nn
            f[f"{name}_var"] = np.mean(s2[name], -1, keepdims=True) / nn
    f = {k: np.asarray(v, np.float32) for k, v in f.items()}
    return Buffers(**f, spp_map=n.astype(np.float32)[..., None], spp=float(max(1, round(float(np.mean(n))))),
                   **camera)


def _blocks(x: np.ndarray, k: int, reduce) -> np.ndarray:
    """(H, W, C) -> (ceil(H/k), ceil(W/k), C): ``reduce`` over k x k blocks, the last row and column
    of blocks filled by repeating the edge."""
    h, w = x.shape[:2]
    x = np.pad(x, ((0, -h % k), (0, -w % k), (0, 0)), mode="edge")
    return reduce(x.reshape(x.shape[0] // k, k, x.shape[1] // k, k, -1), axis=(1, 3))


def render_adaptive(scene, *, spp: int, adaptive: str | Spec = "relvar", passes: int = 1,
                    initial: int | None = None, map_spp: int | None = None, seed: int = 0,
                    settings: PathSettings = PathSettings(),
                    record: Iterable[str] = (), samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS,
                    denoise: Callable[[Any], Any] | None = None, camera: dict | None = None,
                    floor_fraction: float = FLOOR_FRACTION, cap: float = CAP, smooth: int = SMOOTH,
                    cost_aware: bool = COST_AWARE,
                    on_pass: Callable[[float], None] | None = None) -> tuple[dict, dict]:
    """Render one frame with ``spp`` samples per pixel on average, adaptively.

    Returns ``(buffers, info)``: ``buffers`` as `data_gen.render.moments_to_buffers` returns them
    (``color``, ``color_var``, the recorded features and their variances) plus ``spp_map`` (H, W, 1);
    ``info`` the plan, the pass weights, and the seconds spent making maps (the map's halves of the
    buffers it reads, its denoiser's calls, the estimate and the allocation) and rendering (all the
    rest: the passes, the bookkeeping between them and the frame's pooling; Dr.Jit's one-off kernel
    compilation apart, in ``compile_seconds``). ``denoise(buffers) -> image`` is
    the map's denoiser (``jaxdenoise.load(method)`` when None and the spec names one); ``camera``
    the frame's camera matrices (RAE reads them).
    ``map_spp``: the pilot's samples per pixel that feed the map (default `map_split`: half the
    pilot, at least 2); the rest of the pilot is pooled by count with the last pass (module
    docstring). ``map_spp`` equal to the pilot gives every pass a fixed weight.
    ``floor_fraction``, ``cap``: each adaptive pass gives a pixel between ``max(1, floor_fraction m)``
    and ``cap m`` samples (``m`` the pass's mean); ``smooth``: the box the error map is averaged over;
    ``cost_aware``: divide each pixel's share by its samples' cost, the mean path vertices of its
    map samples (`jaxdenoise.adaptive.allocate`'s ``cost``), so the map minimizes error per time.
    """
    import jax

    from jaxdenoise import adaptive as ad

    spec = adaptive if isinstance(adaptive, Spec) else parse_spec(adaptive)
    width, height = film_size(scene)
    npix = width * height
    n0, budgets = plan(spp, passes, initial, npix)
    a0 = map_split(n0, map_spp)
    fixed = [a0 / spp] + [b / (spp * npix) for b in budgets[:-1]]   # the map's passes: their budget shares
    weights = {"map": fixed, "frame": 1.0 - sum(fixed)}
    wanted, map_feats = set(record), set()
    if spec.method is not None:
        from jaxdenoise.methods import get

        map_feats = {f for f in get(spec.method).needs() if f in FEATURES}   # what the map's denoiser reads
        wanted |= map_feats
        if denoise is None:
            from jaxdenoise.api import load

            denoise = load(spec.method)
    record = [f for f in FEATURES if f in wanted]
    names = ["color"] + record
    map_names = ["color"] + [f for f in record if f in map_feats]     # what a map reads of the halves
    chans = {k: 3 if k == "color" else FEATURE_DIMS[k] for k in names}
    zeros = lambda keys=names: {k: np.zeros((height, width, chans[k])) for k in keys}  # noqa: E731
    map_groups, frame_groups = [], []                 # (counts, sums, sumsq): fixed-weight / count-pooled
    half_sum = [zeros(map_names), zeros(map_names)]
    half_n = [np.zeros((height, width)), np.zeros((height, width))]
    info = {"spec": spec.label, "spp": int(spp), "pilot_spp": n0, "map_spp": a0, "passes": int(passes),
            "weights": weights, "cost_aware": bool(cost_aware),
            "render_seconds": 0.0, "compile_seconds": 0.0, "map_seconds": 0.0, "pass_counts": []}
    full = lambda v: np.full((height, width), v, np.int64)                     # noqa: E731
    counts = full(n0)
    # Everything but the maps is the render's time (the passes, the bookkeeping, the frame's pooling),
    # Dr.Jit's one-off kernel compilation apart, as for a uniform render.
    with RenderTimer() as timer:
        for k in range(passes + 1):
            # parts[0], parts[1]: the map's two halves (every pass but the last); `frame`: the index of
            # the part pooled by count (the pilot's rest, the last pass), None where the pass has none
            if k == 0:
                parts = [*_split(full(a0)), *([full(n0 - a0)] if n0 > a0 else [])]
                has_map, frame = True, (2 if n0 > a0 else None)
            elif k < passes:
                parts, has_map, frame = list(_split(counts)), True, None
            else:
                parts, has_map, frame = [counts], False, 0
            moments = render_counts(scene, parts=parts, seed=derive_seed(seed, "adaptive", k), settings=settings,
                                    record=record, samples_per_pass=samples_per_pass, on_pass=on_pass,
                                    vertices=cost_aware and k == 0)
            if cost_aware and k == 0:                     # a sample's cost: the map samples' mean path length
                verts = (moments[0][VERTICES][0] + moments[1][VERTICES][0])[..., 0] / a0
                cost = np.maximum(np.asarray(ad.smooth(verts, size=smooth), np.float64), 1.0)
            if has_map:                                   # the map's halves: fixed weight, and the map's data
                sums, sq = zeros(), zeros()
                for h in (0, 1):
                    for name in names:
                        s, q = moments[h][name]
                        sums[name] += s
                        sq[name] += q
                        if name in half_sum[h]:
                            half_sum[h][name] += s
                    half_n[h] += parts[h]
                map_groups.append((parts[0] + parts[1], sums, sq))
            if frame is not None:                         # pooled by count, never read by a map
                frame_groups.append((parts[frame], {n: moments[frame][n][0] for n in names},
                                     {n: moments[frame][n][1] for n in names}))
            info["pass_counts"].append({"min": int(counts.min()), "max": int(counts.max()),
                                        "mean": float(counts.mean())})
            if k == passes:
                break
            t0 = time.perf_counter()
            s2 = _pooled_variance(map_groups, map_names)
            n_all = half_n[0] + half_n[1]
            if spec.method is None:
                err = ad.relative_variance((half_sum[0]["color"] + half_sum[1]["color"]) / n_all[..., None],
                                           s2["color"] / n_all[..., None])
            elif spec.estimator == "halves":
                bufs = [_buffers_from(half_sum[h], half_n[h], s2, camera or {}, spec.scale) for h in (0, 1)]
                da, db = (np.asarray(denoise(b)) for b in bufs)
                err = _full_size(ad.halves_error(da, db), spec.scale, height, width)
            else:
                whole = {name: half_sum[0][name] + half_sum[1][name] for name in map_names}
                b = _buffers_from(whole, n_all, s2, camera or {}, spec.scale)
                err = _full_size(ad.relative_variance(b.color, b.color_var, denoised=np.asarray(denoise(b))),
                                 spec.scale, height, width)
            err = np.asarray(jax.block_until_ready(ad.smooth(err, size=smooth)), np.float64)
            floor = max(1, int(floor_fraction * budgets[k] / npix))
            counts = ad.allocate(err, n_all, budgets[k], floor=floor, cap=cap, cost=cost if cost_aware else None,
                                 base=n0 - a0 if k == passes - 1 else 0)
            info["map_seconds"] += time.perf_counter() - t0
        frame = _pool(map_groups, frame_groups, names, weights)
    info["compile_seconds"] = timer.compile_seconds
    info["render_seconds"] = max(0.0, timer.seconds - info["map_seconds"])
    return frame, info


def _full_size(err, scale: int, height: int, width: int) -> np.ndarray:
    """A map made at 1/``scale`` of the resolution, each value repeated over its block, cropped to the frame."""
    e = np.asarray(err)
    if scale > 1:
        e = np.repeat(np.repeat(e, scale, axis=0), scale, axis=1)
    return e[:height, :width]


def map_split(pilot: int, map_spp: int | None = None) -> int:
    """The pilot's samples per pixel that feed the map: ``map_spp``, by default half the pilot (at
    least 2: a variance and two halves); checked to lie in ``2 .. pilot``."""
    a = max(2, int(pilot) // 2) if map_spp is None else map_spp
    if isinstance(a, bool) or int(a) != a or not 2 <= a <= pilot:
        raise JaxdenoiseError(f"adaptive sampling: map_spp is {map_spp!r}; expected an integer in 2 .. {pilot} "
                              "(the pilot's samples per pixel)")
    return int(a)


def _pooled_variance(groups, names) -> dict:
    """Per-sample variance of each buffer, pooled over the groups of samples (squares around each
    group's own mean)."""
    dof = sum(np.maximum(c - 1, 0) for c, _, _ in groups)
    out = {}
    for name in names:
        ss = sum(q[name] - s[name] ** 2 / np.maximum(c, 1)[..., None] for c, s, q in groups)
        out[name] = np.maximum(ss, 0.0) / np.maximum(dof, 1)[..., None]
    return out


def _pool(map_groups, frame_groups, names, weights) -> dict:
    """The frame: ``sum_k w_k m_k`` over the map's groups plus ``w_F`` times the count-pooled mean of
    the frame groups, each buffer's variance of that mean, and ``spp_map``."""
    groups = map_groups + frame_groups
    s2 = _pooled_variance(groups, names)
    wf = weights["frame"]
    nf = sum(c for c, _, _ in frame_groups)
    eff = sum(w * w / c for w, (c, _, _) in zip(weights["map"], map_groups)) + wf * wf / nf
    out = {}
    for name in names:
        mean = sum(w * s[name] / c[..., None] for w, (c, s, _) in zip(weights["map"], map_groups))
        mean = mean + wf * sum(s[name] for _, s, _ in frame_groups) / nf[..., None]
        var = s2[name] * eff[..., None]
        out[name] = mean.astype(np.float32)
        if name == "color":
            out["color_var"] = var.astype(np.float32)
        else:
            out[f"{name}_var"] = var.mean(-1, keepdims=True).astype(np.float32)
    out["spp_map"] = sum(c for c, _, _ in groups).astype(np.float32)[..., None]
    return out
