"""One shot (noisy renders at several spp and instances + a reference) in the bench layout, resumable.

Layout (docs/architecture.md "Data folders"): ``out_dir/spp{spp:04d}_{instance:02d}.exr`` noisy renders,
``out_dir/reference.exr`` the reference, ``out_dir/shot.json`` the shot's manifest record. A file is
skipped on a re-run when it exists, its checksum matches the record and the record's settings equal
the requested ones; every file is written to a temporary name and renamed (``jaxdenoise.io`` and
``jaxdenoise.fsutil``), so an interrupted run never leaves a half-written file.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .integrator import FEATURES, PathSettings, derive_seed
from .mitsuba_setup import RenderTimer
from .render import DEFAULT_SAMPLES_PER_PASS, camera_matrices, film_size, render_buffers, render_reference
from .scenes import describe, load_scene
from jaxdenoise.buffers import EMISSION_FIELD, GRADIENT_FIELDS, SAMPLE_COUNT_FIELD
from jaxdenoise.errors import JaxdenoiseError

# What a gradient frame's ``seconds`` covers (written into its manifest entry).
GRADIENT_TIME_NOTE = ("seconds = the gradient frame rendered in one pass (colour, features, dx, dy together: "
                      "render_gradients(record=...)), Dr.Jit compilation excluded (compile_seconds); "
                      "buffer_seconds = a buffer-only render of the same frame (same seed: bit-identical colour and "
                      "features, checked), timed beside it: what a method that reads no gradient is charged")
SHOT_RECORD = "shot.json"
INTEGRATOR_NAME = "data_gen.buffers"


# --------------------------------------------------------------------------------------------------
# Which buffers to render
# --------------------------------------------------------------------------------------------------
def requested_fields(methods: Iterable[str] | None, buffers: Iterable[str] | None) -> frozenset[str] | None:
    """The Buffers fields asked for: ``buffers`` if given, else the union of the methods' ``needs()``,
    else None (= everything the scene can vary)."""
    from jaxdenoise.buffers import ALL_FIELDS

    if buffers is not None:
        buffers = frozenset(buffers)
        unknown = sorted(buffers - set(ALL_FIELDS))
        if unknown:
            raise JaxdenoiseError(f"buffers: unknown buffer name(s) {unknown}; known: {list(ALL_FIELDS)}")
        return buffers | {"color"}
    if methods is not None:
        import importlib

        registry = importlib.import_module("jaxdenoise.methods")  # jaxdenoise.methods may be shadowed by a function

        need: set[str] = {"color"}
        for name in methods:
            need |= set(registry.get(name).needs())
        return frozenset(need)
    return None


def plan_buffers(desc: dict, settings: PathSettings, requested: frozenset[str] | None, spp: int) -> tuple[list[str], dict[str, str]]:
    """(fields to write, {left-out buffer: why}) for one noisy render.

    With ``requested is None`` every buffer the scene can vary is written; a buffer a method asks for
    is always written (even if constant here), except variances at 1 spp, which cannot be estimated.
    """
    from jaxdenoise.buffers import IMAGE_FIELDS

    invariant: dict[str, str] = {}
    if settings.max_depth < 3:
        invariant["albedo2"] = f"max_depth={settings.max_depth} < 3: paths end before a second surface"
    if desc["emitters"] == 0:
        invariant["visibility"] = "the scene has no emitters"
    elif settings.max_depth < 2:
        invariant["visibility"] = f"max_depth={settings.max_depth} < 2: no shadow rays"
    if len(desc["roughness_values"]) <= 1:
        invariant["roughness"] = f"every BSDF has the same roughness {desc['roughness_values']}: a constant buffer"
    # the per-pixel sample count is written by adaptive renders only (`data_gen.adaptive`), the emission
    # beside the gradients that leave it out (`render_shot`'s gradient_emission)
    candidates = [f for f in IMAGE_FIELDS if f not in (SAMPLE_COUNT_FIELD, EMISSION_FIELD)]
    left: dict[str, str] = {}
    fields: list[str] = []
    for f in candidates:
        base = f[:-4] if f.endswith("_var") else f
        if requested is not None and f not in requested:
            left[f] = "not needed by the requested methods/buffers"
            continue
        if requested is None and f in GRADIENT_FIELDS:
            left[f] = "no gradient-domain method requested (shifted paths not traced)"
            continue
        if requested is None and base in invariant:
            left[f] = invariant[base]
            continue
        if f.endswith("_var") and spp < 2:
            left[f] = "1 spp: the variance of the mean cannot be estimated from one sample"
            continue
        fields.append(f)
    if not desc["lens"]:
        left["lens"] = "pinhole camera: no aperture samples are drawn"
    return fields, left


# --------------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------------
def sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def data_sha256(arrays: dict) -> str:
    """Checksum of the pixel data (field names + float32 bytes). The EXR file's own checksum also
    covers header fields such as OpenImageIO's DateTime, which differ between otherwise equal runs."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        h.update(k.encode())
        h.update(np.ascontiguousarray(np.asarray(arrays[k], np.float32)).tobytes())
    return h.hexdigest()


