"""The buffer integrator: a Dr.Jit path tracer that records, per sample, radiance and the auxiliary
features the denoisers read, and reduces them to per-pixel means and variances of the mean.

Light transport follows Mitsuba 3's own ``path`` integrator (``src/integrators/path.cpp``): unidirectional
path tracing with next-event estimation, MIS (power heuristic) between BSDF and emitter sampling, and
Russian roulette from ``rr_depth`` on. ``max_depth`` has Mitsuba's meaning (1 = only emitters seen
directly, 2 = direct illumination, 3 = one indirect bounce as in Chaitanya 2017 Sec. 3.2).

Features (Kalantari 2015 Sec. 3.2 "primary features"; Chaitanya 2017 Sec. 3.2; Yang 2019 Sec. 3.1;
Guo 2019 Sec. 5.1). The *feature vertex* of a path is its first intersection whose BSDF has a
non-delta (smooth) lobe; delta bounces (mirrors, smooth glass) are followed up to ``max_depth``:

- ``albedo``: ``bsdf.eval_diffuse_reflectance`` at the feature vertex (the texture value);
- ``albedo2``: the same at the next intersection of the path after the feature vertex (second hit);
- ``normal``: world-space shading normal at the feature vertex, in [-1, 1];
- ``position``: world position of the feature vertex;
- ``depth``: distance from the camera to the first intersection (the primary ray's hit distance);
- ``visibility``: 1 if the next-event shadow ray of the feature vertex reaches the light (a light
  sample on the light's back side or with zero pdf counts as 0), so its pixel mean is the fraction
  of shadow rays that reach the light;
- ``roughness``: per-BSDF scalar: its GGX/Beckmann ``alpha`` (mean of ``alpha_u``/``alpha_v``, or
  ``roughness`` for ``principled``) when it has one, else 1 for BSDFs with a diffuse lobe, else 0
  (pure delta BSDFs).

Samples whose path has no feature vertex (the camera ray misses, or only delta surfaces were hit)
record 0 for every feature (albedo 0, normal 0, position 0, visibility 0, roughness 0); ``depth`` is 0
when the camera ray misses. Radiance is linear HDR and unclipped.

Each sample is one camera ray through a uniformly jittered point of its pixel (a box pixel filter),
so the samples of a pixel are independent and identically distributed: their sample mean is the
pixel value and ``sample variance / n`` its variance of the mean.
"""
from __future__ import annotations

import dataclasses
import hashlib
from typing import Any

import numpy as np

from .mitsuba_setup import is_vectorized
from jaxdenoise.errors import JaxdenoiseError

# feature -> channel count, in `jaxdenoise.buffers.CHANNELS` order.
FEATURE_DIMS: dict[str, int] = {
    "albedo": 3, "albedo2": 3, "normal": 3, "position": 3, "depth": 1, "visibility": 1, "roughness": 1,
}
FEATURES: tuple[str, ...] = tuple(FEATURE_DIMS)
# `trace(record={EMISSION})`: what a surface emitter seen directly gives the sample (its camera ray's first
# hit emits toward the camera: the depth-0 term of its radiance where that ray hits a shape; an environment
# seen directly is not counted), which gradient-domain frames keep out of dx, dy.
EMISSION = "emission"


@dataclasses.dataclass(frozen=True)
class PathSettings:
    """Light-transport settings of the buffer integrator (Mitsuba ``path`` names and meanings)."""

    max_depth: int = 8
    rr_depth: int = 5

    def __post_init__(self) -> None:
        if not isinstance(self.max_depth, int) or self.max_depth < 1:
            raise JaxdenoiseError(f"max_depth must be an int >= 1 (1 = emitters only), got {self.max_depth!r}")
        if not isinstance(self.rr_depth, int) or self.rr_depth < 1:
            raise JaxdenoiseError(f"rr_depth must be an int >= 1, got {self.rr_depth!r}")


def derive_seed(*parts: Any) -> int:
    """A 31-bit seed from any printable parts (stable across processes and Python versions)."""
    h = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(h[:4], "little") & 0x7FFFFFFF


# --------------------------------------------------------------------------------------------------
# Roughness per BSDF
# --------------------------------------------------------------------------------------------------
def bsdf_roughness(bsdf) -> float:
    """The scalar roughness of one BSDF (see module docstring for the rule)."""
    import mitsuba as mi

    params = mi.traverse(bsdf)
    vals: list[float] = []
    for key in params.keys():
        parts = key.split(".")
        if any(p in ("alpha", "alpha_u", "alpha_v", "roughness") for p in parts[-2:]) and parts[-1] in (
                "alpha", "alpha_u", "alpha_v", "roughness", "value", "data"):
            try:
                arr = np.asarray(params[key], dtype=np.float64).ravel()
            except Exception:  # noqa: BLE001 - a texture we cannot read as numbers: skip it
                continue
            if arr.size:
                vals.append(float(arr.mean()))
    if vals:
        return float(np.mean(vals))
    flags = bsdf.flags()
    if mi.has_flag(flags, mi.BSDFFlags.Diffuse):
        return 1.0
    return 0.0


