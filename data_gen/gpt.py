"""Gradient-domain path tracing with the reconnection shift (Kettunen et al. 2015, "Gradient-Domain
Path Tracing", Sec. 4 and 5; the shift of Lehtinen et al. 2013, Sec. 5.2, extended with MIS).

One Dr.Jit wavefront traces, per lane, a *base* path through its pixel and shifts it into four
*offset* paths through the right, lower, left and upper neighbours (`NEIGHBOURS`), so every pair of
neighbouring pixels is sampled from both ends. The base path is the plain path tracer of
`data_gen.integrator.trace` (same random numbers, same operations: its radiance is bit-identical);
the offsets consume no random numbers of their own.

The shift (Kettunen 2015 Sec. 5.2; the public Mitsuba 0.5 ``gpt`` integrator was read to learn the
structure, nothing is copied):

- The offset camera ray goes through the neighbour pixel with the same film jitter and the same
  aperture, time and wavelength samples (a translation of the film sample: Jacobian 1).
- While not yet reconnected, the offset follows the base path's *decisions*: at a vertex where the
  base sampled a direction, if the base vertex, the base's next vertex and the offset vertex are all
  rough (`ShiftSettings.roughness_threshold`), the offset *reconnects* to the base's next vertex
  (a visibility test; Jacobian ``|cos_y| d_x^2 / (|cos_x| d_y^2)`` at the shared vertex) and from
  then on shares the base path's tail (one BSDF evaluation with the new incoming direction at the
  shared vertex, then nothing but the base's own values). Otherwise it copies the base's local
  half-vector (reflection; Jacobian ``|wo_y . h| / |wo_x . h|``) or, where the base sampled a delta
  lobe, takes the same delta lobe (same event type: reflection stays reflection, refraction stays
  refraction, a change of type or total internal reflection is a failure).
- Next-event estimation: the offset vertex reconnects to the base's light sample (the same point on
  an area light, the same direction for an environment) when both vertices are rough; at glossy
  vertices light sampling is not used by either path of the pair (the base's BSDF-sampled hits then
  carry the light alone), as in Kettunen's tracer.
- Every contribution (light sample or BSDF hit) of the base path ``x`` and its offset ``y`` is
  weighted with the power heuristic over four techniques: base light sampling, base BSDF sampling,
  and the same two from the neighbour pixel followed by the inverse shift, i.e.

      W = p_x^2 / (p_x^2 + q_x^2 + J^2 (p_y^2 + q_y^2))

  (``p`` the density of the technique used, ``q`` of the other one, ``J`` the shift's Jacobian
  ``|dy/dx|``); the lane adds ``W (f_y J - f_x) / p_x`` to the gradient toward its neighbour, and
  ``W f_x / p_x`` resp. ``W f_y J / p_x`` to the MIS estimates of its own and the neighbour's pixel
  (the G-PT primal). The pixel pair's other end adds its own terms with the shift reversed; for
  every path the weights of the two ends sum to one, which makes each gradient unbiased. A failed
  shift has offset density 0 (the base keeps its usual weight, the offset contributes nothing) and
  is counted.
- Light samples are used by the gradient estimator only where they face their light (a one-sided
  emitter's back gives no radiance; the sphere's cone sampling cannot reach its far side), so the
  light-sampling density of an endpoint is the same whichever end computes it.

Bookkeeping in ratios (Veach style, as Kettunen's implementation notes suggest for stability): the
base carries ``beta = f_x / p_x``; each offset carries ``beta_y = J f_y / p_x`` and the density
ratio ``R = J p_y / p_x`` of its prefix. Russian roulette (the base's decision) scales both paths'
densities alike, so ``R`` is unchanged.

Cost: Dr.Jit's LLVM backend runs every operation of a vectorized loop for every lane, masked or not,
but a symbolic conditional (``dr.if_stmt``) only for the SIMD packets that hold a lane taking it. Each
offset's update is therefore traced three times, in nested conditionals on its state: all of the
shift for offsets not yet connected, the shared vertex's BSDF for those connected one vertex ago, and
the base path's own values for those sharing its tail (or dead), which after the first bounces are
most of them. The three traces are one function with the other states' masks set to a literal False
(`_state_masks`); ``branch_states=False`` traces it once for every state, bit-identical (tested).
Since 0.9.9 the offsets' light samples on an environment reuse the base's density and radiance (same
direction), and a caller whose primal is the base image leaves the pair estimates out
(``pair_estimates=False``): together 5-10 % of a frame on the bench's outdoor scene (with the per-pixel
sums gathered per buffer in `data_gen.gradient`).

Supported BSDFs: what the procedural families and our XML scenes use (diffuse, rough and smooth
conductor, rough and smooth plastic, rough and smooth dielectric). A half-vector copy through a rough
*refraction* (a rough dielectric below the roughness threshold) is not implemented and counts as a
failed shift (unbiased: the failure is symmetric, the other end does the same). Choices and
measurements: ``docs/methods/gradient_domain.md``.
"""
from __future__ import annotations