def _read_record(out_dir: Path) -> dict:
    p = out_dir / SHOT_RECORD
    if not p.exists():
        return {}
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError:
        return {}  # a record written by a crashed older version: re-render everything


def _is_done(out_dir: Path, record: dict, name: str, key: dict) -> bool:
    entry = record.get("files", {}).get(name)
    path = out_dir / name
    if entry is None or not path.exists() or entry.get("key") != key:
        return False
    return entry.get("sha256") == sha256(path)


def _scene_label(scene: Any) -> str:
    from .library import is_spec, scene_label

    if is_spec(scene):  # library:<name> -> library:<name>@<digest>: an edited scene is re-rendered
        return scene_label(scene.split(":", 1)[1])
    if isinstance(scene, (str, os.PathLike)):
        return os.fspath(scene)
    if isinstance(scene, dict):
        return str(scene.get("__name__", scene.get("__family__", "dict")))
    return "mitsuba.Scene"


# --------------------------------------------------------------------------------------------------
# render_shot
# --------------------------------------------------------------------------------------------------
def render_shot(scene: Any, out_dir: str | os.PathLike, *, spp: Sequence[int] = (4,), ref_spp: int = 1024,
                instances: int = 1, methods: Iterable[str] | None = None, buffers: Iterable[str] | None = None,
                max_depth: int = 8, rr_depth: int = 5, seed: int = 0, progress: bool = True,
                samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS, width: int | None = None,
                height: int | None = None, shift: str | None = None, primal: str = "base",
                gradient_emission: str = "separate", label: str | None = None, adaptive: str | None = None, passes: int = 1,
                initial_spp: int | None = None, map_spp: int | None = None, _stop_after: int | None = None) -> dict:
    """Render noisy frames at every ``spp`` (``instances`` independent realizations each) and a
    ``ref_spp`` reference into ``out_dir``; return the shot's manifest record (also in ``shot.json``).

    ``scene``: scene dict, XML path or loaded ``mi.Scene``. ``methods`` (registered names) or
    ``buffers`` (field names) choose what is written; both None = every buffer the scene can vary.
    ``ref_spp=0`` skips the reference. Finished files are skipped (resumable).
    ``shift`` (``replay`` or ``reconnect``; None = `data_gen.gradient.DEFAULT_SHIFT`) and ``primal``
    (``base`` or ``gpt``: the colour of gradient frames is then the G-PT primal) apply to frames with
    gradient buffers (`data_gen.gradient.render_gradients`), and so does ``gradient_emission``
    (``separate``: the directly seen emission is kept out of dx, dy and written as the ``emission``
    layer, the header's ``gradient_emission`` says so; ``included``: in the gradients). ``label``: the scene's name in the record
    and the resume keys (default: the XML path as given, a dict's ``__name__``, ``library:<name>@<digest>``
    for a library scene, ``mitsuba.Scene`` for a loaded scene).
    ``adaptive`` (`data_gen.adaptive.parse_spec`: ``relvar``, ``METHOD``, ``METHOD:relvar|halves``)
    renders every noisy frame adaptively: an ``initial_spp`` uniform pilot (of which ``map_spp``
    samples per pixel feed the map), then ``passes`` passes whose per-pixel counts follow the map; the
    frame gets the ``spp`` layer (`data_gen.adaptive`).
    """
    from jaxdenoise.buffers import Buffers
    from jaxdenoise.fsutil import remove_stale_temporaries, write_json
    from jaxdenoise.io import write_buffers

    spp = [int(s) for s in (spp if isinstance(spp, (list, tuple)) else [spp])]
    if not spp and not ref_spp:
        raise JaxdenoiseError("render_shot: nothing to render (empty spp and ref_spp=0)")
    if any(s < 1 for s in spp):
        raise JaxdenoiseError(f"spp: every value must be >= 1, got {spp}")
    if not isinstance(instances, int) or instances < 1:
        raise JaxdenoiseError(f"instances must be an int >= 1, got {instances!r}")
    if ref_spp and ref_spp < 2:
        raise JaxdenoiseError(f"ref_spp must be 0 (no reference) or >= 2, got {ref_spp}")
    shift = _check_shift(shift, primal, gradient_emission)
    settings = PathSettings(max_depth=int(max_depth), rr_depth=int(rr_depth))
    label = _scene_label(scene) if label is None else str(label)
    spec = _check_adaptive(adaptive, spp, passes, initial_spp, map_spp)
    loaded = load_scene(scene, width=width, height=height)
    desc = describe(loaded)
    w, h = film_size(loaded)
    camera = {k: v for k, v in camera_matrices(loaded).items() if v is not None}  # each frame's header
    requested = requested_fields(methods, buffers)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out_dir)  # left by a writer that was killed: the resumed run redoes them
    record = _read_record(out_dir)
    files: dict[str, dict] = dict(record.get("files", {}))
    base_key = {"scene": label, "seed": int(seed), "width": w, "height": h, "max_depth": settings.max_depth,
                "rr_depth": settings.rr_depth, "integrator": INTEGRATOR_NAME}
    jobs = []
    left_out: dict[str, dict[str, str]] = {}
    for s in spp:
        fields, left = plan_buffers(desc, settings, requested, s)
        left_out[f"spp{s}"] = left
        for i in range(instances):
            name = noisy_name(s, i, spec)
            key = dict(base_key, spp=s, instance=i, fields=fields)
            if any(f in fields for f in GRADIENT_FIELDS):
                if spec is not None:
                    raise JaxdenoiseError("adaptive sampling renders no gradient buffers (dx, dy); request methods "
                                          "or buffers without them, or sample uniformly")
                key.update(shift=shift, primal=primal, gradient_emission=gradient_emission)
                if gradient_emission == "separate":
                    fields = fields + [EMISSION_FIELD]
                    key.update(fields=fields)
            if spec is not None:
                fields = fields + [SAMPLE_COUNT_FIELD]
                key.update(fields=fields, adaptive=spec.label, passes=int(passes), initial_spp=initial_spp,
                           map_spp=map_spp)
            jobs.append((name, key, s, i, fields))
    if ref_spp:
        jobs.append(("reference.exr", dict(base_key, spp=int(ref_spp), reference=True), int(ref_spp), None, ["color"]))
    todo = [j for j in jobs if not _is_done(out_dir, record, j[0], j[1])]
    total = sum(j[2] for j in todo)
    bar = None
    if progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="spp", desc=f"{out_dir.name}", leave=False, file=sys.stderr)

    def tick(n: int) -> None:
        if bar is not None:
            bar.update(n)

    rec = {"scene": label, "seed": int(seed), "width": w, "height": h, "settings": dataclass_dict(settings),
           "spp": spp, "instances": instances, "ref_spp": int(ref_spp), "scene_info": desc,
           "requested": sorted(requested) if requested is not None else None, "left_out": left_out,
           "files": files, "reference": record.get("reference")}
    written = 0
    try:
        for name, key, s, inst, fields in todo:
            if inst is None:
                with RenderTimer() as timer:
                    ref, noise = render_reference(loaded, spp=s, seed=derive_seed(seed, "reference"),
                                                  settings=settings, samples_per_pass=samples_per_pass, on_pass=tick)
                seconds, compile_seconds = timer.seconds, timer.compile_seconds
                attrs = _attrs(base_key, s, None, seconds)
                attrs["ref_relmse_halves"] = noise
                write_buffers(out_dir / name, Buffers(color=ref, spp=s, **camera), attrs)
                dsha = data_sha256({"color": ref})
                rec["reference"] = {"file": name, "spp": s, "seconds": seconds,
                                    "compile_seconds": compile_seconds, "relmse_halves": noise,
                                    "relmse_estimate": noise / 4.0,
                                    "note": "relmse_halves = RelMSE between two independent half-spp renders; "
                                            "the full reference's own RelMSE is about a quarter of it"}
            else:
                fseed = derive_seed(seed, "noisy", s, inst)
                if spec is not None:
                    data, seconds, compile_seconds, adaptive_info = _adaptive_frame(
                        loaded, s, fseed, settings, fields, samples_per_pass, spec, passes, initial_spp, map_spp,
                        camera, tick)
                    buffer_seconds, stats = None, None
                else:
                    data, seconds, compile_seconds, buffer_seconds, stats = _noisy_frame(
                        loaded, s, fseed, settings, fields, samples_per_pass, shift, primal, gradient_emission, tick)
                bufs = Buffers(**{f: data[f] for f in fields if f in data}, spp=s, **camera)
                attrs = _attrs(base_key, s, inst, seconds)
                if spec is not None:
                    attrs.update(adaptive=spec.label, adaptive_passes=int(passes),
                                 adaptive_pilot_spp=int(adaptive_info["pilot_spp"]),
                                 adaptive_map_spp=int(adaptive_info["map_spp"]))
                if buffer_seconds is not None:
                    attrs.update(gradient_shift=shift, primal=primal, gradient_emission=gradient_emission)
                write_buffers(out_dir / name, bufs, attrs)
                dsha = data_sha256({f: data[f] for f in fields if f in data})
                key = dict(key)
                files[name] = {"key": key, "seconds": seconds, "compile_seconds": compile_seconds,
                               "spp": s, "instance": inst, "seed": fseed, "fields": fields}
                if buffer_seconds is not None:
                    files[name]["buffer_seconds"] = buffer_seconds
                    files[name]["gradient_note"] = GRADIENT_TIME_NOTE
                    files[name]["shift_stats"] = stats
                if spec is not None:
                    files[name]["adaptive"] = adaptive_info
            files.setdefault(name, {})
            files[name].update({"key": key, "sha256": sha256(out_dir / name), "data_sha256": dsha})
            if inst is None:
                files[name].update({"seconds": seconds, "compile_seconds": compile_seconds, "spp": s})
            rec["files"] = files
            write_json(out_dir / SHOT_RECORD, rec)
            written += 1
            if _stop_after is not None and written >= _stop_after:
                raise KeyboardInterrupt(f"render_shot: stopped after {written} file(s) (_stop_after)")
    finally:
        if bar is not None:
            bar.close()
    # Drop entries of files no longer requested, so the record lists exactly the shot's files.
    # (a run of the other sampling mode keeps its files: uniform and adaptive frames share the shot)
    wanted = {j[0] for j in jobs} | {k for k in files if _mode(k) != _mode(noisy_name(1, 0, spec))
                                     and k != "reference.exr" and (out_dir / k).exists()}
    rec["files"] = {k: v for k, v in files.items() if k in wanted}
    # every render this shot cost, a gradient frame's timed buffer pass too
    rec["render_seconds"] = float(sum(v.get("seconds", 0.0) + (v.get("buffer_seconds") or 0.0)
                                      for v in rec["files"].values()))
    write_json(out_dir / SHOT_RECORD, rec)
    return rec


