"""Gradient-domain buffers ``dx``, ``dy`` by primary-sample-space (PSS) replay.

Mitsuba 3 has no gradient-domain path tracer. This module estimates the finite differences

    dx[y, x] = I[y, x+1] - I[y, x]        dy[y, x] = I[y+1, x] - I[y, x]

from *correlated pairs* of paths: for every pixel (x, y) and sample s, the base path through
(x, y) and the two shifted paths through (x+1, y) and (x, y+1) are traced with the SAME stream of
random numbers (the same sampler lane, seeded identically), the film sample being offset by exactly
one pixel. This is the "random replay" / primary-sample-space shift (Lehtinen et al. 2013, Sec. 5;
Kettunen et al. 2015, Sec. 4.2 contrast it with their reconnection shift): where the base and
shifted paths see the same smooth geometry and materials they take almost the same bounces, so the
per-sample difference has far lower variance than the difference of two independent renders. The
estimator is unbiased for any scene, because each shifted path, taken alone, is an ordinary path
through its own pixel driven by uniform random numbers; only the correlation (hence the variance)
depends on the scene.

Guo et al. 2019 (GradNet), Sec. 5.1 and 6.1, generate their data with Kettunen et al.'s
gradient-domain path tracer (a different shift). The issue asks for pure PSS replay; the choice and
its consequences are written in ``docs/methods/gradient_domain.md``.

Implementation: a vectorized Dr.Jit wavefront. A pass traces every pixel x ``n`` samples at once
(bounded by ``samples_per_pass`` lanes, as in `data_gen.render.render_moments`) with the buffer
integrator's path tracer `data_gen.integrator.trace`. Lane ``i`` of a pass is always sample
``i % n`` of base pixel ``i // n``; the independent sampler seeds lane ``i`` from (pass seed, i)
only, so the three traces of a pass (offsets (0,0), (1,0), (0,1)) consume identical random numbers.
With the same ``seed``, ``spp`` and ``samples_per_pass``, ``primal`` is bit-identical to the
``color`` of `data_gen.render.render_buffers` (same seeds, same lane layout, same camera samples),
as long as no base sample is non-finite (see ``n_invalid``).

Pixel integration uses a box filter (each sample counts toward its own pixel only), which is what
makes ``mean(shifted) - mean(base)`` the finite difference of pixel values.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from .integrator import EMISSION, FEATURE_DIMS, FEATURES, PathSettings, derive_seed, trace
from .mitsuba_setup import is_vectorized, setup_mitsuba
from .gpt import NEIGHBOURS, ShiftSettings, trace_gpt
from .render import DEFAULT_SAMPLES_PER_PASS, camera_ray, camera_samples, block_sums, moments_to_buffers
from .scenes import load_scene
from jaxdenoise.buffers import GRADIENT_EMISSION_MODES, PRIMALS
from jaxdenoise.errors import JaxdenoiseError

__all__ = ["render_gradients", "trace_shifted", "trace_reconnect", "OFFSETS", "SHIFTS", "DIRECT_EMISSION"]

# Film offsets (pixels) of the three correlated traces: base, horizontal and vertical neighbour.
OFFSETS: dict[str, tuple[int, int]] = {"base": (0, 0), "dx": (1, 0), "dy": (0, 1)}

# The shift mappings: primary-sample-space replay (this module) and Kettunen's reconnection (`data_gen.gpt`).
SHIFTS: tuple[str, ...] = ("replay", "reconnect")
# The shift data_gen uses for dx, dy unless told otherwise (docs/results/data_gen_gradient.md).
DEFAULT_SHIFT = "reconnect"
# Where the directly seen emission goes (Kettunen et al. 2015's tracer: "separate", the default): kept out
# of dx, dy and returned as an image of its own (``emission``) that a reconstruction adds back, or
# "included" in the gradients like every other path (what data_gen did before 0.7.0).
DIRECT_EMISSION: tuple[str, ...] = GRADIENT_EMISSION_MODES


def _wavefront(scene, *, seed: int, n: int, width: int, height: int):
    """Sensor, seeded sampler, base pixel coordinates and film jitter of one pass (lane ``i`` is
    sample ``i % n`` of base pixel ``i // n``); the jitter is the lane's first 2D sample."""
    import drjit as dr
    import mitsuba as mi

    sensor = scene.sensors()[0]
    sampler = mi.load_dict({"type": "independent"})
    npix = int(width) * int(height)
    sampler.seed(dr.opaque(mi.UInt32, int(seed)), npix * int(n))
    idx = dr.arange(mi.UInt32, npix * int(n))
    if n > 1:
        idx = idx // dr.opaque(mi.UInt32, int(n))
    py = idx // dr.opaque(mi.UInt32, int(width))
    px = idx - py * int(width)
    return sensor, sampler, px, py, sampler.next_2d()


def _film_position(px, py, jitter, offset, width: int, height: int):
    """[0, 1]^2 film position (over the film's crop window, as `sample_ray_differential` expects) of
    the jittered pixel ``(px, py) + offset``. Opaque offsets keep the traced kernel identical for
    every offset, so the LLVM backend compiles it once."""
    import drjit as dr
    import mitsuba as mi

    pos_f = mi.Vector2f(mi.Float(px) + dr.opaque(mi.Float, float(offset[0])),
                        mi.Float(py) + dr.opaque(mi.Float, float(offset[1])))
    pos_f += jitter
    return pos_f * dr.rcp(mi.ScalarVector2f(float(width), float(height)))


def trace_shifted(scene, *, seed: int, offset: tuple[int, int], n: int, width: int, height: int,
                  settings: PathSettings, record: frozenset[str] = frozenset()):
    """Per-sample radiance of one wavefront whose camera samples are shifted by ``offset`` pixels.

    Lane ``i`` is sample ``i % n`` of base pixel ``(x, y) = (p % width, p // width)``,
    ``p = i // n``; its film position is ``(x + offset[0] + u, y + offset[1] + v)`` on a
    ``width x height`` grid laid over the sensor's film crop window, ``(u, v)`` being the lane's
    first 2D sample. The sampler is a fresh ``independent`` one seeded with ``(seed, lanes)``, so two
    calls that differ only in ``offset`` replay the same random numbers lane by lane. The camera
    sample dimensions (position, aperture, time, wavelength) are drawn in the same order as
    `data_gen.render` so that offset (0, 0) reproduces its samples exactly.

    Returns the Dr.Jit values (unevaluated) of ``width * height * n`` lanes: the radiance and the
    directly seen emission it holds (`data_gen.integrator.EMISSION`), ``Spectrum``s, and a dict of the
    features in ``record`` (`data_gen.integrator.trace`).
    """
    sensor, sampler, px, py, jitter = _wavefront(scene, seed=seed, n=n, width=width, height=height)
    ray, weight = camera_ray(sensor, sampler, _film_position(px, py, jitter, offset, width, height))
    out = trace(scene, sampler, ray, True, settings=settings, record=frozenset({EMISSION}) | frozenset(record))
    return out["color"] * weight, out[EMISSION] * weight, {f: out[f] for f in FEATURES if f in record}


def trace_reconnect(scene, *, seed: int, n: int, width: int, height: int, settings: PathSettings,
                    shift: ShiftSettings, separate_emission: bool = True, record: frozenset[str] = frozenset(),
                    pair_estimates: bool = True):
    """One wavefront of the reconnection shift (`data_gen.gpt.trace_gpt`): the base camera ray is the
    one `trace_shifted` builds for offset (0, 0) (same samples, so the same base path); the four
    offset rays go through the `NEIGHBOURS` with the same jitter and camera samples. ``pair_estimates``:
    as `data_gen.gpt.trace_gpt` (the G-PT primal's shares)."""
    sensor, sampler, px, py, jitter = _wavefront(scene, seed=seed, n=n, width=width, height=height)
    cam = camera_samples(sensor, sampler)
    ray, weight = camera_ray(sensor, None, _film_position(px, py, jitter, (0, 0), width, height), cam)
    rays, weights = [], []
    for off in NEIGHBOURS:
        r, w = camera_ray(sensor, None, _film_position(px, py, jitter, off, width, height), cam)
        rays.append(r)
        weights.append(w)
    out = trace_gpt(scene, sampler, ray, weight, rays, weights, settings=settings, shift=shift,
                    separate_emission=separate_emission, record=record, pair_estimates=pair_estimates)
    out["px"], out["py"] = px, py
    return out


def render_gradients(
    scene: Any,
    *,
    spp: int,
    seed: int = 0,
    max_depth: int = 8,
    rr_depth: int = 5,
    resolution: tuple[int, int] | None = None,
    samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS,
    on_pass: Callable[[int], None] | None = None,
    shift: str = DEFAULT_SHIFT,
    primal: str = "base",
    roughness_threshold: float = ShiftSettings.roughness_threshold,
    direct_emission: str = "separate",
    record: Any = (),
) -> dict[str, Any]:
    """Base image and gradient-domain finite differences, by primary-sample-space replay or by
    Kettunen et al.'s reconnection shift (`data_gen.gpt`).

    Args:
        scene: a loaded ``mi.Scene``, a scene dict, or a path to a Mitsuba XML file. Its first
            sensor is used; light transport is `data_gen.integrator.trace` (Mitsuba ``path``
            semantics) with ``max_depth``/``rr_depth``, whatever integrator the scene names.
        spp: samples per pixel, >= 1 (with 1, the variance of the mean cannot be estimated and the
            ``*_var`` entries are left out, as in `data_gen.render.moments_to_buffers`).
        seed: seeds every pass; a fixed seed gives bit-identical output.
        max_depth: longest path (Mitsuba convention: 1 = emitters seen directly, 2 = direct light).
        rr_depth: depth from which Russian roulette may end paths (Mitsuba convention).
        resolution: ``(width, height)`` of the pixel grid laid over the sensor's film; ``None``
            uses the film's (crop) size. It must keep the film's aspect ratio (square pixels).
        samples_per_pass: most lanes (pixels x samples) per wavefront; a pass holds at least one
            sample of every pixel.
        on_pass: called after each pass with the number of samples per pixel it added.
        shift: ``"reconnect"`` (the default, `DEFAULT_SHIFT`) or ``"replay"`` (three replayed paths
            per sample: base, right, lower neighbour); ``"reconnect"`` is G-PT: the base path and four offset paths, to every neighbour, combined
            with MIS between the two ends of each pixel pair; docs/methods/gradient_domain.md).
        primal: ``"base"`` (the plain path-traced image, bit-identical to `render_buffers`' colour
            with the same seed) or ``"gpt"`` (reconnect only: Kettunen's primal, the mean over the
            pixel's neighbour pairs of the MIS estimates from both ends; at the image border only
            the pairs inside the image count).
        roughness_threshold: reconnect only: `data_gen.gpt.ShiftSettings.roughness_threshold`.
        direct_emission: ``"separate"`` (the default, as Kettunen et al.'s tracer): what a camera ray's
            first hit emits stays out of ``dx``/``dy``, which are then the differences of
            ``primal - emission``, and is returned as ``emission``; ``"included"``: the gradients
            hold it like every other contribution (no ``emission``). `DIRECT_EMISSION`.
        record: features (`data_gen.integrator.FEATURES`) recorded along the base paths, returned as
            `data_gen.render.render_buffers` returns them (``<feature>`` means and, with spp > 1,
            ``<feature>_var``) and equal to its output for the same seed: a gradient frame in one
            pass (how data_gen's shots render gradient frames: docs/metrics.md).

    Returns:
        dict of float32 ``HWC`` arrays, 3 channels, linear radiance:
        ``primal`` (mean of the base paths) and ``primal_var`` (variance of that mean);
        ``dx`` = I[y, x+1] - I[y, x] and ``dy`` = I[y+1, x] - I[y, x], each the mean of per-sample
        differences of replayed pairs, with ``dx_var``, ``dy_var`` (variance of the mean; only when
        ``spp > 1``). The last column of ``dx``/``dx_var`` and the last row of ``dy``/``dy_var``
        would need pixels outside the image: they are 0. Also ``spp`` (int) and ``n_invalid``
        (int: lanes with a non-finite sample in any of the three traces; a non-finite base sample
        counts as 0 in ``primal``, a pair with a non-finite member as a difference of 0).
        With ``shift="reconnect"``, ``dx``/``dy`` are the sums of the two ends' MIS-weighted
        estimates (variances from the two ends' independent samples), ``n_invalid`` counts lanes
        with a non-finite value (their gradient shares count as 0), and ``shift_stats`` gives the
        fractions of offset paths that reconnected, went through a half-vector copy, and failed.
        With ``direct_emission="separate"``: ``emission`` (the mean of the base paths' directly
        seen emission, part of ``primal``) and ``emission_var`` (its variance of the mean, spp > 1).
    """
    if shift not in SHIFTS:
        raise JaxdenoiseError(f"shift: expected one of {SHIFTS}, got {shift!r}")
    if primal not in PRIMALS:
        raise JaxdenoiseError(f"primal: expected one of {PRIMALS}, got {primal!r}")
    if direct_emission not in DIRECT_EMISSION:
        raise JaxdenoiseError(f"direct_emission: expected one of {DIRECT_EMISSION}, got {direct_emission!r}")
    separate = direct_emission == "separate"
    record = frozenset(record)
    if record - set(FEATURES):
        raise JaxdenoiseError(f"record: unknown feature(s) {sorted(record - set(FEATURES))}; expected some of {FEATURES}")
    if primal == "gpt" and shift != "reconnect":
        raise JaxdenoiseError("primal='gpt' needs shift='reconnect' (replay has no offset estimates of a pixel)")
    shift_settings = ShiftSettings(roughness_threshold=roughness_threshold)
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise JaxdenoiseError(f"spp: expected a positive integer, got {spp!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise JaxdenoiseError(f"seed: expected a non-negative integer, got {seed!r}")
    if isinstance(samples_per_pass, bool) or not isinstance(samples_per_pass, (int, np.integer)) \
            or samples_per_pass < 1:
        raise JaxdenoiseError(f"samples_per_pass: expected a positive integer, got {samples_per_pass!r}")
    settings = PathSettings(max_depth=int(max_depth), rr_depth=int(rr_depth))

    setup_mitsuba()
    if not is_vectorized():
        raise RuntimeError(
            "render_gradients needs a vectorized Mitsuba variant (llvm_ad_rgb): setup_mitsuba() fell back "
            "to scalar_rgb; install LLVM >= 16 or set DRJIT_LIBLLVM_PATH"
        )
    import drjit as dr
    import mitsuba as mi

    scene = load_scene(scene)
    if not scene.sensors():
        raise JaxdenoiseError("scene: has no sensor")
    film_w, film_h = (int(v) for v in scene.sensors()[0].film().crop_size())
    if resolution is None:
        width, height = film_w, film_h
    else:
        if len(resolution) != 2 or any(int(v) < 1 for v in resolution):
            raise JaxdenoiseError(f"resolution: expected (width, height) of positive integers, got {resolution!r}")
        width, height = int(resolution[0]), int(resolution[1])
        if abs(width * film_h - height * film_w) > 1e-3 * film_w * height:
            raise JaxdenoiseError(
                f"resolution: {width}x{height} does not keep the film's aspect ratio {film_w}x{film_h} "
                "(pixels would not be square)"
            )

    npix = width * height
    per_pass = max(1, min(int(spp), int(samples_per_pass) // npix))
    acc: dict[str, list[np.ndarray]] = {}
    n_invalid = 0
    flag_counts = np.zeros(3, np.int64)

    def add(values: dict, n: int) -> None:
        # Per-pixel sums and sums of squares (float64 on the host) of per-lane values (Spectrum, or a
        # feature of FEATURE_DIMS channels): evaluated in one kernel, then summed per pixel in one more
        # (`block_sums`).
        names = list(values)
        dims = [FEATURE_DIMS.get(k, 3) for k in names]
        comps = [values[k][c] if d == 3 else values[k] for k, d in zip(names, dims) for c in range(d)]
        dr.eval(*comps)
        sums = iter(block_sums(comps, npix, n))
        for k, d in zip(names, dims):
            pairs = [next(sums) for _ in range(d)]
            # One contiguous (npix, d) array per key (a column at a time into fresh zeros cost 0.04 s of a
            # 0.46 s frame at 256x256). The first pass's sums are kept, plus 0.0 in place: what adding them
            # to zeros gave (-0.0 becomes 0.0), bit for bit.
            s, q = np.stack([a for a, _ in pairs], -1), np.stack([b for _, b in pairs], -1)
            if k in acc:
                acc[k][0] += s
                acc[k][1] += q
            else:
                s += 0.0
                q += 0.0
                acc[k] = [s, q]

    def finite(v):
        f = mi.Bool(True)
        for c in range(3):
            f &= dr.isfinite(v[c])
        return f

    done, k = 0, 0
    while done < spp:
        n = min(per_pass, int(spp) - done)
        pseed = derive_seed(seed, "pass", k)  # the same pass seeds as data_gen.render
        kw = dict(seed=pseed, n=n, width=width, height=height, settings=settings)
        if shift == "replay":
            base, e_b, feats = trace_shifted(scene, offset=OFFSETS["base"], record=record, **kw)
            dr.eval(base, e_b, feats)
            shx, e_x, _ = trace_shifted(scene, offset=OFFSETS["dx"], **kw)
            dr.eval(shx, e_x)
            shy, e_y, _ = trace_shifted(scene, offset=OFFSETS["dy"], **kw)
            dr.eval(shy, e_y)
            # Guard: a non-finite sample (a 0/0 in a BSDF or a degenerate frame) would poison its
            # pixel and the differences it enters: a non-finite base sample is set to 0, and a pair
            # with a non-finite member contributes a difference of 0. Such lanes are counted.
            ok_b = finite(base)
            ok_x, ok_y = ok_b & finite(shx), ok_b & finite(shy)
            n_invalid += int(dr.count(~(ok_x & ok_y))[0])
            vals = {"base": dr.select(ok_b, base, 0.0)}
            if separate:
                vals.update(dx=dr.select(ok_x, (shx - e_x) - (base - e_b), 0.0),
                            dy=dr.select(ok_y, (shy - e_y) - (base - e_b), 0.0), emission=dr.select(ok_b, e_b, 0.0))
            else:
                vals.update(dx=dr.select(ok_x, shx - base, 0.0), dy=dr.select(ok_y, shy - base, 0.0))
            vals.update(feats)
            add(vals, n)
            del base, shx, shy, e_b, e_x, e_y, vals
        else:
            out = trace_reconnect(scene, shift=shift_settings, separate_emission=separate, record=record,
                                  pair_estimates=primal == "gpt", **kw)
            ok_b = finite(out["color"])
            ok_g = mi.Bool(ok_b)
            for name in ("grad", "main", "shifted"):  # main and shifted: only for the G-PT primal
                for v in out.get(name, ()):
                    ok_g &= finite(v)
            px, py = out["px"], out["py"]
            vals = {"base": dr.select(ok_b, out["color"], 0.0)}
            own = mi.Spectrum(0.0)
            for j, (ox, oy) in enumerate(NEIGHBOURS):
                # The pair (pixel, neighbour) exists only if the neighbour is inside the image.
                inside = mi.Bool(True)
                if ox > 0:
                    inside &= px + ox < width
                if ox < 0:
                    inside &= px >= -ox
                if oy > 0:
                    inside &= py + oy < height
                if oy < 0:
                    inside &= py >= -oy
                vals[f"g{j}"] = dr.select(ok_g, out["grad"][j], 0.0)
                if primal == "gpt":  # the pair estimates only make the G-PT primal
                    vals[f"s{j}"] = dr.select(ok_g, out["shifted"][j], 0.0)
                    own += dr.select(ok_g & inside, out["main"][j], 0.0)
            if primal == "gpt":
                vals["own"] = own
            if separate:
                vals["emission"] = dr.select(ok_b, out["emission"], 0.0)
            vals.update({f: out[f] for f in FEATURES if f in record})
            dr.eval(ok_g, out["flags"], vals)  # the trace and what is summed of it: one kernel
            n_invalid += int(dr.count(~ok_g)[0])
            add(vals, n)
            flags = np.asarray(out["flags"], dtype=np.uint32)
            for b in range(3):
                flag_counts[b] += sum(int(np.count_nonzero(flags & np.uint32(1 << (b + 3 * j))))
                                      for j in range(len(NEIGHBOURS)))
            del out, vals, own
        done += n
        k += 1
        if on_pass is not None:
            on_pass(n)

    def mean_var(name):
        s, q = acc[name]
        # Unbiased sample variance / n (spp > 1 only). Guard: float64 cancellation in q - s^2/n can
        # leave tiny negatives where all samples are (nearly) equal, e.g. a perfectly correlated pair.
        var = np.maximum(q - s * s / spp, 0.0) / max(spp - 1, 1) / spp
        return (s / spp).reshape(height, width, 3), var.reshape(height, width, 3)

    out: dict[str, Any] = {}
    if shift == "replay":
        for name, key in (("base", "primal"), ("dx", "dx"), ("dy", "dy")):
            out[key], out[key + "_var"] = mean_var(name)
    else:
        g = [mean_var(f"g{j}") for j in range(len(NEIGHBOURS))]
        # dx[y, x]: the right shifts of (x, y) plus the left shifts of (x+1, y), reversed in sign.
        dx, dx_var = np.zeros((height, width, 3)), np.zeros((height, width, 3))
        dx[:, :-1] = g[0][0][:, :-1] - g[2][0][:, 1:]
        dx_var[:, :-1] = g[0][1][:, :-1] + g[2][1][:, 1:]
        dy, dy_var = np.zeros((height, width, 3)), np.zeros((height, width, 3))
        dy[:-1] = g[1][0][:-1] - g[3][0][1:]
        dy_var[:-1] = g[1][1][:-1] + g[3][1][1:]
        out.update(dx=dx, dx_var=dx_var, dy=dy, dy_var=dy_var)
        if primal == "base":
            out["primal"], out["primal_var"] = mean_var("base")
        else:
            # Pixel (x, y): its own MIS shares toward every neighbour inside the image, plus each such
            # neighbour's shares shifted onto it, averaged over the pairs.
            sh = [mean_var(f"s{j}") for j in range(len(NEIGHBOURS))]
            own, own_var = mean_var("own")
            tot, tot_var = own.copy(), own_var.copy()
            pairs = np.zeros((height, width, 1))
            pairs[:, :-1] += 1  # right neighbour: its left shifts (s2) land here
            tot[:, :-1] += sh[2][0][:, 1:]
            tot_var[:, :-1] += sh[2][1][:, 1:]
            pairs[:, 1:] += 1  # left neighbour: its right shifts (s0)
            tot[:, 1:] += sh[0][0][:, :-1]
            tot_var[:, 1:] += sh[0][1][:, :-1]
            pairs[:-1] += 1  # lower neighbour: its up shifts (s3)
            tot[:-1] += sh[3][0][1:]
            tot_var[:-1] += sh[3][1][1:]
            pairs[1:] += 1  # upper neighbour: its down shifts (s1)
            tot[1:] += sh[1][0][:-1]
            tot_var[1:] += sh[1][1][:-1]
            pairs = np.maximum(pairs, 1)
            out["primal"], out["primal_var"] = tot / pairs, tot_var / pairs ** 2
        total = len(NEIGHBOURS) * npix * int(spp)
        out["shift_stats"] = {"offset_paths": total, "reconnected": float(flag_counts[0] / total),
                              "half_vector": float(flag_counts[1] / total), "failed": float(flag_counts[2] / total)}
    if separate:
        out["emission"], out["emission_var"] = mean_var("emission")
    # the features as render_buffers gives them (means; with spp > 1 the channel-mean variance of the mean)
    out.update(moments_to_buffers({f: tuple(a.reshape(height, width, -1) for a in acc[f])
                                   for f in FEATURES if f in record}, int(spp)))
    for key in list(out):
        if isinstance(out[key], np.ndarray):
            out[key] = out[key].astype(np.float32)
    if spp == 1:
        for key in ("primal_var", "dx_var", "dy_var", "emission_var"):
            out.pop(key, None)
    # Border convention: I[y, W] and I[H, x] lie outside the image, so these differences are 0.
    for key in ("dx", "dx_var"):
        if key in out:
            out[key][:, -1] = 0.0
    for key in ("dy", "dy_var"):
        if key in out:
            out[key][-1, :] = 0.0
    out["spp"] = int(spp)
    out["n_invalid"] = n_invalid
    return out
