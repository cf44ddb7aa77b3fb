"""The catalogue of stiff and extreme inputs, and the checks run on it (docs/architecture.md "Numerical stability").

One catalogue serves three consumers: ``test_methods.py`` (every registered method, through
`jaxdenoise.methods.get`), ``test_filters.py`` (the public filters of `jaxdenoise.filters` and the
screened-Poisson solvers of `jaxdenoise.solvers`) and ``experiments/stability_report.py`` (the
method x case table in ``docs/results/stability.md``). The checks live here too, so the tests and
the report cannot disagree about what passes.

Pass rule: a call passes ("ok") when its output has the input's pixel grid, is finite and is not
absurd (see `_check_output`), and, for trainable methods and for filters/solvers, its gradient is
finite; or it passes as "clear error" when it raises the exception type the case allows *and* the
message matches the case's fragment (which names the bad input). Anything else is "FAIL".

NaN/Inf inputs (decided here, documented in ``docs/results/stability.md``): `jaxdenoise.io` rejects
them at read time (or repairs them by policy) and `jaxdenoise.denoise` / `jaxdenoise.load` check the
buffers a method reads before calling it. A bare jitted ``apply`` cannot look at values, so its
behaviour on NaN/Inf is unspecified (NaN typically propagates); the NaN/Inf cases are therefore run
through `jaxdenoise.denoise`, which must raise `BuffersError` naming the buffer when the method reads
it, and must return a finite image when the method does not read it (the bad buffer is dropped).
Filters and solvers validate concrete (non-traced) inputs themselves and must raise their own error
naming the argument.

Sizes are tiny (8x8, 7x5, 1x1) so a method compiles at most four times (8x8 float32, 8x8 float16,
7x5, 1x1); jitted functions are cached per method.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import re
import traceback
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxdenoise import metrics
from jaxdenoise.buffers import ALL_FIELDS, Buffers, BuffersError

H, W = 8, 8

# Every case's camera (frame metadata): 5 units in front of the origin looking along +z, a 90-degree
# field of view (`jaxdenoise.view` conventions), float32 whatever the case's dtype.
CAMERA = {"world_to_camera": np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]], np.float32),
          "world_to_ndc": np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4.99], [0, 0, 1, 5]], np.float32)}
FIREFLY = 1e6


# == frames ======================================================================================
def _forward_diff(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """docs/architecture.md gradients: dx = I[y, x+1] - I[y, x], dy = I[y+1, x] - I[y, x]; 0 past the border."""
    dx = np.zeros_like(img)
    dy = np.zeros_like(img)
    dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy[:-1] = img[1:] - img[:-1]
    return dx, dy


def frame(h: int = H, w: int = W, *, seed: int = 0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A plausible noisy frame with every buffer, and its clean reference.

    The clean image is a smooth ramp with a vertical edge; colour = clean x (1 + 0.5 noise) >= 0 with
    the matching variance of the mean; gradients are the clean image's plus a little noise.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    ramp = 0.1 + 0.5 * (yy + 1) / (h + 1)
    edge = np.where(xx >= w // 2, 0.4, 0.0)
    clean = np.stack([ramp + edge, ramp, 0.6 - 0.3 * ramp + edge], -1)
    color = np.maximum(clean * (1.0 + 0.5 * rng.standard_normal(clean.shape)), 0.0)
    dx, dy = _forward_diff(clean)
    n = rng.standard_normal((h, w, 3)) + np.array([0.0, 0.0, 2.0])
    depth = rng.uniform(1.0, 5.0, (h, w, 1))
    d = {
        "color": color,
        "color_var": 0.25 * clean ** 2 / 4.0 + 1e-4,
        "albedo": rng.uniform(0.1, 0.9, (h, w, 3)),
        "albedo_var": rng.uniform(0.0, 1e-3, (h, w, 1)),
        "albedo2": rng.uniform(0.1, 0.9, (h, w, 3)),
        "albedo2_var": rng.uniform(0.0, 1e-3, (h, w, 1)),
        "normal": n / np.linalg.norm(n, axis=-1, keepdims=True),
        "normal_var": rng.uniform(0.0, 1e-3, (h, w, 1)),
        "position": np.concatenate([(xx[..., None] - w / 2) * 0.1, (yy[..., None] - h / 2) * 0.1, depth], -1),
        "position_var": rng.uniform(0.0, 1e-3, (h, w, 1)),
        "depth": depth,
        "depth_var": rng.uniform(0.0, 1e-3, (h, w, 1)),
        "visibility": rng.uniform(0.0, 1.0, (h, w, 1)),
        "visibility_var": rng.uniform(0.0, 1e-2, (h, w, 1)),
        "roughness": rng.uniform(0.0, 1.0, (h, w, 1)),
        "roughness_var": rng.uniform(0.0, 1e-3, (h, w, 1)),
        "dx": dx + 0.05 * rng.standard_normal(dx.shape),
        "dy": dy + 0.05 * rng.standard_normal(dy.shape),
    }
    return d, clean


def _with_firefly(d, ref):
    c = d["color"].copy()
    c[2, 3, :] = FIREFLY
    c[5, 1, 0] = FIREFLY
    v = d["color_var"].copy()
    v[2, 3, :] = FIREFLY ** 2 / 4.0  # a firefly's variance: one 1e6 sample among 4 spp
    v[5, 1, 0] = FIREFLY ** 2 / 4.0
    # the firefly also sits in the rendered gradients (gradient-domain rendering traces both)
    gx, gy = _forward_diff(c - d["color"])
    return dict(d, color=c, color_var=v, dx=d["dx"] + gx, dy=d["dy"] + gy), ref


def _black(d, ref):
    z = np.zeros_like(d["color"])
    return dict(d, color=z, color_var=z, dx=z, dy=z), np.zeros_like(ref)


def _zero_variance(d, ref):
    return {k: (np.zeros_like(v) if k.endswith("_var") else v) for k, v in d.items()}, ref


def _zero_albedo(d, ref):
    return dict(d, albedo=np.zeros_like(d["albedo"]), albedo2=np.zeros_like(d["albedo2"]),
                albedo_var=np.zeros_like(d["albedo_var"]), albedo2_var=np.zeros_like(d["albedo2_var"])), ref


def _zero_features(d, ref):
    """Every auxiliary feature exactly 0 (a renderer that wrote none: constant features, zero
    variance across the frame)."""
    feats = ("albedo", "albedo2", "normal", "position", "depth", "visibility", "roughness")
    return dict(d, **{k: np.zeros_like(v) for k, v in d.items() if k.split("_var")[0] in feats}), ref


def _depth_scaled(scale):
    def f(d, ref):
        return dict(d, depth=d["depth"] * scale, depth_var=d["depth_var"] * scale ** 2,
                    position=d["position"] * scale, position_var=d["position_var"] * scale ** 2), ref
    return f


def _depth_range(d, ref):
    rng = np.random.default_rng(7)
    depth = 10.0 ** rng.uniform(-3.0, 6.0, d["depth"].shape)  # 1e-3 .. 1e6 in one frame
    direction = d["position"] / np.linalg.norm(d["position"], axis=-1, keepdims=True)
    return dict(d, depth=depth, depth_var=(1e-3 * depth) ** 2, position=direction * depth,
                position_var=(1e-3 * depth) ** 2), ref


def _poison(field: str, value: float):
    def f(d, ref):
        a = d[field].copy()
        a.reshape(-1)[5 % a.size] = value
        return dict(d, **{field: a}), ref
    return f


@dataclasses.dataclass(frozen=True)
class Allowed:
    """The clear error a case accepts: exception types and a regex the message must match."""

    types: tuple[type, ...]
    pattern: str

    def matches(self, exc: BaseException) -> bool:
        return isinstance(exc, self.types) and re.search(self.pattern, str(exc)) is not None

    def describe(self) -> str:
        return f"{'/'.join(t.__name__ for t in self.types)} matching /{self.pattern}/"


@dataclasses.dataclass(frozen=True)
class Case:
    """One stiff input: how to build it, and which clear error (if any) it may raise instead."""

    name: str
    what: str
    modify: Callable = None  # (arrays, ref) -> (arrays, ref); None: the plain frame
    size: tuple[int, int] = (H, W)
    dtype: Any = np.float32
    allowed: Allowed | None = None
    bad_field: str | None = None  # NaN/Inf cases: the poisoned buffer (run through jaxdenoise.denoise)

    def arrays(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        d, ref = frame(*self.size)
        if self.modify is not None:
            d, ref = self.modify(d, ref)
        return {k: np.asarray(v, self.dtype) for k, v in d.items()}, np.asarray(ref, np.float32)

    def buffers(self) -> tuple[Buffers, np.ndarray]:
        d, ref = self.arrays()
        return Buffers(**d, spp=np.asarray(4.0, self.dtype), **CAMERA), ref


# A size error must say which size (or the minimum it needs); a dtype error must name the dtype.
SIZE_1x1 = Allowed((ValueError,), r"1 ?x ?1|\(1, 1[,)]|at least|too small|smaller than")
SIZE_7x5 = Allowed((ValueError,), r"7 ?x ?5|\(7, 5[,)]|at least|multiple of")
DTYPE_F16 = Allowed((TypeError, ValueError), r"float16|dtype")

CASES: tuple[Case, ...] = (
    Case("baseline", "plausible 8x8 noisy frame (sanity)"),
    Case("firefly_1e6", "two fireflies of 1e6 in colour (variance 2.5e11, also in dx/dy)", _with_firefly),
    Case("black", "all-black colour, zero variance, zero gradients", _black),
    Case("zero_variance", "every variance buffer exactly 0", _zero_variance),
    Case("zero_albedo", "albedo and albedo2 exactly 0 (demodulation by zero)", _zero_albedo),
    Case("zero_features", "every feature buffer (albedo, normal, position, depth, ...) exactly 0", _zero_features),
    Case("depth_1e-3", "depth and position scaled to 1e-3..5e-3", _depth_scaled(1e-3)),
    Case("depth_1e6", "depth and position scaled to 1e6..5e6", _depth_scaled(1e6)),
    Case("depth_range", "depth log-uniform over 1e-3..1e6 in one frame", _depth_range),
    Case("size_1x1", "1x1 image", size=(1, 1), allowed=SIZE_1x1),
    Case("size_7x5", "7x5 image (odd, not a multiple of any stride)", size=(7, 5), allowed=SIZE_7x5),
    Case("float16", "every buffer float16", dtype=np.float16, allowed=DTYPE_F16),
    Case("nan_color", "one NaN in colour", _poison("color", math.nan), bad_field="color"),
    Case("inf_color", "one +Inf in colour", _poison("color", math.inf), bad_field="color"),
    Case("nan_albedo", "one NaN in albedo", _poison("albedo", math.nan), bad_field="albedo"),
    Case("inf_depth", "one +Inf in depth", _poison("depth", math.inf), bad_field="depth"),
    Case("nan_dx", "one NaN in the x gradient", _poison("dx", math.nan), bad_field="dx"),
)
CASE_BY_NAME = {c.name: c for c in CASES}
VALUE_CASES = tuple(c for c in CASES if c.bad_field is None)  # run through the bare apply
BAD_VALUE_CASES = tuple(c for c in CASES if c.bad_field is not None)  # run through jaxdenoise.denoise


# == outcomes ====================================================================================
OK, CLEAR, UNAVAILABLE, FAIL = "ok", "clear error", "unavailable", "FAIL"


@dataclasses.dataclass(frozen=True)
class Outcome:
    status: str  # OK | CLEAR | UNAVAILABLE | FAIL
    detail: str = ""

    @property
    def passed(self) -> bool:
        return self.status in (OK, CLEAR, UNAVAILABLE)


def _exc(e: BaseException) -> str:
    msg = str(e).strip().splitlines()
    return f"{type(e).__name__}: {msg[0] if msg else ''}"[:300]


def _check_output(out: Any, shape: tuple[int, ...], scale: float, what: str = "output") -> str | None:
    """None if ``out`` is a sane image of ``shape``, else what is wrong.

    Sane: same shape, floating, every value finite, and max |out| <= 100 (max |input| + 1): a
    denoiser output is built from the input's radiance, so anything far beyond it is garbage (e.g.
    an unguarded 1 / eps).
    """
    try:
        a = np.asarray(out)
    except Exception as e:  # noqa: BLE001 - reported as the failure
        return f"{what} is not an array ({_exc(e)})"
    if a.shape != tuple(shape):
        return f"{what} has shape {a.shape}; expected {tuple(shape)}"
    if not np.issubdtype(a.dtype, np.floating):
        return f"{what} has dtype {a.dtype}; expected floating point"
    a = a.astype(np.float64)
    bad = int(a.size - np.count_nonzero(np.isfinite(a)))
    if bad:
        return f"{what} has {bad} non-finite value(s) of {a.size}"
    bound = 100.0 * (scale + 1.0)
    if a.size and float(np.max(np.abs(a))) > bound:
        return f"{what} reaches |{float(np.max(np.abs(a))):.3g}|, beyond 100 x (max |input| + 1) = {bound:.3g}"
    return None


def _tree_nonfinite(tree: Any) -> int:
    return sum(int(np.size(x) - np.count_nonzero(np.isfinite(np.asarray(x, np.float64))))
               for x in jax.tree_util.tree_leaves(tree))


# == methods =====================================================================================
@functools.lru_cache(maxsize=None)
def method(name: str):
    from jaxdenoise.methods import get

    return get(name)


@functools.lru_cache(maxsize=None)
def method_params(name: str) -> Any:
    """Shipped weights when the method has them, else ``init(PRNGKey(0))`` (random for networks)."""
    from jaxdenoise import api, checkpoint

    m = method(name)
    folder = m.weights_dir
    if folder is not None and (folder / checkpoint.PARAMS_FILE).is_file():
        return api.resolve(m)[1]
    return m.init(jax.random.PRNGKey(0))


def is_trainable(name: str) -> bool:
    m = method(name)
    return m.trainable and m.jittable and len(jax.tree_util.tree_leaves(method_params(name))) > 0


def _apply_fn(name: str) -> Callable:
    """The inference function `jaxdenoise.denoise` uses (jitted and cached per method and config by
    `jaxdenoise.inference.inference_fn`), so the suite and the API share one compile per shape."""
    from jaxdenoise.inference import inference_fn

    return inference_fn(method(name))


@functools.lru_cache(maxsize=None)
def _grad_fn(name: str) -> Callable:
    """d RelMSE(apply(params, buffers), ref) / d params: the gradient training follows (the method's
    own ``loss`` takes a method-specific batch, so the suite differentiates through ``apply``)."""
    m = method(name)
    return jax.jit(jax.grad(lambda p, b, ref: metrics.relmse(m.apply(p, b).astype(jnp.float32), ref)))


@functools.lru_cache(maxsize=None)
def _step_fn(name: str) -> Callable:
    m = method(name)

    def one(p, b):
        state = m.module.init_state(b, m.config)
        return m.module.step(p, state, b, m.config)[1]
    return jax.jit(one) if m.jittable else one


def check_method(name: str, case: Case, *, grad: bool = True) -> Outcome:
    """Run one method on one case (see the module docstring for the pass rule)."""
    from jaxdenoise import api
    from jaxdenoise.inference import prepare

    try:
        m = method(name)
        why = m.requirements()
    except Exception as e:  # noqa: BLE001 - an import error is this method's failure
        return Outcome(FAIL, f"cannot load method: {_exc(e)}")
    if why:
        return Outcome(UNAVAILABLE, why)
    buffers, ref = case.buffers()
    scale = float(np.max(np.abs(np.nan_to_num(np.asarray(buffers.color, np.float64), posinf=0.0))))
    params = method_params(name)
    if case.bad_field is not None:
        reads = case.bad_field in m.needs()
        try:
            if reads:  # must be refused before anything runs
                out = api.denoise(buffers, method=name, params=params)
            else:  # denoise's own steps, reusing the compiled function of the value cases
                out = _apply_fn(name)(params, prepare(m, buffers))
        except BuffersError as e:
            if reads and case.bad_field in str(e) and "NaN/Inf" in str(e):
                return Outcome(CLEAR, _exc(e))
            return Outcome(FAIL, f"unexpected error ({'reads' if reads else 'does not read'} "
                                 f"'{case.bad_field}'): {_exc(e)}")
        except Exception as e:  # noqa: BLE001
            return Outcome(FAIL, f"jaxdenoise.denoise raised {_exc(e)}; expected BuffersError naming "
                                 f"'{case.bad_field}' and NaN/Inf")
        if reads:
            return Outcome(FAIL, f"jaxdenoise.denoise accepted a NaN/Inf in '{case.bad_field}', which "
                                 f"the method reads")
        bad = _check_output(out, buffers.color.shape, scale)
        return Outcome(FAIL, bad) if bad else Outcome(OK, f"'{case.bad_field}' not read; dropped")

    b = buffers.only(m.needs())
    try:
        out = _apply_fn(name)(params, b)
        out = np.asarray(out)
    except Exception as e:  # noqa: BLE001
        if case.allowed is not None and case.allowed.matches(e):
            return Outcome(CLEAR, _exc(e))
        want = f"; allowed: {case.allowed.describe()}" if case.allowed else "; this case must succeed"
        return Outcome(FAIL, f"apply raised {_exc(e)}{want}\n{traceback.format_exc(limit=-3)}")
    bad = _check_output(out, buffers.color.shape, scale)
    if bad:
        return Outcome(FAIL, bad)
    if m.recurrent:
        try:
            bad = _check_output(_step_fn(name)(params, b), buffers.color.shape, scale, "step output")
        except Exception as e:  # noqa: BLE001
            bad = f"step raised {_exc(e)} although apply succeeded"
        if bad:
            return Outcome(FAIL, bad)
    if grad and is_trainable(name):
        try:
            g = _grad_fn(name)(params, b, ref)
        except Exception as e:  # noqa: BLE001
            return Outcome(FAIL, f"gradient raised {_exc(e)} although apply succeeded")
        n = _tree_nonfinite(g)
        if n:
            return Outcome(FAIL, f"gradient w.r.t. params has {n} non-finite value(s)")
        return Outcome(OK, "output and gradient finite")
    return Outcome(OK, "output finite")


# == filters =====================================================================================
# The bandwidth-like parameters of every filter are all set to one value `p` from PARAM_VALUES.
# For `gaussian` p is sigma (p -> 0: zero bandwidth, p -> inf: infinite bandwidth); for the
# bilateral family p is lambda = 1 / (2 theta^2) (p -> 0: infinite bandwidth, p -> inf: zero).
PARAM_VALUES: tuple[float, ...] = (0.0, 1e-30, 1e-6, 1.0, 1e6, 1e30)
PARAM_INF = math.inf  # not finite: must give a finite output or a FilterError naming the parameter
RADIUS = 1  # static window radius: 3x3 windows reach neighbours and borders, and compile fast


@dataclasses.dataclass(frozen=True)
class FilterSpec:
    """How the suite calls one public filter: ``call(buffers, p) -> array``.

    ``source(buffers)`` is the input the output is made of: the output must have its pixel grid and
    channels (the last three axes) and, for a normalized (``convex``) filter, stay inside its
    per-channel range over every other axis.
    """

    call: Callable[[Buffers, Any], Any]
    reads: frozenset[str]  # buffers it reads (NaN in another one is not its business)
    params: tuple[str, ...]  # the argument names that receive p (a clear error names one of them)
    source: Callable[[Buffers], Any] = lambda b: b.color
    convex: bool = True  # output is a convex combination of input pixels: stays in the input's range
    static_param: bool = False  # p is a static (non-traced, non-differentiable) threshold
    grad_field: str = "color"  # the buffer the gradient is taken w.r.t. (besides p)


def _feats(b: Buffers):
    names = ["position", "normal", "albedo", "albedo2", "visibility", "depth"]
    return [getattr(b, n) for n in names], [getattr(b, n + "_var") for n in names]


def _volume(b: Buffers) -> Buffers:
    """A 3-frame sequence: the frame, and two copies whose colour is scaled by 0.9 and 1.1."""
    def stack(a):
        if a is None or np.ndim(a) == 0:
            return a
        return jnp.stack([a, a, a])
    v = jax.tree_util.tree_map(stack, b)
    return v.replace(color=v.color * jnp.asarray([0.9, 1.0, 1.1], v.color.dtype)[:, None, None, None])


def _filters_mod():
    from jaxdenoise import filters
    return filters


def _taa(b: Buffers, p):
    """Two TAA steps under one camera (world = NDC): a history made from half the colour, then the
    colour; ``alpha = 1 / (1 + p)`` (p 0: no history; p inf: alpha 0, refused)."""
    f, cam, alpha = _filters_mod(), np.eye(4, dtype=np.float32), 1.0 / (1.0 + p)
    state, _ = f.taa_step(f.taa_init(np.shape(b.color)), 0.5 * b.color, b.position, b.normal, cam, alpha=alpha)
    return f.taa_step(state, b.color, b.position, b.normal, cam, alpha=alpha)[1]


def _accumulate(b: Buffers, p):
    """Two accumulation steps under one camera (world = NDC), the colour both times (a running mean of
    reprojected pixels of it, the history's clamp at 4x off: convex); at most ``1 + p`` frames (p inf:
    refused), tangent-plane tolerance 0.02."""
    f, cam = _filters_mod(), np.eye(4, dtype=np.float32)
    one = lambda st: f.accumulate_step(st, b.color, b.position, b.normal, cam, frames=1.0 + p,  # noqa: E731
                                       tolerance=0.02, clamp=0.0)
    return one(one(f.taa_init(np.shape(b.color)))[0])[1]


def _prefiltered(b: Buffers, p):
    f, v = _filters_mod().prefilter_features(b.position, b.position_var, radius=RADIUS, patch_radius=1, lam=p)
    return jnp.concatenate([f, v], -1)


_FEATURE_READS = frozenset({"position", "normal", "albedo", "albedo2", "visibility", "depth",
                            "position_var", "normal_var", "albedo_var", "albedo2_var", "visibility_var",
                            "depth_var"})

FILTERS: dict[str, FilterSpec] = {
    "gaussian": FilterSpec(
        lambda b, p: _filters_mod().gaussian(b.color, p, radius=RADIUS),
        frozenset({"color"}), ("sigma",)),
    "bilateral": FilterSpec(
        lambda b, p: _filters_mod().bilateral(b.color, p, p, radius=RADIUS),
        frozenset({"color"}), ("lam_spatial", "lam_range")),
    "cross_bilateral": FilterSpec(
        lambda b, p: _filters_mod().cross_bilateral(b.color, b.color_var, *_feats(b), p, p, [p] * 6, radius=RADIUS),
        frozenset({"color", "color_var"}) | _FEATURE_READS, ("lam_spatial", "lam_color", "lam_features")),
    "spatiotemporal_cross_bilateral": FilterSpec(
        lambda b, p: _filters_mod().spatiotemporal_cross_bilateral(
            _volume(b).color, _volume(b).color_var, *_feats(_volume(b)), p, p, [p] * 6, radius=RADIUS,
            lam_temporal=p),
        frozenset({"color", "color_var"}) | _FEATURE_READS,
        ("lam_spatial", "lam_color", "lam_features", "lam_temporal"), source=lambda b: _volume(b).color),
    "cross_nlm": FilterSpec(
        lambda b, p: _filters_mod().cross_nlm(b.color, b.color_var, *_feats(b), p, [p] * 6, radius=RADIUS),
        frozenset({"color", "color_var"}) | _FEATURE_READS, ("lam_patch", "lam_features")),
    "prefilter_features": FilterSpec(
        _prefiltered, frozenset({"position", "position_var"}), ("lam",), grad_field="position",
        source=lambda b: jnp.concatenate([b.position, b.position_var], -1)),
    "remove_spikes": FilterSpec(
        lambda b, p: _filters_mod().remove_spikes(b.color, n_std=p),
        frozenset({"color"}), ("n_std",), static_param=True),
    # scales a spike down keeping its hue: not a convex combination of input pixels
    "clamp_outliers": FilterSpec(
        lambda b, p: _filters_mod().clamp_outliers(b.color, p, 0.2),
        frozenset({"color"}), ("factor",), static_param=True, convex=False),
    # scales each pixel by a smooth gain: not a convex combination of input pixels
    "match_level": FilterSpec(
        lambda b, p: _filters_mod().match_level(b.color, b.albedo, p, 1e-3),
        frozenset({"color", "albedo"}), ("sigma",), static_param=True, convex=False),
    "match_to_input": FilterSpec(
        lambda b, p: _filters_mod().match_to_input(b.albedo, b.color, p, spike=2.0, floor=0.2, max_gain=1.1),
        frozenset({"color", "albedo"}), ("sigma",), static_param=True, convex=False, source=lambda b: b.albedo,
        grad_field="albedo"),
    # the history is clamped to the frame's 3x3 range, then blended with the frame: convex
    "taa_step": FilterSpec(_taa, frozenset({"color", "position", "normal"}), ("alpha",), static_param=True),
    # a running mean of the frame and its reprojected history (itself such a mean): convex
    "accumulate_step": FilterSpec(_accumulate, frozenset({"color", "position", "normal"}), ("frames",),
                                  static_param=True),
    # a normalised cross-bilateral average of the image's pixels: convex; range_sigma = p + 1e-3 (it must be > 0)
    "refine": FilterSpec(
        lambda b, p: _filters_mod().refine(b.color, b.albedo, b.normal, sigma=1.0, range_sigma=p + 1e-3,
                                           albedo_sigma=0.1, normal_sigma=0.3, radius=RADIUS),
        frozenset({"color", "albedo", "normal"}), ("range_sigma",), static_param=True),
}
# Public names of jaxdenoise.filters that are not image filters (helpers and the error type; `exact_mask`
# returns a boolean mask by exact comparisons: nothing to overflow, no parameter, no gradient; `taa_init`,
# `reproject`, `TaaState`, `hdr_weight` and `check_taa_settings` are the parts of `taa_step`, which has its entry;
# `level_gain` and `input_gain` are the gains `match_level` and `match_to_input` multiply by, exercised by their
# entries in every case; `check_refine_settings` refuses a config's settings for `refine`).
FILTER_HELPERS = frozenset({"FilterError", "gaussian_kernel_1d", "drop_constant_features", "DELTA", "ZETA",
                            "check_match_settings", "check_exact_window", "exact_mask", "check_taa_settings",
                            "taa_init", "reproject", "TaaState", "hdr_weight", "check_refine_settings",
                            "level_gain", "input_gain"})


def public_filters() -> list[str]:
    """Every public filter of `jaxdenoise.filters` (its ``__all__`` minus helpers)."""
    f = _filters_mod()
    return [n for n in getattr(f, "__all__", []) if n not in FILTER_HELPERS and callable(getattr(f, n, None))]


@functools.lru_cache(maxsize=None)
def _filter_fn(name: str) -> Callable:
    spec = FILTERS[name]
    return jax.jit(spec.call, static_argnums=(1,) if spec.static_param else ())


@functools.lru_cache(maxsize=None)
def _filter_grad_fn(name: str) -> Callable:
    """Gradient of a weighted sum of the output w.r.t. the filtered buffer and (unless static) ``p``:
    the two paths training differentiates (LBF's MLP drives ``p``)."""
    spec = FILTERS[name]

    def loss(x, p, b):
        out = spec.call(b.replace(**{spec.grad_field: x}), p)
        w = jnp.linspace(0.5, 1.5, out.size, dtype=jnp.float32).reshape(out.shape)
        return jnp.sum(out.astype(jnp.float32) * w)
    if spec.static_param:
        return jax.jit(jax.grad(loss), static_argnums=(1,))
    return jax.jit(jax.grad(loss, argnums=(0, 1)))


def check_filter(name: str, case: Case, p: float = 1.0, *, grad: bool = True) -> Outcome:
    """Run one public filter on one case with every bandwidth parameter set to ``p``.

    Finite inputs run under ``jit`` (the way methods call filters; one compile per filter and image
    shape), so nothing but the numerics can keep the output finite. Inputs that must be refused (a
    NaN/Inf in a buffer the filter reads, a non-finite ``p``) run eagerly, where the filter checks
    concrete values, and must raise `FilterError` naming the argument. ``grad``: the gradient
    w.r.t. the image and ``p`` must be finite too."""
    from jaxdenoise.filters import FilterError

    spec = FILTERS[name]
    buffers, _ = case.buffers()
    bad_param = not math.isfinite(p)
    bad_value = case.bad_field is not None and case.bad_field in spec.reads
    pv = float(p) if spec.static_param else jnp.asarray(p, jnp.float32)
    try:
        if bad_param or bad_value:  # eager: the filter's value checks only run on concrete arguments
            out = spec.call(buffers, p)
        else:  # jitted (as methods call it), compiled once per filter and image shape
            out = _filter_fn(name)(buffers, pv)
        out = np.asarray(out)
    except Exception as e:  # noqa: BLE001
        if bad_value and isinstance(e, FilterError) and re.search(r"argument '[^']+' has \d+ NaN/Inf", str(e)):
            return Outcome(CLEAR, _exc(e))
        if bad_param and isinstance(e, FilterError) and any(f"'{n}" in str(e) for n in spec.params):
            return Outcome(CLEAR, _exc(e))
        if case.allowed is not None and case.allowed.matches(e):
            return Outcome(CLEAR, _exc(e))
        return Outcome(FAIL, f"raised {_exc(e)}\n{traceback.format_exc(limit=-3)}")
    if bad_value:
        return Outcome(FAIL, f"accepted a NaN/Inf in '{case.bad_field}' (which it reads) without an error")
    if bad_param:
        return Outcome(FAIL, f"accepted {spec.params[0]} = {p} without an error")
    src = np.asarray(spec.source(buffers), np.float64)
    finite = src[np.isfinite(src)]
    scale = float(np.max(np.abs(finite))) if finite.size else 0.0
    bad = _check_output(out, src.shape[-3:], scale)
    if bad:
        return Outcome(FAIL, bad)
    if spec.convex and case.bad_field is None:
        axes = tuple(range(src.ndim - 1))
        lo, hi = src.min(axis=axes), src.max(axis=axes)
        # rounding of the normalized weighted sum: float16 inputs are rounded once more
        tol = (1e-3 if np.dtype(case.dtype) == np.float16 else 1e-5) * (scale + 1.0)
        o = out.astype(np.float64)
        if np.any(o < lo - tol) or np.any(o > hi + tol):
            return Outcome(FAIL, f"output [{o.min():.6g}, {o.max():.6g}] leaves the input's per-channel range "
                                 f"[{lo}, {hi}] (tolerance {tol:.2g}); a normalized filter cannot do that")
    if grad and case.bad_field is None:
        try:
            g = _filter_grad_fn(name)(getattr(buffers, spec.grad_field), pv, buffers)
        except Exception as e:  # noqa: BLE001
            return Outcome(FAIL, f"gradient raised {_exc(e)}")
        n = _tree_nonfinite(g)
        if n:
            return Outcome(FAIL, f"gradient w.r.t. ({spec.grad_field}, parameter) has {n} non-finite value(s)")
        return Outcome(OK, "output in range, gradient finite")
    return Outcome(OK, "output in range")


def check_gaussian_default_radius(sigma: float = 1e30) -> Outcome:
    """`gaussian` with its default radius ``ceil(3 sigma)`` and sigma -> infinity: the blur must be
    finite (infinite bandwidth with border renormalization is the per-channel mean, tolerance 1e-5
    relative) or refused with a `FilterError` naming sigma / radius."""
    from jaxdenoise import filters

    img = CASE_BY_NAME["baseline"].buffers()[0].color
    try:
        out = np.asarray(filters.gaussian(img, sigma))
    except filters.FilterError as e:
        if "'sigma'" in str(e) or "'radius'" in str(e):
            return Outcome(CLEAR, _exc(e))
        return Outcome(FAIL, f"FilterError not naming sigma/radius: {_exc(e)}")
    except Exception as e:  # noqa: BLE001
        return Outcome(FAIL, f"gaussian(image, {sigma:g}) raised {_exc(e)}, not a FilterError naming sigma/radius")
    bad = _check_output(out, img.shape, float(np.max(np.abs(img))))
    if bad:
        return Outcome(FAIL, bad)
    mean = np.broadcast_to(np.asarray(img, np.float64).mean(axis=(0, 1)), img.shape)
    if not np.allclose(out, mean, rtol=1e-5, atol=0):
        return Outcome(FAIL, f"infinite bandwidth should give the per-channel mean; max deviation "
                             f"{float(np.max(np.abs(out - mean))):.3g}")
    return Outcome(OK, "per-channel mean")


# == screened Poisson solvers =====================================================================
ALPHAS: tuple[float, ...] = (1e-6, 1e-3, 1.0, 1e3, 1e6)
BAD_ALPHAS: tuple[float, ...] = (0.0, -1.0, math.inf, math.nan)
SOLVER_CASES = ("baseline", "firefly_1e6", "black", "size_1x1", "size_7x5", "float16")


def public_solvers() -> list[str]:
    """Every screened-Poisson reconstruction in `jaxdenoise.solvers` (``poisson_*``, signature
    ``(base, dx, dy, alpha)``)."""
    from jaxdenoise import solvers

    return [n for n in solvers.__all__ if n.startswith("poisson_")]


@functools.lru_cache(maxsize=None)
def _solver_fn(name: str) -> Callable:
    from jaxdenoise import solvers

    return jax.jit(getattr(solvers, name))


@functools.lru_cache(maxsize=None)
def _solver_grad_fn(name: str) -> Callable:
    from jaxdenoise import solvers

    fn = getattr(solvers, name)

    def loss(base, dx, dy, alpha):
        out = fn(base, dx, dy, alpha)
        w = jnp.linspace(0.5, 1.5, out.size, dtype=jnp.float32).reshape(out.shape)
        return jnp.sum(out.astype(jnp.float32) * w)
    return jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))