def scene_bsdfs(scene) -> list:
    out = []
    seen = set()
    for shape in scene.shapes():
        b = shape.bsdf()
        if b is not None and id(b) not in seen:
            seen.add(id(b))
            out.append(b)
    return out


class RoughnessLookup:
    """Maps a (vectorized) BSDF pointer to its roughness: a gather in a table indexed by the
    registry id of the BSDF (LLVM variants), or a dict lookup (scalar variant)."""

    def __init__(self, scene) -> None:
        import drjit as dr
        import mitsuba as mi

        self.vectorized = is_vectorized()
        bsdfs = scene_bsdfs(scene)
        self.values = {id(b): bsdf_roughness(b) for b in bsdfs}
        if self.vectorized:
            ids = [int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(b))[0]) for b in bsdfs]
            table = np.zeros(max(ids + [0]) + 1, np.float32)
            for b, i in zip(bsdfs, ids):
                table[i] = self.values[id(b)]
            self.table = mi.Float(table)

    def __call__(self, bsdf, active):
        import drjit as dr
        import mitsuba as mi

        if self.vectorized:
            idx = dr.reinterpret_array(mi.UInt32, bsdf)
            return dr.gather(mi.Float, self.table, idx, active)
        return self.values.get(id(bsdf), 0.0) if (active and bsdf is not None) else 0.0


# --------------------------------------------------------------------------------------------------
# The path tracer
# --------------------------------------------------------------------------------------------------
def mis_weight(pdf_a, pdf_b):
    import drjit as dr

    a2 = dr.square(pdf_a)
    b2 = dr.square(pdf_b)
    w = a2 / (a2 + b2)
    # Guard: both pdfs 0 (or inf/inf) gives NaN; such a sample carries no contribution.
    return dr.select(dr.isfinite(w), w, 0.0)


