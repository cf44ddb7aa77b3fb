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

from .integrator import PathSettings, derive_seed, trace
from .mitsuba_setup import is_vectorized, setup_mitsuba
from .render import DEFAULT_SAMPLES_PER_PASS, camera_ray
from .scenes import load_scene

__all__ = ["render_gradients", "trace_shifted", "OFFSETS"]

# Film offsets (pixels) of the three correlated traces: base, horizontal and vertical neighbour.
OFFSETS: dict[str, tuple[int, int]] = {"base": (0, 0), "dx": (1, 0), "dy": (0, 1)}


def trace_shifted(scene, *, seed: int, offset: tuple[int, int], n: int, width: int, height: int,
                  settings: PathSettings):
    """Per-sample radiance of one wavefront whose camera samples are shifted by ``offset`` pixels.

    Lane ``i`` is sample ``i % n`` of base pixel ``(x, y) = (p % width, p // width)``,
    ``p = i // n``; its film position is ``(x + offset[0] + u, y + offset[1] + v)`` on a
    ``width x height`` grid laid over the sensor's film crop window, ``(u, v)`` being the lane's
    first 2D sample. The sampler is a fresh ``independent`` one seeded with ``(seed, lanes)``, so two
    calls that differ only in ``offset`` replay the same random numbers lane by lane. The camera
    sample dimensions (position, aperture, time, wavelength) are drawn in the same order as
    `data_gen.render` so that offset (0, 0) reproduces its samples exactly.

    Returns the Dr.Jit ``Spectrum`` (unevaluated) of ``width * height * n`` lanes.
    """
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
    # Opaque offsets keep the traced kernel identical for the three traces, so the LLVM backend
    # compiles it once and replays it from its cache.
    pos_f = mi.Vector2f(mi.Float(px) + dr.opaque(mi.Float, float(offset[0])),
                        mi.Float(py) + dr.opaque(mi.Float, float(offset[1])))
    pos_f += sampler.next_2d()
    # [0, 1]^2 spans the film's crop window (what `sample_ray_differential` expects).
    pos_film = pos_f * dr.rcp(mi.ScalarVector2f(float(width), float(height)))
    ray, weight = camera_ray(sensor, sampler, pos_film)
    out = trace(scene, sampler, ray, True, settings=settings, record=frozenset())
    return out["color"] * weight


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
) -> dict[str, Any]:
    """Base image and gradient-domain finite differences by primary-sample-space replay.

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

    Returns:
        dict of float32 ``HWC`` arrays, 3 channels, linear radiance:
        ``primal`` (mean of the base paths) and ``primal_var`` (variance of that mean);
        ``dx`` = I[y, x+1] - I[y, x] and ``dy`` = I[y+1, x] - I[y, x], each the mean of per-sample
        differences of replayed pairs, with ``dx_var``, ``dy_var`` (variance of the mean; only when
        ``spp > 1``). The last column of ``dx``/``dx_var`` and the last row of ``dy``/``dy_var``
        would need pixels outside the image: they are 0. Also ``spp`` (int) and ``n_invalid``
        (int: lanes with a non-finite sample in any of the three traces; a non-finite base sample
        counts as 0 in ``primal``, a pair with a non-finite member as a difference of 0).
    """
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ValueError(f"spp: expected a positive integer, got {spp!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    if isinstance(samples_per_pass, bool) or not isinstance(samples_per_pass, (int, np.integer)) \
            or samples_per_pass < 1:
        raise ValueError(f"samples_per_pass: expected a positive integer, got {samples_per_pass!r}")
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
        raise ValueError("scene: has no sensor")
    film_w, film_h = (int(v) for v in scene.sensors()[0].film().crop_size())
    if resolution is None:
        width, height = film_w, film_h
    else:
        if len(resolution) != 2 or any(int(v) < 1 for v in resolution):
            raise ValueError(f"resolution: expected (width, height) of positive integers, got {resolution!r}")
        width, height = int(resolution[0]), int(resolution[1])
        if abs(width * film_h - height * film_w) > 1e-3 * film_w * height:
            raise ValueError(
                f"resolution: {width}x{height} does not keep the film's aspect ratio {film_w}x{film_h} "
                "(pixels would not be square)"
            )

    npix = width * height
    per_pass = max(1, min(int(spp), int(samples_per_pass) // npix))
    sums = {k: np.zeros((npix, 3), np.float64) for k in ("base", "dx", "dy")}
    sqs = {k: np.zeros((npix, 3), np.float64) for k in ("base", "dx", "dy")}
    n_invalid = 0
    done, k = 0, 0
    while done < spp:
        n = min(per_pass, int(spp) - done)
        pseed = derive_seed(seed, "pass", k)  # the same pass seeds as data_gen.render
        kw = dict(seed=pseed, n=n, width=width, height=height, settings=settings)
        base = trace_shifted(scene, offset=OFFSETS["base"], **kw)
        dr.eval(base)
        shx = trace_shifted(scene, offset=OFFSETS["dx"], **kw)
        dr.eval(shx)
        shy = trace_shifted(scene, offset=OFFSETS["dy"], **kw)
        dr.eval(shy)
        # Guard: a non-finite sample (a 0/0 in a BSDF or a degenerate frame) would poison its pixel
        # and the differences it enters: a non-finite base sample is set to 0, and a pair with a
        # non-finite member contributes a difference of 0. Lanes with any non-finite value are counted.
        finite = []
        for v in (base, shx, shy):
            f = mi.Bool(True)
            for c in range(3):
                f &= dr.isfinite(v[c])
            finite.append(f)
        ok_b, ok_x, ok_y = finite[0], finite[0] & finite[1], finite[0] & finite[2]
        n_invalid += int(dr.count(~(ok_x & ok_y))[0])
        comps = {}
        for c in range(3):
            comps[("base", c)] = dr.select(ok_b, base[c], 0.0)
            comps[("dx", c)] = dr.select(ok_x, shx[c] - base[c], 0.0)
            comps[("dy", c)] = dr.select(ok_y, shy[c] - base[c], 0.0)
        red = [dr.block_sum(v, n) for v in comps.values()] + [dr.block_sum(v * v, n) for v in comps.values()]
        dr.eval(*red)
        arrs = [np.asarray(a, dtype=np.float64) for a in red]
        m = len(comps)
        for j, (name, c) in enumerate(comps):
            sums[name][:, c] += arrs[j]
            sqs[name][:, c] += arrs[m + j]
        del base, shx, shy, comps, red
        done += n
        k += 1
        if on_pass is not None:
            on_pass(n)

    out: dict[str, Any] = {}
    for name, key in (("base", "primal"), ("dx", "dx"), ("dy", "dy")):
        s, q = sums[name], sqs[name]
        mean = s / spp
        # Unbiased sample variance / n (spp > 1 only). Guard: float64 cancellation in q - s^2/n can
        # leave tiny negatives where all samples are (nearly) equal, e.g. a perfectly correlated pair.
        var = np.maximum(q - s * s / spp, 0.0) / max(spp - 1, 1) / spp
        out[key] = mean.reshape(height, width, 3).astype(np.float32)
        if spp > 1:
            out[key + "_var"] = var.reshape(height, width, 3).astype(np.float32)
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