GRADIENTS = ("rendered", "exact", "near")


def solver_inputs(case: Case, gradients: str = "rendered") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(base, dx, dy) of a case. ``gradients``: ``"rendered"`` (the case's noisy dx, dy),
    ``"exact"`` (the base's own forward differences: every solver must return the base) or
    ``"near"`` (exact plus 1e-4 noise, the inconsistency float16 rounding leaves: the result must
    stay close to the base, the stiff regime of reweighted L1 solvers)."""
    d, _ = case.arrays()
    base = d["color"]
    if gradients == "rendered":
        return base, d["dx"], d["dy"]
    if gradients not in GRADIENTS:
        raise ValueError(f"solver_inputs: 'gradients' is {gradients!r}; expected one of {GRADIENTS}")
    dx, dy = _forward_diff(base.astype(np.float64))
    if gradients == "near":
        rng = np.random.default_rng(3)
        dx, dy = _forward_diff(base.astype(np.float64))
        dx = dx + 1e-4 * rng.standard_normal(dx.shape) * (dx != 0)
        dy = dy + 1e-4 * rng.standard_normal(dy.shape) * (dy != 0)
    return base, dx.astype(base.dtype), dy.astype(base.dtype)


def check_solver(name: str, case: Case, alpha: float, *, gradients: str = "rendered", grad: bool = False,
                 primal_tol: float = 1e-2) -> Outcome:
    """Run one solver on ``solver_inputs(case, gradients)``. With ``"exact"`` or ``"near"`` gradients
    the result must also return the primal (the base) to ``primal_tol`` x (max |base| + 1): every
    screened-Poisson energy is 0 there (near: almost 0)."""
    from jaxdenoise.solvers import SolverError

    exact = gradients != "rendered"
    base, dx, dy = solver_inputs(case, gradients)
    finite_alpha = math.isfinite(alpha) and alpha > 0
    try:
        if finite_alpha and case.bad_field is None:
            out = _solver_fn(name)(base, dx, dy, jnp.asarray(alpha, jnp.float32))  # one compile per shape
        else:  # eager: the solver's value checks only run on concrete arguments
            from jaxdenoise import solvers
            out = getattr(solvers, name)(base, dx, dy, alpha)
        out = np.asarray(out)
    except Exception as e:  # noqa: BLE001
        if not finite_alpha and isinstance(e, SolverError) and "'alpha'" in str(e):
            return Outcome(CLEAR, _exc(e))
        if case.bad_field is not None and isinstance(e, SolverError) and "NaN/Inf" in str(e):
            return Outcome(CLEAR, _exc(e))
        if case.allowed is not None and case.allowed.matches(e):
            return Outcome(CLEAR, _exc(e))
        return Outcome(FAIL, f"raised {_exc(e)}\n{traceback.format_exc(limit=-3)}")
    if case.bad_field is not None:
        return Outcome(FAIL, f"accepted a NaN/Inf in '{case.bad_field}' without an error")
    if not finite_alpha:
        return Outcome(FAIL, f"accepted alpha = {alpha} without an error")
    scale = float(np.max(np.abs(np.concatenate([a.ravel() for a in (base, dx, dy)]).astype(np.float64))))
    bad = _check_output(out, base.shape, scale)
    if bad:
        return Outcome(FAIL, bad)
    if exact:
        err = float(np.max(np.abs(out.astype(np.float64) - base.astype(np.float64))))
        tol = primal_tol * (float(np.max(np.abs(base.astype(np.float64)))) + 1.0)
        if err > tol:
            return Outcome(FAIL, f"{gradients} gradients: max |out - base| = {err:.3g} > {tol:.3g}")
    if grad:
        try:
            g = _solver_grad_fn(name)(jnp.asarray(base), jnp.asarray(dx), jnp.asarray(dy),
                                      jnp.asarray(alpha, jnp.float32))
        except Exception as e:  # noqa: BLE001
            return Outcome(FAIL, f"gradient raised {_exc(e)}")
        n = _tree_nonfinite(g)
        if n:
            return Outcome(FAIL, f"gradient w.r.t. (base, dx, dy, alpha) has {n} non-finite value(s)")
    return Outcome(OK, "finite" + (", returns the primal" if exact else "") + (", gradient finite" if grad else ""))


def _all_fields_present() -> bool:
    """Every case carries every buffer of a uniformly sampled frame (so a method's ``needs`` decides
    what it reads); the per-pixel ``spp_map`` belongs to adaptive frames only, the ``emission`` layer to
    gradient frames that leave it out of dx, dy (tests/test_gradient_emission.py)."""
    d, _ = CASES[0].arrays()
    return set(d) | {"spp"} | set(CAMERA) == set(ALL_FIELDS) - {"spp_map", "emission"}