import dataclasses

from .integrator import FEATURE_DIMS, FEATURES, PathSettings, feature_vertex, mis_weight, RoughnessLookup
from jaxdenoise.errors import JaxdenoiseError

__all__ = ["ShiftSettings", "NEIGHBOURS", "trace_gpt"]

# Pixel offsets of the four offset paths: right, down, left, up (image x to the right, y down).
NEIGHBOURS: tuple[tuple[int, int], ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))

# Offset path states (Kettunen 2015 Sec. 5.2; Mitsuba 0.5 gpt's RayConnection).
NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED, DEAD = 0, 1, 2, 3
_ALL_STATES = (NOT_CONNECTED, RECENTLY_CONNECTED, CONNECTED)
# Per-lane event flags, one bit per neighbour and kind.
RECONNECTED, HALF_VECTOR, FAILED = 1, 2, 4

_EPS = 1e-20
_MIN_DIST2 = 1e-10  # squared distance (scene units) below which two vertices count as one
_ONE_MINUS = 0.99999994  # largest float32 below 1: picks a BSDF's second (transmissive) delta lobe


@dataclasses.dataclass(frozen=True)
class ShiftSettings:
    """Choices the paper leaves open (docs/methods/gradient_domain.md).

    roughness_threshold: a vertex is "rough" (reconnectable) when the roughness of the lobe in use
        (`data_gen.integrator.bsdf_roughness`: GGX/Beckmann alpha, 1 for diffuse, 0 for delta) is
        above this; Mitsuba 0.5's ``gpt`` default ``shiftThreshold`` is 0.001.
    """

    roughness_threshold: float = 0.001

    def __post_init__(self) -> None:
        if not isinstance(self.roughness_threshold, (int, float)) or not 0.0 <= self.roughness_threshold < 1.0:
            raise JaxdenoiseError(f"roughness_threshold: expected a number in [0, 1), got {self.roughness_threshold!r}")


def _norm_dir(v):
    import drjit as dr

    n2 = dr.squared_norm(v)
    return v * dr.rsqrt(dr.maximum(n2, _EPS)), n2


def _reconnection_jacobian(cos_y, dist2_y, cos_x, dist2_x):
    """|d omega_y / d omega_x| of a reconnection to a shared vertex (or light point): the ratio of
    the solid angles one area element there subtends from the offset and from the base vertex
    (Kettunen 2015 Sec. 5.2): ``(|cos_y| / d_y^2) / (|cos_x| / d_x^2)``."""
    import drjit as dr

    return dr.abs(cos_y) * dist2_x / dr.maximum(dr.abs(cos_x) * dist2_y, _EPS)


def _state_masks(active, st, states):
    """The masks ``(connected, recently connected, not connected)`` of the lanes in ``active`` whose
    offset is in that state; a state not in ``states`` gives a literal False, so Dr.Jit drops the code
    only it needs, and such a lane is handled as DEAD (a caller traces the code of a lane's actual state)."""
    import mitsuba as mi

    return tuple(active & (st == v) if v in states else mi.Bool(False)
                 for v in (CONNECTED, RECENTLY_CONNECTED, NOT_CONNECTED))


def _pair_weight(base_terms, offset_terms):
    """Power-heuristic weight of a base-path contribution, its densities divided by its own:
    ``base_terms`` = 1 + (other base technique)^2, ``offset_terms`` = the two offset techniques'
    squared densities times J^2 (the neighbour pixel's end of the pair)."""
    import drjit as dr

    return dr.rcp(base_terms + offset_terms)


