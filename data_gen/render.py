"""Per-pixel means and variances of the mean, rendered in bounded passes.

All samples of a pass are traced in one wavefront (sample index = pixel * n + s), then reduced per pixel
into sums and sums of squares in float64 by one more kernel (`segment_sums`); passes accumulate in
float64 on the host, so memory is bounded by ``samples_per_pass`` whatever the sample count (the
references and the gradient-domain renders use the same code).
"""
from __future__ import annotations

from typing import Callable, Iterable, Sequence

import numpy as np

from .integrator import FEATURE_DIMS, FEATURES, PathSettings, RoughnessLookup, derive_seed, trace
from .mitsuba_setup import is_vectorized
from jaxdenoise.errors import JaxdenoiseError

DEFAULT_SAMPLES_PER_PASS = 1 << 20
VERTICES = "vertices"  # `render_counts(vertices=True)`: the path vertices a pixel's samples traced (their cost)


def film_size(scene) -> tuple[int, int]:
    """(width, height) of the first sensor's film crop."""
    film = scene.sensors()[0].film()
    size = film.crop_size()
    return int(size[0]), int(size[1])


def camera_matrices(scene) -> dict:
    """The first sensor's ``world_to_camera`` and ``world_to_ndc`` as `jaxdenoise.view` defines them
    (column-vector 4x4 matrices; camera +x right, +y up, +z along the view: OpenEXR's
    ``worldToCamera``; NDC x, y in [-1, 1] left to right and bottom to top, over the film crop).

    Mitsuba's camera frame has +x to the image's left (``look_at``'s ``left`` axis), so the x axis is
    negated. ``world_to_ndc`` needs a perspective or thin-lens sensor (``x_fov``); for other sensors
    it is None. A crop window, or a principal point offset, is not supported here (None)."""
    import mitsuba as mi

    sensor = scene.sensors()[0]
    to_world = np.asarray(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    w2c = np.diag([-1.0, 1.0, 1.0, 1.0]) @ np.linalg.inv(to_world)
    out = {"world_to_camera": w2c.astype(np.float32), "world_to_ndc": None}
    params = mi.traverse(sensor)
    if "x_fov" not in params:
        return out
    film = sensor.film()
    (fw, fh), (cw, ch) = film.size(), film.crop_size()
    scalar = lambda v: float(np.asarray(v, np.float64).reshape(-1)[0])  # Dr.Jit arrays in vectorized variants
    off = [scalar(params[k]) for k in ("principal_point_offset_x", "principal_point_offset_y") if k in params]
    if (int(fw), int(fh)) != (int(cw), int(ch)) or any(off):
        return out
    tx = np.tan(np.radians(scalar(params["x_fov"])) / 2)
    ty = tx * float(fh) / float(fw)
    near = scalar(params["near_clip"]) if "near_clip" in params else 0.0
    proj = np.array([[1 / tx, 0, 0, 0], [0, 1 / ty, 0, 0], [0, 0, 1, -near], [0, 0, 1, 0]], np.float64)
    out["world_to_ndc"] = (proj @ w2c).astype(np.float32)
    return out


def _channels(name: str) -> int:
    return 3 if name == "color" else 1 if name == VERTICES else FEATURE_DIMS[name]


def _sample_wavefront(scene, sensor, sampler, idx, width: int):
    """Camera rays for the samples of a wavefront, ``idx`` holding each sample's pixel (row-major over
    the film crop; box filter: uniform in the pixel)."""
    import drjit as dr
    import mitsuba as mi

    film = sensor.film()
    pos = mi.Vector2i()
    pos.y = mi.Int32(idx // dr.opaque(mi.UInt32, width))
    pos.x = mi.Int32(idx) - pos.y * width
    pos += mi.Vector2i(film.crop_offset())
    pos_f = mi.Vector2f(pos) + sampler.next_2d()
    scale = dr.rcp(mi.ScalarVector2f(film.crop_size()))
    offset = -mi.ScalarVector2f(film.crop_offset()) * scale
    return camera_ray(sensor, sampler, dr.fma(pos_f, scale, offset))


def _traced_components(scene, sensor, sampler, idx, width: int, settings, record, rough, names) -> list:
    """Trace the wavefront whose samples fall on pixels ``idx``; return every buffer of ``names`` as
    per-sample scalar arrays (colour and 3-vectors split per channel), evaluated in one launch."""
    import drjit as dr

    ray, weight = _sample_wavefront(scene, sensor, sampler, idx, width)
    out = trace(scene, sampler, ray, True, settings=settings, record=record, roughness=rough)
    out["color"] = out["color"] * weight
    comps = []
    for name in names:
        v = out[name]
        comps.extend([v[c] for c in range(3)] if _channels(name) == 3 else [v])
    dr.eval(*comps)
    return comps


def camera_samples(sensor, sampler):
    """The camera sample dimensions after the film position (aperture, time, wavelength), drawn in
    this fixed order, which `data_gen.gradient` relies on to replay the same samples."""
    import mitsuba as mi

    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Vector2f(0.5)
    t = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0:
        t += sampler.next_1d() * sensor.shutter_open_time()
    wav = sampler.next_1d()
    return aperture, t, wav


def camera_ray(sensor, sampler, pos_film, samples=None):
    """Ray and weight through film position ``pos_film`` ([0, 1]^2 over the crop window). The other
    camera dimensions come from ``samples`` (a `camera_samples` result, so that several rays can
    share them: the gradient-domain shifts) or are drawn from ``sampler``."""
    import mitsuba as mi

    aperture, t, wav = camera_samples(sensor, sampler) if samples is None else samples
    ray, weight = sensor.sample_ray_differential(time=t, sample1=wav, sample2=pos_film, sample3=aperture)
    return mi.Ray3f(ray), weight


def render_moments(scene, *, spp: int, seed: int, settings: PathSettings, record: Iterable[str] = (),
                   samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS,
                   on_pass: Callable[[int], None] | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Sums and sums of squares over ``spp`` samples per pixel, per buffer.

    Returns ``{name: (sum, sumsq)}`` with float64 arrays of shape (H, W, C) for ``color`` and every
    feature in ``record``. ``on_pass(k)`` is called after each pass with the samples it added per pixel.
    """
    import drjit as dr
    import mitsuba as mi

    if not isinstance(spp, (int, np.integer)) or spp < 1:
        raise JaxdenoiseError(f"spp must be an int >= 1, got {spp!r}")
    record = _check_record(record)
    names = ["color"] + [f for f in FEATURES if f in record]
    width, height = film_size(scene)
    npix = width * height
    sensor = scene.sensors()[0]
    rough = RoughnessLookup(scene) if "roughness" in record else None
    acc = {k: (np.zeros((npix, _channels(k))), np.zeros((npix, _channels(k)))) for k in names}

    if not is_vectorized():
        _render_scalar(scene, sensor, spp, seed, settings, record, rough, acc, width, on_pass)
    else:
        per_pass = max(1, min(int(spp), samples_per_pass // max(npix, 1)))
        sampler = mi.load_dict({"type": "independent"})
        done, k = 0, 0
        while done < spp:
            n = min(per_pass, spp - done)
            sampler.seed(dr.opaque(mi.UInt32, derive_seed(seed, "pass", k)), npix * n)
            idx = dr.arange(mi.UInt32, npix * n)
            if n > 1:
                idx = idx // dr.opaque(mi.UInt32, n)
            comps = _traced_components(scene, sensor, sampler, idx, width, settings, record, rough, names)
            sums = block_sums(comps, npix, n)
            i = 0
            for name in names:
                c = _channels(name)
                acc[name][0][:] += np.stack([a for a, _ in sums[i:i + c]], -1)
                acc[name][1][:] += np.stack([b for _, b in sums[i:i + c]], -1)
                i += c
            del comps, sums
            done += n
            k += 1
            if on_pass is not None:
                on_pass(n)
    return {k: (v[0].reshape(height, width, -1), v[1].reshape(height, width, -1)) for k, v in acc.items()}


def first_hits(scene, *, spp: int = 16, seed: int = 0) -> dict[str, np.ndarray]:
    """What each pixel's camera rays hit first, as fractions of ``spp`` rays per pixel (uniform in the
    pixel, as the renders' box filter): ``surface`` (a shape that emits nothing toward the ray, which
    includes the back of a one-sided area light), ``emitter`` (an area emitter's emitting side; an
    environment seen directly counts as neither: depth 0). (H, W) float64
    each. The masks the colour-level studies need (issue 33: surface pixels and emitters apart); one
    intersection per ray, so far cheaper than a render. Vectorized (LLVM) variants only."""
    import drjit as dr
    import mitsuba as mi

    if not isinstance(spp, (int, np.integer)) or spp < 1:
        raise JaxdenoiseError(f"first_hits: spp must be an int >= 1, got {spp!r}")
    if not is_vectorized():
        raise JaxdenoiseError("first_hits needs a vectorized Mitsuba variant (llvm_*); this one is scalar "
                              "(scripts/setup.sh installs the LLVM it needs)")
    width, height = film_size(scene)
    npix = width * height
    sensor = scene.sensors()[0]
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, derive_seed(seed, "first-hits")), npix * spp)
    idx = dr.arange(mi.UInt32, npix * spp) // dr.opaque(mi.UInt32, spp)
    ray, _ = _sample_wavefront(scene, sensor, sampler, idx, width)
    si = scene.ray_intersect(ray)
    emitters = si.emitter(scene)
    emitter = si.is_valid() & (emitters != None)  # noqa: E711 - Dr.Jit's pointer comparison
    # an emitter counts where it sends light toward the camera: a one-sided area light seen from
    # behind emits nothing there and is a surface (its reference is black, not a light)
    le = emitters.eval(si, emitter)
    emitter &= (le[0] > 0) | (le[1] > 0) | (le[2] > 0)
    comps = [mi.Float(dr.select(si.is_valid() & ~emitter, 1.0, 0.0)), mi.Float(dr.select(emitter, 1.0, 0.0))]
    dr.eval(*comps)
    (surf, _), (em, _) = block_sums(comps, npix, spp)
    return {"surface": (surf / spp).reshape(height, width), "emitter": (em / spp).reshape(height, width)}


def _check_record(record: Iterable[str]) -> frozenset[str]:
    record = frozenset(record)
    unknown = record - set(FEATURES)
    if unknown:
        raise JaxdenoiseError(f"record: unknown feature(s) {sorted(unknown)}; known: {list(FEATURES)}")
    return record


def render_counts(scene, *, parts: Sequence[np.ndarray], seed: int, settings: PathSettings,
                  record: Iterable[str] = (), samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS,
                  vertices: bool = False,
                  on_pass: Callable[[float], None] | None = None) -> list[dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Per-pixel sample counts (adaptive sampling, `data_gen.adaptive`): pixel ``p`` gets
    ``sum_q parts[q][p]`` samples, the first ``parts[0][p]`` of them summed into the first result, the
    next ``parts[1][p]`` into the second, and so on (independent samples: two parts are two
    independent half-buffers). Returns one ``{name: (sum, sumsq)}`` per part, as `render_moments`.

    ``parts``: (H, W) arrays of non-negative integers. The counts are fixed before the call, so each
    part's per-pixel sums give an unbiased mean. ``vertices``: each result also sums ``"vertices"``,
    the path vertices the samples traced (one channel: the cost of a pixel's samples).
    ``on_pass(k)``: after each wavefront, with the samples it added per pixel on average.

    Vectorized variants trace wavefronts of at most ``samples_per_pass`` samples (at least one
    pixel's), cut at pixel boundaries, each pixel's samples contiguous and drawn as `render_moments`
    draws them (one part of ``spp`` samples everywhere gives its samples when the frame fits one
    wavefront); the per-pixel sums are accumulated on the device (`segment_sums`), so only
    per-pixel sums come back.
    """
    record = _check_record(record)
    names = ["color"] + [f for f in FEATURES if f in record] + ([VERTICES] if vertices else [])
    width, height = film_size(scene)
    npix = width * height
    parts = [check_counts(c, height, width).reshape(-1) for c in parts]
    if not parts:
        raise JaxdenoiseError("render_counts: 'parts' is empty; expected at least one (H, W) count array")
    accs = [{k: (np.zeros((npix, _channels(k))), np.zeros((npix, _channels(k)))) for k in names} for _ in parts]
    sensor = scene.sensors()[0]
    rough = RoughnessLookup(scene) if "roughness" in record else None
    if not is_vectorized():
        for q, c in enumerate(parts):
            _render_scalar(scene, sensor, 0, derive_seed(seed, "part", q), settings, record, rough, accs[q], width,
                           on_pass, c)
    else:
        _render_parts(scene, sensor, parts, seed, settings, record, rough, accs, names, width, samples_per_pass,
                      on_pass)
    return [{k: (v[0].reshape(height, width, -1), v[1].reshape(height, width, -1)) for k, v in acc.items()}
            for acc in accs]


def check_counts(counts, height: int, width: int) -> np.ndarray:
    """Per-pixel sample counts as int64 (H, W), refused with a clear error unless they are finite
    non-negative integers on the film's pixel grid."""
    c = np.asarray(counts)
    if c.shape != (height, width):
        raise JaxdenoiseError(f"counts: shape {c.shape}; expected the film's ({height}, {width})")
    if c.size and (not np.all(np.isfinite(c)) or np.any(c < 0) or np.any(c != np.round(c))):
        raise JaxdenoiseError("counts: expected non-negative integers (samples per pixel)")
    return c.astype(np.int64)


def _render_parts(scene, sensor, parts, seed, settings, record, rough, accs, names, width, samples_per_pass,
                  on_pass) -> None:
    import drjit as dr
    import mitsuba as mi

    counts = sum(parts)
    npix = counts.size
    cum = np.cumsum(counts)
    sampler = mi.load_dict({"type": "independent"})
    start, k = 0, 0
    while start < npix:
        before = int(cum[start - 1]) if start else 0
        end = max(start + 1, int(np.searchsorted(cum, before + samples_per_pass, side="right")))
        c = counts[start:end]
        n = int(c.sum())
        if n:
            sampler.seed(dr.opaque(mi.UInt32, derive_seed(seed, "pass", k)), n)   # render_moments' streams
            pix = np.repeat(np.arange(start, end, dtype=np.uint32), c)
            comps = _traced_components(scene, sensor, sampler, mi.UInt32(pix), width, settings, record, rough,
                                       names)
            # each part's range [b_q, b_{q+1}) of a pixel's samples; b_0 = the pixel's first sample
            bounds = [np.cumsum(c) - c]
            for part in parts:
                bounds.append(bounds[-1] + part[start:end])
            res = [segment_sums(comps, bounds[q], bounds[q + 1]) for q in range(len(parts))]
            for q, acc in enumerate(accs):
                arr = [(np.asarray(a, np.float64), np.asarray(b, np.float64)) for a, b in res[q]]
                i = 0
                for name in names:
                    ch = _channels(name)
                    acc[name][0][start:end] += np.stack([a for a, _ in arr[i:i + ch]], -1)
                    acc[name][1][start:end] += np.stack([b for _, b in arr[i:i + ch]], -1)
                    i += ch
            del comps, res
            k += 1
        if on_pass is not None:
            on_pass(n / npix)
        start = end


def block_sums(comps, npix: int, n: int) -> list:
    """`segment_sums` of a uniform wavefront: lane ``i`` is sample ``i % n`` of pixel ``i // n``."""
    begin = np.arange(npix, dtype=np.int64) * n
    return segment_sums(comps, begin, begin + n)


def segment_sums(comps, begin: np.ndarray, end: np.ndarray) -> list:
    """Per pixel, ``(sum, sum of squares)`` of each evaluated per-sample array in ``comps`` over the
    pixel's samples ``[begin, end)``: one symbolic Dr.Jit loop, a lane per pixel walking its own
    samples by gathers, accumulating in float64 (deterministic and free of the cancellation a
    prefix-sum difference suffers next to a firefly). Returns float64 NumPy pairs, in ``comps`` order."""
    import drjit as dr
    import mitsuba as mi

    first, stop = mi.UInt32(begin.astype(np.uint32)), mi.UInt32(end.astype(np.uint32))
    zeros = [mi.Float64(dr.zeros(mi.Float64, len(begin))) for _ in comps]

    def body(j, s, s2):
        vs = [mi.Float64(dr.gather(mi.Float, c, j)) for c in comps]
        return j + 1, [a + v for a, v in zip(s, vs)], [a + v * v for a, v in zip(s2, vs)]

    _, s, s2 = dr.while_loop((first, zeros, [mi.Float64(z) for z in zeros]), lambda j, s, s2: j < stop, body,
                             label="data_gen.segment_sums")
    dr.eval(s, s2)
    return [(np.asarray(a, np.float64), np.asarray(b, np.float64)) for a, b in zip(s, s2)]


def _render_scalar(scene, sensor, spp, seed, settings, record, rough, acc, width, on_pass, counts=None) -> None:
    """The same estimator one sample at a time, for the ``scalar_rgb`` fallback (slow: tiny images only);
    ``counts`` (flat, per pixel) replaces ``spp`` where given."""
    import mitsuba as mi

    film = sensor.film()
    size = film.crop_size()
    off = film.crop_offset()
    sampler = mi.load_dict({"type": "independent"})
    npix = acc["color"][0].shape[0]
    for p in range(npix):
        sampler.seed(derive_seed(seed, "pixel", p), 1)
        y, x = divmod(p, width)
        for _ in range(spp if counts is None else int(counts[p])):
            u = sampler.next_2d()
            pos = mi.ScalarVector2f((x + off[0] + u[0] - off[0]) / size[0], (y + off[1] + u[1] - off[1]) / size[1])
            aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
            t = sensor.shutter_open()
            if sensor.shutter_open_time() > 0:
                t += sampler.next_1d() * sensor.shutter_open_time()
            ray, weight = sensor.sample_ray_differential(t, sampler.next_1d(), pos, aperture)
            out = trace(scene, sampler, mi.Ray3f(ray), True, settings=settings, record=record, roughness=rough)
            out["color"] = out["color"] * weight
            for name, (s, q) in acc.items():
                v = np.array([out[name][c] for c in range(3)] if _channels(name) == 3 else [out[name]], np.float64)
                s[p] += v
                q[p] += v * v
        if on_pass is not None and p == npix - 1:
            on_pass(spp if counts is None else float(np.mean(counts)))


def moments_to_buffers(moments: dict, spp: int) -> dict[str, np.ndarray]:
    """Means and variances of the mean (float32 HWC) from ``render_moments`` output.

    ``color_var`` keeps 3 channels; ``<feature>_var`` is the mean of the per-channel variances (one
    channel). With ``spp == 1`` the variance cannot be estimated, so no ``*_var`` is returned.
    """
    out: dict[str, np.ndarray] = {}
    for name, (s, q) in moments.items():
        mean = s / spp
        out[name] = mean.astype(np.float32)
        if spp > 1:
            # Unbiased sample variance / n. Guard: float64 cancellation can leave tiny negatives.
            var = np.maximum(q - s * s / spp, 0.0) / (spp - 1) / spp
            if name == "color":
                out["color_var"] = var.astype(np.float32)
            else:
                out[f"{name}_var"] = var.mean(-1, keepdims=True).astype(np.float32)
    return out


def render_buffers(scene, *, spp: int, seed: int, settings: PathSettings, record: Iterable[str] = (),
                   samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS, on_pass=None) -> dict[str, np.ndarray]:
    """Render ``spp`` samples per pixel and return the buffers (means + variances of the mean)."""
    m = render_moments(scene, spp=spp, seed=seed, settings=settings, record=record,
                       samples_per_pass=samples_per_pass, on_pass=on_pass)
    return moments_to_buffers(m, spp)


def render_reference(scene, *, spp: int, seed: int, settings: PathSettings,
                     samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS, on_pass=None) -> tuple[np.ndarray, float]:
    """A radiance-only reference from two independent halves (different seeds).

    Returns (image float32 HWC, RelMSE between the two halves). The RelMSE of the full-spp average
    against the true image is about a quarter of the half-vs-half RelMSE (each half has twice the
    variance of the average, and their difference four times): both numbers go into the manifest.
    """
    if spp < 2:
        raise JaxdenoiseError(f"ref_spp must be >= 2 (two independent halves), got {spp}")
    half_a = spp // 2
    half_b = spp - half_a
    ma = render_moments(scene, spp=half_a, seed=derive_seed(seed, "ref-a"), settings=settings,
                        samples_per_pass=samples_per_pass, on_pass=on_pass)["color"][0]
    mb = render_moments(scene, spp=half_b, seed=derive_seed(seed, "ref-b"), settings=settings,
                        samples_per_pass=samples_per_pass, on_pass=on_pass)["color"][0]
    a, b = ma / half_a, mb / half_b
    ref = ((ma + mb) / spp).astype(np.float32)
    # RelMSE as in docs/architecture.md (eps = 0.01), computed here in float64 without importing jax.
    noise = float(np.mean((a - b) ** 2 / (ref.astype(np.float64) ** 2 + 0.01)))
    return ref, noise