def render_frame(scene: Any, *, spp: int = 4, methods: Iterable[str] | None = None,
                 buffers: Iterable[str] | None = None, seed: int = 0, instance: int = 0, max_depth: int = 8,
                 rr_depth: int = 5, width: int | None = None, height: int | None = None, shift: str | None = None,
                 primal: str = "base", gradient_emission: str = "separate",
                 samples_per_pass: int = DEFAULT_SAMPLES_PER_PASS):
    """One noisy frame rendered into memory as `jaxdenoise.Buffers`, no file written: the frame
    `render_shot` (same arguments) writes to ``spp{spp:04d}_{instance:02d}.exr``, the same samples
    (its seed is derived the same way) and the same buffers (``methods``' ``needs()``, or ``buffers``,
    or everything the scene varies), with ``spp`` and the camera matrices as the file's header has
    them; pass it straight to `jaxdenoise.denoise`. ``scene``: an XML path, a scene dict, a loaded
    ``mi.Scene`` or ``library:<name>``; ``width``/``height`` resize its film."""
    from jaxdenoise.buffers import Buffers

    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise JaxdenoiseError(f"spp must be an int >= 1, got {spp!r}")
    if isinstance(instance, bool) or not isinstance(instance, (int, np.integer)) or instance < 0:
        raise JaxdenoiseError(f"instance must be an int >= 0, got {instance!r}")
    shift = _check_shift(shift, primal, gradient_emission)
    settings = PathSettings(max_depth=int(max_depth), rr_depth=int(rr_depth))
    loaded = load_scene(scene, width=width, height=height)
    camera = {k: v for k, v in camera_matrices(loaded).items() if v is not None}
    fields, _ = plan_buffers(describe(loaded), settings, requested_fields(methods, buffers), int(spp))
    if gradient_emission == "separate" and any(f in fields for f in GRADIENT_FIELDS):
        fields = fields + [EMISSION_FIELD]
    data = _noisy_frame(loaded, int(spp), derive_seed(seed, "noisy", int(spp), int(instance)), settings, fields,
                        samples_per_pass, shift, primal, gradient_emission, None, buffer_pass=False)[0]
    return Buffers(**{f: data[f] for f in fields if f in data}, spp=int(spp), **camera)