def _direction_sample(ds, *, p, d, dist):
    """A copy of the emitter sample ``ds`` seen from another vertex. (Mitsuba's copy constructor
    drops ``d``, ``dist`` and ``emitter``: every field is set here.)"""
    import drjit as dr
    import mitsuba as mi

    out = dr.zeros(mi.DirectionSample3f)
    out.p, out.n, out.uv, out.time, out.pdf, out.delta = p, ds.n, ds.uv, ds.time, ds.pdf, ds.delta
    out.d, out.dist, out.emitter = d, dist, ds.emitter
    return out


def trace_gpt(scene, sampler, ray, weight, offset_rays, offset_weights, *, settings: PathSettings,
              shift: ShiftSettings = ShiftSettings(), roughness: RoughnessLookup | None = None,
              separate_emission: bool = True, record: frozenset[str] = frozenset(),
              branch_states: bool = True, pair_estimates: bool = True) -> dict:
    """Trace one base path per lane of ``ray`` and shift it to the four ``offset_rays`` (camera rays
    through the `NEIGHBOURS`, same camera samples; ``*_weight`` the camera weights).

    Returns a dict of per-lane Dr.Jit values: ``color`` (the base path's radiance, exactly what
    `data_gen.integrator.trace` returns for the same sampler and ray), and per neighbour ``k``
    ``grad[k]`` (this lane's share of ``I[neighbour] - I[pixel]``), ``main[k]`` and ``shifted[k]``
    (its shares of the MIS estimates of its own pixel and of the neighbour; only with
    ``pair_estimates``: they make the G-PT primal and nothing else), ``flags`` (UInt32:
    bits ``(RECONNECTED | HALF_VECTOR | FAILED) << (3 k)``) and ``emission`` (what a surface emitter
    seen directly gives the base path: the depth-0 part of ``color`` where the camera ray hits a shape).

    ``separate_emission`` (Kettunen's tracer, for surface emitters): that emission stays out of the
    gradients and of the pair estimates; each lane gives its own pixel's MIS estimate the whole of it
    (``main``) and its neighbours nothing, so the G-PT primal still holds it, and a reconstruction adds
    the ``emission`` image back to what it solves from ``primal - emission`` and the gradients. An
    environment seen directly stays in the gradients (smooth, and its directly seen radiance added back
    unfiltered made the thin-lens scene's reconstruction worse; docs/methods/gradient_domain.md).
    False: every depth-0 pair is weighted 1/2 from each end like every other pair (Jacobian 1, equal
    densities), and the visible emitters' edges enter ``grad``.

    ``record``: features of `data_gen.integrator.FEATURES` recorded along the base path, exactly as
    `data_gen.integrator.trace` records them for the same sampler and ray (same vertices, same values),
    returned under their names: a gradient frame's buffers need no separate plain render.

    ``branch_states`` (True): each offset's update runs in symbolic conditionals on its state (module
    docstring, "Cost"); False traces it once for every state and every lane, the tracer before 0.9.3,
    with the same outputs bit for bit (the reference the branches are tested against; the bench's
    "before" column).

    ``pair_estimates`` (True): trace ``main`` and ``shifted``; False leaves them out of the loop (24 fewer
    values carried per lane and the updates of them; 2-4 % of a frame on the bench's outdoor scene), for a
    caller whose primal is the base image. ``color``, ``grad`` and the rest are the same bit for bit.
    """
    import drjit as dr
    import mitsuba as mi

    if roughness is None:
        roughness = RoughnessLookup(scene)
    record = frozenset(record)
    if record - set(FEATURES):
        raise JaxdenoiseError(f"record: unknown feature(s) {sorted(record - set(FEATURES))}; expected some of {FEATURES}")
    thr = float(shift.roughness_threshold)
    ctx = mi.BSDFContext()
    K = len(NEIGHBOURS)
    Spectrum, Float, UInt32, Bool = mi.Spectrum, mi.Float, mi.UInt32, mi.Bool

    def has(flags, f):
        return mi.has_flag(flags, f)

    def rough(bsdf, delta_sampled, active):
        # The lobe in use: after a delta event the BSDF's delta lobes count (roughness 0).
        r = roughness(bsdf, active) > thr
        return r & ~(delta_sampled & has(bsdf.flags(), mi.BSDFFlags.Delta))

    # ---- depth 0: camera rays, emitters seen directly (Jacobian 1, equal densities: W = 1/2) ----
    # Throughputs are relative to the base camera weight (as in trace, whose caller multiplies the
    # radiance by it); the outputs are scaled by it at the end.
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=True)
    ds0 = mi.DirectionSample3f(scene, si=si, ref=dr.zeros(mi.SurfaceInteraction3f))
    L = Spectrum(0.0) + dr.select(Bool(True), Spectrum(1.0) * 1.0 * ds0.emitter.eval(si, True), 0.0)
    c_x0 = si.emitter(scene).eval(si, True)
    e_x0 = dr.select(si.is_valid(), c_x0, 0.0)  # what a surface emitter seen directly gives
    valid0 = si.is_valid()
    w_x = Spectrum(weight)
    offs = []
    for k in range(K):
        si_y = scene.ray_intersect(offset_rays[k], ray_flags=mi.RayFlags.All, coherent=True, active=True)
        beta_y = Spectrum(offset_weights[k]) / dr.select(w_x != 0.0, w_x, 1.0)
        c_y0 = beta_y * si_y.emitter(scene).eval(si_y, True)
        alive = valid0 & si_y.is_valid()
        if separate_emission:
            # A surface emitter seen directly goes to the base pixel whole; an environment seen directly
            # (an invalid hit) stays a pair like any other (docs/methods/gradient_domain.md).
            env_x, env_y = c_x0 - e_x0, dr.select(si_y.is_valid(), 0.0, c_y0)
            g0, pm0, ps0 = 0.5 * (env_y - env_x), e_x0 + 0.5 * env_x, 0.5 * env_y
        else:
            g0, pm0, ps0 = 0.5 * (c_y0 - c_x0), 0.5 * c_x0, 0.5 * c_y0
        offs.append(dict(
            st=dr.select(alive, UInt32(NOT_CONNECTED), UInt32(DEAD)), si=si_y, yp=mi.Point3f(0.0),
            beta=beta_y, R=Float(1.0), g=g0,
            fl=dr.select(valid0 & ~si_y.is_valid(), UInt32(FAILED << (3 * k)), UInt32(0)),
        ))
        if pair_estimates:
            offs[-1].update(pm=pm0, ps=ps0)
    # Features of the base path (as data_gen.integrator.trace): the feature vertex is the first smooth
    # one; ``pending`` marks a reached vertex the loop will not visit (the path's last allowed vertex),
    # whose features are recorded after the loop.
    feats = {f: (mi.Color3f(0.0) if FEATURE_DIMS[f] == 3 else Float(0.0)) for f in FEATURES if f in record}
    if "depth" in feats:
        feats["depth"] = dr.select(valid0, si.t, 0.0)
    state = dict(ray=mi.Ray3f(ray), si=si, depth=UInt32(0), L=L, beta=Spectrum(1.0), eta=Float(1.0),
                 active=valid0 & (settings.max_depth > 1), offs=offs, feats=feats, found=Bool(False),
                 pending=valid0 & (settings.max_depth <= 1))

    def by_state(st, active, fn, args):
        # ``fn(*args, states)`` traced once per group of offset states, each group in a symbolic
        # conditional: Dr.Jit's LLVM backend runs a branch only for the SIMD packets that hold a lane
        # taking it, so the reconnection and half-vector code runs only where an offset has not yet
        # connected (cost: docs/methods/gradient_domain.md). ``branch_states=False``: one trace of
        # every state (the reference the branches are tested against, bit for bit).
        if not branch_states:
            return fn(*args, _ALL_STATES)
        return dr.if_stmt(
            args=args, cond=active & (st == NOT_CONNECTED), true_fn=lambda *a: fn(*a, _ALL_STATES),
            false_fn=lambda *a: dr.if_stmt(
                args=a, cond=active & (st == RECENTLY_CONNECTED),
                true_fn=lambda *b: fn(*b, (RECENTLY_CONNECTED,)), false_fn=lambda *b: fn(*b, (CONNECTED,)),
                label="data_gen.gpt.recent"),
            label="data_gen.gpt.shift")

    def add_pair(o, w, c_x, c_y):
        # A pair contribution: the lane's gradient share and, with pair_estimates, its shares of the MIS
        # estimates of its own pixel (``pm``) and of the neighbour (``ps``).
        out = dict(g=o["g"] + w * (c_y - c_x))
        if pair_estimates:
            out.update(pm=o["pm"] + w * c_x, ps=o["ps"] + w * c_y)
        return out

    sums = ("g", "pm", "ps") if pair_estimates else ("g",)

    def body(s, smp):
        ray, si, depth, active = s["ray"], s["si"], s["depth"], s["active"]
        L, beta = s["L"], s["beta"]
        bsdf = si.bsdf(ray)
        smooth = has(bsdf.flags(), mi.BSDFFlags.Smooth)
        offs = [dict(o) for o in s["offs"]]
        at_feat = active & ~s["found"] & smooth

        # ---------------- next-event estimation (as data_gen.integrator.trace) ----------------
        active_em = active & smooth
        ds_em, em_weight = scene.sample_emitter_direction(si, smp.next_2d(active_em), False, active_em)
        active_em &= ds_em.pdf != 0.0
        shadow = si.spawn_ray_to(ds_em.p)
        occluded = scene.ray_test(shadow, active_em)
        reaches = active_em & ~occluded & (dr.max(em_weight) > 0.0)
        wo = si.to_local(ds_em.d)
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, reaches)
        mis_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, bsdf_pdf))
        L = L + dr.select(reaches, beta * bsdf_val * em_weight * mis_em, 0.0)

        inf = has(ds_em.emitter.flags(), mi.EmitterFlags.Infinite)
        point = ds_em.delta & ~inf
        ev = active_em & (inf | point | (dr.dot(ds_em.d, ds_em.n) < 0.0))
        a_x = dr.maximum(ds_em.pdf, _EPS)
        b_x = dr.select(reaches & ~ds_em.delta, bsdf_pdf, 0.0)
        den_x = 1.0 + dr.square(b_x / a_x)
        c_x = dr.select(reaches, beta * bsdf_val * em_weight, 0.0)
        rough_nee = roughness(bsdf, ev) > thr

        def nee_shift(o, states):
            # An offset's share of the light sample; ``states``: the offset states the traced code handles
            # (a lane in another one is treated as DEAD: see `_state_masks`).
            st, R = o["st"], o["R"]
            conn, recent, notc = _state_masks(ev, st, states)
            # Recently connected: the shared vertex seen from the offset's previous vertex.
            wi_r, _ = _norm_dir(o["yp"] - si.p)
            si_r = mi.SurfaceInteraction3f(si)
            si_r.wi = si.to_local(wi_r)
            val_r, pdf_r = bsdf.eval_pdf(ctx, si_r, wo, recent & reaches)
            b_r = dr.select(reaches & ~ds_em.delta, pdf_r, 0.0)
            # Not connected: reconnect the offset vertex to the base's light sample.
            si_y = o["si"]
            bsdf_y = si_y.bsdf()
            recon = notc & ((rough_nee & (roughness(bsdf_y, notc) > thr)) | point)
            d_y, dist2_y = _norm_dir(ds_em.p - si_y.p)
            ds_y = _direction_sample(ds_em, p=dr.select(inf, si_y.p + (ds_em.p - si.p), ds_em.p),  # at infinity:
                                     d=dr.select(inf, ds_em.d, d_y),                              # same direction
                                     dist=dr.select(inf, ds_em.dist, dr.sqrt(dist2_y)))
            front_y = inf | point | (dr.dot(ds_y.d, ds_em.n) < 0.0)
            dist2_x = dr.square(ds_em.dist)
            jac = dr.select(inf | point, 1.0,
                            _reconnection_jacobian(dr.dot(ds_em.n, ds_y.d), dist2_y, dr.dot(ds_em.n, ds_em.d), dist2_x))
            # A delta light (point or directional) is sampled with the same discrete probability
            # from any vertex; Mitsuba reports no direction density for it.
            # An environment (an infinite emitter that is not a delta: envmap, constant) has a direction
            # density and a radiance that depend on the direction alone, and the offset keeps the base's
            # direction: the offset takes the base's sample values instead of looking them up again (5 % of
            # a frame on the bench's outdoor scene; ``em_weight * pdf`` is the radiance). They equal the
            # lookups within Mitsuba's own round trip (tests/test_gpt.py: an envmap's density to 2e-4
            # relative near its poles, the radiance to 1e-5); a lookup from the base's vertex would differ
            # from its own sample the same way.
            env = inf & ~ds_em.delta
            a_y = dr.select(ds_em.delta | env, ds_em.pdf,
                            scene.pdf_emitter_direction(si_y, ds_y, recon & front_y & ~ds_em.delta & ~env))
            a_y = dr.select(front_y, a_y, 0.0)
            le_y = dr.select(env, em_weight * ds_em.pdf,
                             scene.eval_emitter_direction(si_y, ds_y, recon & front_y & ~env))
            occ_y = scene.ray_test(si_y.spawn_ray_to(ds_y.p), recon & front_y)
            # Guard: a light point on the offset vertex itself has no direction (0/0 Jacobian).
            vis_y = recon & front_y & ~occ_y & (inf | point | (dist2_y > _MIN_DIST2)) & dr.isfinite(jac)
            val_y, pdf_y = bsdf_y.eval_pdf(ctx, si_y, si_y.to_local(ds_y.d), vis_y)
            b_y = dr.select(vis_y & ~ds_em.delta, pdf_y, 0.0)
            c_y_nc = dr.select(vis_y, o["beta"] * jac * val_y * le_y / a_x, 0.0)

            c_y = dr.select(conn, dr.select(reaches, o["beta"] * bsdf_val * em_weight, 0.0),
                            dr.select(recent, dr.select(reaches, o["beta"] * val_r * em_weight, 0.0), c_y_nc))
            w = dr.select(
                conn, _pair_weight(den_x, den_x * dr.square(R)),
                dr.select(recent, _pair_weight(den_x, dr.square(R) * (1.0 + dr.square(b_r / a_x))),
                          dr.select(recon, _pair_weight(den_x, dr.square(R * jac / a_x) * (dr.square(a_y) + dr.square(b_y))),
                                    dr.select(notc, 0.0, dr.rcp(den_x)))))
            w = dr.select(ev, w, 0.0)
            c_y = dr.select(ev & (st != DEAD), c_y, 0.0)
            return add_pair(o, w, c_x, c_y)

        for o in offs:
            o.update(by_state(o["st"], ev, lambda acc, states, o=o: nee_shift({**o, **acc}, states),
                              ({k: o[k] for k in sums},)))

        # ---------------- BSDF sampling and Russian roulette (as trace) ----------------
        s1 = smp.next_1d(active)
        s2 = smp.next_2d(active)
        bs, bsdf_weight = bsdf.sample(ctx, si, s1, s2, active)
        beta_n = beta * bsdf_weight
        eta = s["eta"] * bs.eta
        new_ray = si.spawn_ray(si.to_world(bs.wo))
        beta_max = dr.max(mi.unpolarized_spectrum(beta_n))
        rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
        rr_active = depth + 1 >= settings.rr_depth
        inv_q = dr.select(rr_active, dr.rcp(rr_prob), 1.0)
        beta_n = dr.select(rr_active, beta_n * dr.rcp(rr_prob), beta_n)
        rr_continue = smp.next_1d(active) < rr_prob
        cont = active & (~rr_active | rr_continue) & (beta_max != 0.0)

        si_n = scene.ray_intersect(new_ray, ray_flags=mi.RayFlags.All, coherent=False, active=cont)
        delta_s = has(bs.sampled_type, mi.BSDFFlags.Delta)
        ds = mi.DirectionSample3f(scene, si=si_n, ref=si)
        em_pdf = scene.pdf_emitter_direction(si, ds, cont & ~delta_s)
        mis_bsdf = dr.select(delta_s, 1.0, mis_weight(bs.pdf, em_pdf))
        le_x = ds.emitter.eval(si_n, cont)
        L = L + dr.select(cont, beta_n * mis_bsdf * le_x, 0.0)

        valid_n = si_n.is_valid()
        n_inf = ~valid_n  # a miss: the environment (if any) lies at infinity
        a_x = dr.maximum(bs.pdf, _EPS)
        front_x = n_inf | (dr.dot(new_ray.d, si_n.n) < 0.0)
        b_x = dr.select(delta_s | ~front_x, 0.0, em_pdf)
        den_x = 1.0 + dr.square(b_x / a_x)
        c_x = dr.select(cont, beta_n * le_x, 0.0)
        rough_x = rough(bsdf, delta_s, cont)
        rough_next = n_inf | rough(si_n.bsdf(), delta_s, cont & valid_n)
        refl = dr.sign(mi.Frame3f.cos_theta(si.wi)) == dr.sign(mi.Frame3f.cos_theta(bs.wo))
        s1_forced = dr.select(has(bs.sampled_type, mi.BSDFFlags.DeltaTransmission), _ONE_MINUS, 0.0)

        def bsdf_shift(k, o, states):
            # An offset's next vertex (as nee_shift: ``states`` those the traced code handles).
            st, R, beta_y = o["st"], o["R"], o["beta"]
            conn, recent, notc = _state_masks(cont, st, states)
            fail = Bool(False)
            end = Bool(False)
            # -- recently connected: evaluate the shared vertex with the offset's incoming direction.
            wi_r, _ = _norm_dir(o["yp"] - si.p)
            si_r = mi.SurfaceInteraction3f(si)
            si_r.wi = si.to_local(wi_r)
            val_r, pdf_r = bsdf.eval_pdf(ctx, si_r, bs.wo, recent & ~delta_s)
            recent_ok = recent & ~delta_s & (pdf_r > 0.0)
            fail |= recent & ~recent_ok
            # -- not connected: reconnection or half-vector copy.
            si_y = o["si"]
            bsdf_y = si_y.bsdf()
            rough_y = rough(bsdf_y, delta_s, notc)
            recon = notc & rough_x & rough_next & rough_y
            d_y, dist2_y = _norm_dir(si_n.p - si_y.p)
            d_y = dr.select(n_inf, new_ray.d, d_y)
            vis_ray = dr.select(n_inf, si_y.spawn_ray(d_y), si_y.spawn_ray_to(si_n.p))
            recon_vis = recon & ~scene.ray_test(vis_ray, recon)
            cos_x = dr.dot(si_n.n, new_ray.d)
            cos_y = dr.dot(si_n.n, d_y)
            jac_c = dr.select(n_inf, 1.0, _reconnection_jacobian(cos_y, dist2_y, cos_x, dr.square(si_n.t)))
            val_c, pdf_c = bsdf_y.eval_pdf(ctx, si_y, si_y.to_local(d_y), recon_vis)
            si_ny = mi.SurfaceInteraction3f(si_n)
            si_ny.wi = si_n.to_local(-d_y)
            le_c = dr.select(n_inf, le_x, si_n.emitter(scene).eval(si_ny, recon_vis))
            ds_c = mi.DirectionSample3f(scene, si=si_ny, ref=si_y)
            front_c = n_inf | (dr.dot(d_y, si_n.n) < 0.0)
            b_c = dr.select(n_inf, b_x,
                            dr.select(front_c, scene.pdf_emitter_direction(si_y, ds_c, recon_vis & front_c), 0.0))
            # Guard: an offset vertex on the base's next vertex (0 distance) has no incoming direction
            # there; such a degenerate shift fails (and is counted).
            recon_ok = (recon_vis & (pdf_c > 0.0) & (n_inf | (dist2_y > _MIN_DIST2)) & dr.isfinite(jac_c)
                        & (jac_c > 0.0))
            fail |= recon & ~recon_ok
            # half-vector copy (or the same delta lobe)
            hv = notc & ~recon
            bs_d, w_d = bsdf_y.sample(ctx, si_y, s1_forced, s2, hv & delta_s)
            ok_d = hv & delta_s & (bs_d.sampled_type == bs.sampled_type) & (bs_d.pdf > 0.0)
            h, _ = _norm_dir(si.wi + bs.wo)
            wi_y = si_y.wi
            wo_h = 2.0 * dr.dot(wi_y, h) * h - wi_y
            jac_h = dr.abs(dr.dot(wo_h, h)) / dr.maximum(dr.abs(dr.dot(bs.wo, h)), _EPS)
            hv_s = hv & ~delta_s & refl & has(bsdf_y.flags(), mi.BSDFFlags.Smooth)
            val_h, pdf_h = bsdf_y.eval_pdf(ctx, si_y, wo_h, hv_s)
            ok_s = hv_s & (pdf_h > 0.0)
            wo_hv = dr.select(delta_s, bs_d.wo, wo_h)
            hv_ok = ok_d | ok_s
            ray_y = si_y.spawn_ray(si_y.to_world(wo_hv))
            si_yn = scene.ray_intersect(ray_y, ray_flags=mi.RayFlags.All, coherent=False, active=hv_ok)
            valid_yn = si_yn.is_valid()
            rough_yn = rough(si_yn.bsdf(), delta_s, hv_ok & valid_yn)
            both_miss = ~valid_n & ~valid_yn
            hv_ok &= (valid_n == valid_yn) & ~(valid_n & rough_x & rough_y & rough_yn)
            fail |= hv & ~hv_ok
            le_h = si_yn.emitter(scene).eval(si_yn, hv_ok)
            end |= hv_ok & both_miss

            # ---- new offset throughput, density ratio, contribution and weight ----
            f_rel = dr.select(conn, bsdf_weight,
                              dr.select(recent_ok, val_r / a_x,
                                        dr.select(recon_ok, val_c * jac_c / a_x,
                                                  dr.select(ok_d, w_d * bs_d.pdf / a_x, val_h * jac_h / a_x))))
            r_rel = dr.select(conn, 1.0,
                              dr.select(recent_ok, pdf_r / a_x,
                                        dr.select(recon_ok, pdf_c * jac_c / a_x,
                                                  dr.select(ok_d, bs_d.pdf / a_x, pdf_h * jac_h / a_x))))
            alive_n = conn | recent_ok | recon_ok | hv_ok
            beta_y = dr.select(alive_n, beta_y * f_rel * inv_q, 0.0)
            R_n = dr.select(alive_n, R * r_rel, 0.0)
            le_y = dr.select(recon_ok, le_c, dr.select(hv_ok, le_h, le_x))
            c_y = dr.select(alive_n, beta_y * le_y, 0.0)
            w = dr.select(
                conn, _pair_weight(den_x, den_x * dr.square(R)),
                dr.select(recent_ok, _pair_weight(den_x, dr.square(R / a_x) * (dr.square(pdf_r) + dr.square(b_x))),
                          dr.select(recon_ok, _pair_weight(den_x, dr.square(R * jac_c / a_x) * (dr.square(pdf_c) + dr.square(b_c))),
                                    dr.select(hv_ok, _pair_weight(1.0, dr.square(R_n)),
                                              dr.select(hv, 1.0, dr.rcp(den_x))))))
            w = dr.select(cont, w, 0.0)
            new_st = dr.select(conn | recent_ok, UInt32(CONNECTED),
                               dr.select(recon_ok, UInt32(RECENTLY_CONNECTED),
                                         dr.select(hv_ok & ~end, UInt32(NOT_CONNECTED), UInt32(DEAD))))
            return dict(**add_pair(o, w, c_x, c_y), beta=beta_y, R=R_n,
                        st=dr.select(cont, new_st, st), yp=dr.select(recon_ok, si_y.p, o["yp"]),
                        si=dr.select(hv_ok, si_yn, si_y),
                        fl=(o["fl"] | dr.select(recon_ok, UInt32(RECONNECTED << (3 * k)), 0)
                            | dr.select(hv_ok, UInt32(HALF_VECTOR << (3 * k)), 0)
                            | dr.select(cont & fail, UInt32(FAILED << (3 * k)), 0)))

        for k, o in enumerate(offs):
            o.update(by_state(o["st"], cont, lambda step, states, k=k: bsdf_shift(k, step, states), (dict(o),)))

        f = feature_vertex(s["feats"], si, bsdf, at_feat, reaches, roughness)
        if "albedo2" in f:  # the vertex after the feature vertex, where the path reaches one
            at2 = at_feat & cont & valid_n
            f["albedo2"] = dr.select(at2, si_n.bsdf(new_ray).eval_diffuse_reflectance(si_n, at2), f["albedo2"])

        active_n = cont & valid_n & (depth + 2 < settings.max_depth)
        return dict(ray=new_ray, si=si_n, depth=depth + 1, L=L, beta=beta_n, eta=eta, active=active_n,
                    offs=offs, feats=f, found=s["found"] | at_feat, pending=cont & valid_n & ~active_n), smp

    state = dr.while_loop((state, sampler), lambda s, smp: s["active"], body, label="data_gen.gpt")[0]
    offs = state["offs"]
    out = dict(color=state["L"] * w_x, grad=[o["g"] * w_x for o in offs], emission=e_x0 * w_x,
               flags=offs[0]["fl"] | offs[1]["fl"] | offs[2]["fl"] | offs[3]["fl"])
    if pair_estimates:
        out.update(main=[o["pm"] * w_x for o in offs], shifted=[o["ps"] * w_x for o in offs])
    if record:
        # The last allowed vertex: trace visits it (no light sample there: no visibility).
        si, pending = state["si"], state["pending"]
        bsdf = si.bsdf(state["ray"])
        at_feat = pending & ~state["found"] & has(bsdf.flags(), mi.BSDFFlags.Smooth)
        out.update(feature_vertex(state["feats"], si, bsdf, at_feat, Bool(False), roughness))
    return out