def trace(scene, sampler, ray, active, *, settings: PathSettings, record: frozenset[str],
          roughness: RoughnessLookup | None = None) -> dict:
    """Trace one path per lane of ``ray``; returns ``{"color": Spectrum, <feature>: value, ...}``
    for the features in ``record`` (values per sample, 0 where undefined; see module docstring),
    ``vertices`` (the path's vertex count) and, when ``record`` holds `EMISSION`, ``emission``: the part
    of ``color`` that the camera ray's first hit emits where it hits a shape (a Spectrum; 0 where it hits
    no emitter or nothing: an environment seen directly is not counted).

    Which features are recorded is static (a Python set), so a feature left out costs nothing.
    """
    import drjit as dr
    import mitsuba as mi

    vec = is_vectorized()
    Float = mi.Float
    bsdf_ctx = mi.BSDFContext()
    want = {f: (f in record) for f in FEATURES}
    if want["roughness"] and roughness is None:
        roughness = RoughnessLookup(scene)

    feats = {}
    for f in FEATURES:
        if want[f]:
            feats[f] = mi.Color3f(0.0) if FEATURE_DIMS[f] == 3 else Float(0.0)
    if EMISSION in record:
        feats[EMISSION] = mi.Spectrum(0.0)
    state = dict(
        ray=mi.Ray3f(ray), depth=mi.UInt32(0), L=mi.Spectrum(0.0), beta=mi.Spectrum(1.0), eta=Float(1.0),
        active=mi.Bool(active), prev_si=dr.zeros(mi.SurfaceInteraction3f), prev_pdf=Float(1.0),
        prev_delta=mi.Bool(True), found=mi.Bool(False), found2=mi.Bool(False), feats=feats,
    )

    def cond(s):
        return s["active"]

    def body(s):
        ray = s["ray"]
        depth = s["depth"]
        active = s["active"]
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=depth == 0,
                                 active=active)
        valid = si.is_valid()
        bsdf = si.bsdf(ray) if (vec or valid) else None  # scalar: no BSDF lookup on a miss (null shape)

        # Direct emission, MIS-weighted against the previous bounce's emitter sampling.
        ds = mi.DirectionSample3f(scene, si=si, ref=s["prev_si"])
        if vec:
            em_pdf = scene.pdf_emitter_direction(s["prev_si"], ds, active & _not(s["prev_delta"]))
            mis_bsdf = dr.select(s["prev_delta"], 1.0, mis_weight(s["prev_pdf"], em_pdf))
            emitted = dr.select(active, s["beta"] * mis_bsdf * ds.emitter.eval(si, active), 0.0)
            L = s["L"] + emitted
        else:
            # Scalar variant: masks do not protect null pointers (no emitter hit, no surface), so the
            # same estimator is written with Python branches.
            emitted = mi.Spectrum(0.0)
            if active and ds.emitter is not None:
                mis_bsdf = 1.0 if s["prev_delta"] else mis_weight(
                    s["prev_pdf"], scene.pdf_emitter_direction(s["prev_si"], ds, True))
                emitted = s["beta"] * mis_bsdf * ds.emitter.eval(si, True)
            L = s["L"] + emitted
            if EMISSION in record and depth == 0 and valid:
                s = dict(s, feats=dict(s["feats"], **{EMISSION: emitted}))
            if not (active and valid):
                return dict(s, L=L, active=False, found2=s["found2"] or (active and s["found"]))

        active_next = active & (depth + 1 < settings.max_depth) & valid
        smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)

        # Next-event estimation; the shadow ray is traced explicitly so that its outcome doubles as
        # the direct-light visibility feature.
        active_em = active_next & smooth
        ds_em, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(active_em), False, active_em)
        active_em &= ds_em.pdf != 0.0
        shadow = si.spawn_ray_to(ds_em.p)
        occluded = scene.ray_test(shadow, active_em)
        reaches = active_em & _not(occluded) & (dr.max(em_weight) > 0.0)
        wo = si.to_local(ds_em.d)
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, reaches)
        mis_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, bsdf_pdf))
        L = L + dr.select(reaches, s["beta"] * bsdf_val * em_weight * mis_em, 0.0)

        # Features.
        f = dict(s["feats"])
        if vec and EMISSION in record:
            f[EMISSION] = dr.select((depth == 0) & valid, emitted, f[EMISSION])
        found, found2 = s["found"], s["found2"]
        if want["depth"]:
            f["depth"] = dr.select(active & (depth == 0) & valid, si.t, f["depth"])
        at_feat = active & _not(found) & valid & smooth
        at_second = active & found & _not(found2)
        f = feature_vertex(f, si, bsdf, at_feat, reaches, roughness)
        if want["albedo2"]:
            at2 = at_second & valid
            f["albedo2"] = dr.select(at2, bsdf.eval_diffuse_reflectance(si, at2), f["albedo2"])
        found2 = found2 | at_second
        found = found | at_feat

        # BSDF sampling.
        bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(active_next), sampler.next_2d(active_next),
                                      active_next)
        beta = s["beta"] * bsdf_weight
        eta = s["eta"] * bs.eta
        new_ray = si.spawn_ray(si.to_world(bs.wo))

        # Russian roulette (path.cpp: cancels eta^2 so the throughput is unitless, capped at 0.95).
        beta_max = dr.max(mi.unpolarized_spectrum(beta))
        rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
        rr_active = depth + 1 >= settings.rr_depth  # path.cpp counts this vertex first
        beta = dr.select(rr_active, beta * dr.rcp(rr_prob), beta)
        rr_continue = sampler.next_1d(active_next) < rr_prob
        active_next = active_next & (_not(rr_active) | rr_continue) & (beta_max != 0.0)

        return dict(ray=new_ray,
                    depth=depth + 1, L=L, beta=beta, eta=eta, active=active_next, prev_si=si,
                    prev_pdf=bs.pdf, prev_delta=mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                    found=found, found2=found2, feats=f)

    if vec:
        # The sampler is loop state too: its RNG must advance from one bounce to the next.
        state = dr.while_loop((state, sampler), lambda s, smp: cond(s), lambda s, smp: (body(s), smp),
                              label="data_gen.trace")[0]
    else:
        while state["active"]:
            state = body(state)
    out = {"color": state["L"]}
    out.update(state["feats"])
    out["vertices"] = Float(state["depth"])   # path vertices traced: a sample's cost (adaptive sampling)
    return out


def feature_vertex(feats: dict, si, bsdf, at_feat, reaches, roughness) -> dict:
    """``feats`` with the feature vertex's values where ``at_feat``: ``albedo``, ``normal``,
    ``position``, ``roughness`` and ``visibility`` (where ``reaches``: the vertex's light sample got
    through), each only if ``feats`` holds it (module docstring; ``albedo2`` is a vertex later). The
    one definition `trace` and the gradient tracer (`data_gen.gpt`) record."""
    import drjit as dr
    import mitsuba as mi

    f = dict(feats)
    if "albedo" in f:
        f["albedo"] = dr.select(at_feat, bsdf.eval_diffuse_reflectance(si, at_feat), f["albedo"])
    if "normal" in f:
        f["normal"] = dr.select(at_feat, mi.Color3f(si.sh_frame.n), f["normal"])
    if "position" in f:
        f["position"] = dr.select(at_feat, mi.Color3f(si.p), f["position"])
    if "roughness" in f:
        f["roughness"] = dr.select(at_feat, roughness(bsdf, at_feat), f["roughness"])
    if "visibility" in f:
        f["visibility"] = dr.select(at_feat & reaches, 1.0, f["visibility"])
    return f


def _not(mask):
    # `~` on the scalar variant's Python bools is integer negation (~True == -2): compare instead.
    return mask == False  # noqa: E712