def noisy_name(spp: int, instance: int, spec=None) -> str:
    """A noisy frame's file: ``spp0016_00.exr``, or ``spp0016_00_adaptive-oidn-halves.exr`` for an
    adaptive one (`data_gen.adaptive.Spec`; ``oidn:halves/2`` -> ``adaptive-oidn-halves-div2``), so
    both sit in one shot beside one reference."""
    tail = "" if spec is None else "_adaptive-" + spec.label.replace(":", "-").replace("/", "-div")
    return f"spp{int(spp):04d}_{int(instance):02d}{tail}.exr"


def _mode(name: str) -> str:
    """The sampling mode a noisy file's name says (``''``: uniform)."""
    stem = name[:-4] if name.endswith(".exr") else name
    return stem.split("_", 2)[2] if stem.count("_") >= 2 else ""


def _check_adaptive(adaptive, spp, passes, initial_spp, map_spp):
    """The parsed adaptive spec (None: uniform sampling), with every spp's plan checked up front."""
    if adaptive is None:
        return None
    from .adaptive import map_split, parse_spec, plan

    spec = parse_spec(adaptive)
    for s in spp:
        map_split(plan(int(s), passes, initial_spp, 1)[0], map_spp)
    return spec


def _adaptive_frame(loaded, spp, fseed, settings, fields, samples_per_pass, spec, passes, initial_spp, map_spp,
                    camera, tick):
    """(buffers dict, seconds, compile seconds, the run's record) of one adaptive frame; the seconds
    are the render's and the maps' (estimates and denoising)."""
    from .adaptive import render_adaptive

    record_feats = [f for f in FEATURES if f in fields or f"{f}_var" in fields]
    data, info = render_adaptive(loaded, spp=spp, adaptive=spec, passes=passes, initial=initial_spp,
                                 map_spp=map_spp, seed=fseed,
                                 settings=settings, record=record_feats, samples_per_pass=samples_per_pass,
                                 camera=camera, on_pass=tick)
    return data, info["render_seconds"] + info["map_seconds"], info["compile_seconds"], info


def _check_shift(shift: str | None, primal: str, gradient_emission: str = "separate") -> str:
    """The gradient shift to use (the default for None), with ``primal`` checked against it and
    ``gradient_emission`` against `data_gen.gradient.DIRECT_EMISSION`."""
    from .gradient import DEFAULT_SHIFT, DIRECT_EMISSION, PRIMALS, SHIFTS

    if gradient_emission not in DIRECT_EMISSION:
        raise JaxdenoiseError(f"gradient_emission: expected one of {DIRECT_EMISSION}, got {gradient_emission!r}")
    shift = DEFAULT_SHIFT if shift is None else shift
    if shift not in SHIFTS:
        raise JaxdenoiseError(f"shift: expected one of {SHIFTS}, got {shift!r}")
    if primal not in PRIMALS or (primal == "gpt" and shift != "reconnect"):
        raise JaxdenoiseError(f"primal: expected 'base', or 'gpt' with shift='reconnect'; got {primal!r} (shift {shift!r})")
    return shift


def _noisy_frame(loaded, spp, fseed, settings, fields, samples_per_pass, shift, primal, gradient_emission, tick,
                 buffer_pass=True):
    """(buffers dict, seconds, compile seconds, buffer seconds, shift statistics) of one noisy frame.

    A frame without gradients is one buffer pass (buffer seconds None). A gradient frame is rendered
    in one pass (`data_gen.gradient.render_gradients` with ``record``: colour, features, dx, dy
    together) and its seconds are that pass's. The buffer pass of the same seed is rendered and
    timed beside it, because `jaxdenoise.bench` charges a method that reads no gradient that pass
    alone (docs/metrics.md); its colour (with ``primal="base"``) and features must equal the one
    pass's bit for bit (a tracer bug otherwise: an error naming the buffer). ``buffer_pass=False``
    (a frame whose time nobody reads) renders the one pass alone.
    """
    record_feats = [f for f in FEATURES if f in fields or f"{f}_var" in fields]
    gradient_frame = any(f in fields for f in GRADIENT_FIELDS)
    data, buffer_seconds, compile_seconds = None, None, 0.0
    if buffer_pass or not gradient_frame:
        with RenderTimer() as timer:
            data = render_buffers(loaded, spp=spp, seed=fseed, settings=settings, record=record_feats,
                                  samples_per_pass=samples_per_pass, on_pass=tick)
        if not gradient_frame:
            return data, timer.seconds, timer.compile_seconds, None, None
        buffer_seconds, compile_seconds = timer.seconds, timer.compile_seconds
    with RenderTimer() as timer:
        frame, stats = _gradients(loaded, spp, fseed, settings, samples_per_pass, shift, primal,
                                  gradient_emission, record_feats)
    for k, v in (data or {}).items():
        if k in ("color", "color_var") and primal == "gpt":
            continue  # the colour is the G-PT primal, not the base paths' mean
        if isinstance(v, np.ndarray) and not np.array_equal(v, frame.get(k)):
            raise RuntimeError(f"{k}: the one-pass gradient render differs from the buffer pass of the same seed "
                               f"(seed {fseed}, {spp} spp); a tracer bug: report it with the scene")
    return frame, timer.seconds, compile_seconds + timer.compile_seconds, buffer_seconds, stats


def _gradients(scene, spp, seed, settings, samples_per_pass, shift, primal, gradient_emission,
               record=()) -> tuple[dict, dict | None]:
    """The buffers of a gradient frame in one pass: colour (the base paths' mean, or with
    ``primal="gpt"`` the G-PT primal), the ``record``ed features, dx, dy and (with
    ``gradient_emission="separate"``) the emission they leave out; the shift statistics."""
    try:
        from . import gradient
    except ImportError as exc:
        raise RuntimeError(
            "gradient-domain buffers (dx, dy) were requested but data_gen.gradient is not available "
            f"({exc}); request methods/buffers without dx/dy") from None
    out = gradient.render_gradients(scene, spp=spp, seed=seed, max_depth=settings.max_depth,
                                     rr_depth=settings.rr_depth, samples_per_pass=samples_per_pass,
                                     shift=shift, primal=primal, direct_emission=gradient_emission,
                                     record=record)
    # dx_var / dy_var / emission_var have no channels in the EXR contract (jaxdenoise.buffers.CHANNELS).
    keys = ("dx", "dy", EMISSION_FIELD, *record, *(f"{f}_var" for f in record))
    data = {k: np.asarray(out[k], np.float32) for k in keys if k in out}
    data["color"] = np.asarray(out["primal"], np.float32)
    if "primal_var" in out:
        data["color_var"] = np.asarray(out["primal_var"], np.float32)
    stats = dict(out.get("shift_stats") or {}, n_invalid=int(out["n_invalid"]))
    return data, stats


def _attrs(base_key: dict, spp: int, instance, seconds: float) -> dict:
    a = {"integrator": INTEGRATOR_NAME, "scene": str(base_key["scene"])[-200:], "seed": int(base_key["seed"]),
         "max_depth": int(base_key["max_depth"]), "rr_depth": int(base_key["rr_depth"]),
         "pixel_filter": "box"}  # render seconds live in the manifest: files stay byte-identical across runs
    if instance is not None:
        a["instance"] = int(instance)
    return a


def dataclass_dict(obj) -> dict:
    import dataclasses

    return dataclasses.asdict(obj)
