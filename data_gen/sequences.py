"""Camera fly-through sequences for the recurrent denoiser (Chaitanya et al. 2017, Sec. 4.3: "a
smooth camera fly-through animation ... For every frame, we generate 10 different noisy images at 1
sample per pixel, the auxiliary features, and the target image").

`camera_path` turns a base camera (look-from, look-at, up) into ``n_frames`` smooth camera poses:
the look-from point follows a uniform Catmull-Rom spline through random key points scattered around
the base look-from (the first key IS the base camera, so frame 0 is the scene's own view), and the
look-at point follows a second spline through keys scattered around the base look-at. A
Catmull-Rom spline passes through its keys and is C1 (continuous velocity), so consecutive frames
move by O(1/n_frames) and second differences are O(1/n_frames^2) (bounded acceleration). The paper
does not say how its fly-throughs were made; keys in a ball around the scene's own camera keep the
view on the scene's content for any scene (a path through walls is the user's to avoid, with
``radius``).

`render_sequence` renders one shot folder per frame (``frame_0000/``, ...: the bench layout of
``docs/guide.md``) through `data_gen.render_shot`, with several independent noisy renders per
frame (``instances``, default 10 as in the paper) sharing the frame's one reference. Unlike the
paper, whose primary rays are rasterized so that the noisy instances share their auxiliary
features, each instance here path-traces its own (noisy, at 1 spp) features.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from .integrator import derive_seed
from .mitsuba_setup import setup_mitsuba
from jaxdenoise.errors import JaxdenoiseError

__all__ = ["camera_params", "camera_path", "camera_positions", "render_sequence", "set_camera"]


def _vec3(value: Any, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise JaxdenoiseError(f"scene_params[{name!r}]: expected 3 finite numbers, got {value!r}")
    return a


def camera_params(scene) -> dict[str, Any]:
    """The base camera of a loaded scene's first sensor, in the form `camera_path` takes.

    ``origin`` is the sensor position, ``up`` its up axis, and ``target`` lies on its viewing axis
    at the distance of the scene's bounding-box centre along that axis (at least 1% of the box
    diagonal, so a camera outside the box still looks at something).
    """
    setup_mitsuba()
    import mitsuba as mi

    if not isinstance(scene, mi.Scene):
        raise TypeError(f"scene: expected a loaded mitsuba.Scene, got {type(scene).__name__}")
    if not scene.sensors():
        raise JaxdenoiseError("scene: has no sensor")
    m = np.asarray(scene.sensors()[0].world_transform().matrix, dtype=np.float64).reshape(4, 4)
    origin = m[:3, 3]
    forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
    up = m[:3, 1] / np.linalg.norm(m[:3, 1])
    bbox = scene.bbox()
    lo, hi = np.asarray(bbox.min, np.float64), np.asarray(bbox.max, np.float64)
    diag = float(np.linalg.norm(hi - lo)) if np.all(np.isfinite(hi - lo)) else 1.0
    centre = 0.5 * (lo + hi) if np.all(np.isfinite(hi - lo)) else origin + forward
    dist = max(float(np.dot(centre - origin, forward)), 0.01 * max(diag, 1e-6))
    return {"origin": origin.tolist(), "target": (origin + dist * forward).tolist(), "up": up.tolist(),
            "radius": 0.1 * dist, "target_radius": 0.05 * dist}


def _catmull_rom(keys: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Uniform Catmull-Rom spline through ``keys`` (K x 3) at parameters ``t`` in [0, K-1].

    The end tangents use reflected phantom keys (P_-1 = 2 P_0 - P_1, P_K = 2 P_{K-1} - P_{K-2}).
    """
    k = keys.shape[0]
    if k == 1:
        return np.repeat(keys, t.shape[0], axis=0)
    ext = np.concatenate([2 * keys[:1] - keys[1:2], keys, 2 * keys[-1:] - keys[-2:-1]], axis=0)
    seg = np.clip(np.floor(t).astype(int), 0, k - 2)
    u = (t - seg)[:, None]
    p0, p1, p2, p3 = ext[seg], ext[seg + 1], ext[seg + 2], ext[seg + 3]
    return 0.5 * (2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u ** 2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)


def _keys(rng: np.random.Generator, centre: np.ndarray, radius: float, n: int) -> np.ndarray:
    """``n`` key points uniform in the ball of ``radius`` around ``centre``; the first is ``centre``."""
    d = rng.normal(size=(n, 3))
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)  # guard: a zero normal draw
    r = radius * rng.uniform(size=(n, 1)) ** (1.0 / 3.0)
    pts = centre + d * r
    pts[0] = centre
    return pts


def camera_positions(scene_params: Mapping[str, Any], n_frames: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(origins, targets, up)``: float64 ``(n_frames, 3)`` look-from and look-at points and the up axis.

    ``scene_params`` keys: ``origin``, ``target`` (required), ``up`` (default (0, 1, 0)),
    ``radius`` (how far look-from keys stray from ``origin``; default 10% of the camera-target
    distance), ``target_radius`` (default 5%), ``n_keys`` (spline keys; default one per 16 frames,
    at least 2).
    """
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise JaxdenoiseError(f"n_frames: expected a positive integer, got {n_frames!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise JaxdenoiseError(f"seed: expected a non-negative integer, got {seed!r}")
    if not isinstance(scene_params, Mapping):
        raise TypeError(f"scene_params: expected a mapping with 'origin' and 'target' (see camera_params), "
                        f"got {type(scene_params).__name__}")
    for key in ("origin", "target"):
        if key not in scene_params:
            raise JaxdenoiseError(f"scene_params: missing {key!r} (keys: origin, target, up, radius, target_radius, n_keys)")
    origin = _vec3(scene_params["origin"], "origin")
    target = _vec3(scene_params["target"], "target")
    up = _vec3(scene_params.get("up", (0.0, 1.0, 0.0)), "up")
    dist = float(np.linalg.norm(target - origin))
    if not dist > 0:
        raise JaxdenoiseError("scene_params: 'origin' and 'target' coincide (no viewing direction)")
    if np.linalg.norm(up) == 0:
        raise JaxdenoiseError("scene_params['up']: is the zero vector")
    up = up / np.linalg.norm(up)
    radius = float(scene_params.get("radius", 0.1 * dist))
    t_radius = float(scene_params.get("target_radius", 0.05 * dist))
    if not (radius >= 0 and math.isfinite(radius)):
        raise JaxdenoiseError(f"scene_params['radius']: expected a finite number >= 0, got {radius!r}")
    if not (t_radius >= 0 and math.isfinite(t_radius)):
        raise JaxdenoiseError(f"scene_params['target_radius']: expected a finite number >= 0, got {t_radius!r}")
    n_keys = int(scene_params.get("n_keys", max(2, math.ceil(n_frames / 16) + 1)))
    if n_keys < 2:
        raise JaxdenoiseError(f"scene_params['n_keys']: expected an integer >= 2, got {n_keys!r}")

    rng = np.random.default_rng([int(seed), 0x5E0])
    o_keys = _keys(rng, origin, radius, n_keys)
    t_keys = _keys(rng, target, t_radius, n_keys)
    t = np.linspace(0.0, n_keys - 1.0, n_frames) if n_frames > 1 else np.zeros(1)
    origins = _catmull_rom(o_keys, t)
    targets = _catmull_rom(t_keys, t)
    fwd = targets - origins
    fnorm = np.linalg.norm(fwd, axis=1)
    # look_at is undefined when the eye reaches the target or looks along `up`: say so instead of
    # returning a NaN/degenerate frame.
    bad = (fnorm < 1e-9 * dist) | (np.linalg.norm(np.cross(fwd, up), axis=1) < 1e-6 * np.maximum(fnorm, 1e-300))
    if bad.any():
        raise JaxdenoiseError(
            f"scene_params: frame {int(np.argmax(bad))} would look along 'up' or sit on its target; "
            "lower 'radius'/'target_radius' or change 'up'"
        )
    return origins, targets, up


def camera_path(scene_params: Mapping[str, Any], n_frames: int, seed: int) -> list:
    """``n_frames`` smooth camera-to-world transforms (``mi.ScalarTransform4f``, ``look_at``).

    ``scene_params`` is the mapping `camera_positions` documents (`camera_params(scene)` builds it
    from a loaded scene). Frame 0 is the base camera; the same seed gives the same path.
    """
    origins, targets, up = camera_positions(scene_params, n_frames, seed)
    setup_mitsuba()
    import mitsuba as mi

    return [mi.ScalarTransform4f().look_at(origin=o.tolist(), target=t.tolist(), up=up.tolist())
            for o, t in zip(origins, targets)]


def set_camera(scene, transform) -> None:
    """Move the first sensor of a loaded scene to ``transform`` (camera-to-world: a
    ``mi.ScalarTransform4f``, or a 4x4 matrix such as a frame's ``camera["to_world"]`` in
    sequence.json); a Mitsuba parameter update, no reload."""
    import mitsuba as mi

    if not isinstance(transform, mi.ScalarTransform4f):
        transform = mi.ScalarTransform4f(np.asarray(transform, dtype=np.float64).reshape(4, 4))
    params = mi.traverse(scene.sensors()[0])
    if "to_world" not in params:
        raise JaxdenoiseError("scene: its sensor exposes no 'to_world' parameter, so it cannot be moved")
    params["to_world"] = transform
    params.update()


def render_sequence(scene: Any, out_dir: str | os.PathLike, *, n_frames: int, instances: int = 10,
                    spp: int | Iterable[int] = 1, ref_spp: int = 1024, seed: int = 0,
                    buffers: Iterable[str] | None = None, camera: Mapping[str, Any] | None = None,
                    width: int | None = None, height: int | None = None, **shot_kwargs) -> dict:
    """Render a camera fly-through: ``out_dir/frame_0000/``, ... one shot folder per frame.

    Each frame folder holds ``reference.exr`` (``ref_spp``) and ``instances`` independent noisy
    renders per ``spp`` (``spp0001_00.exr``, ``spp0001_01.exr``, ...): the bench layout, written by
    `data_gen.render_shot` (resumable: finished frames are skipped on a re-run). The camera follows
    `camera_path` from ``camera`` (default: `camera_params` of the scene, i.e. a path starting at
    the scene's own view; for a scene of the scene library, named ``library:<name>`` or by its XML
    path, the keys of its entry in ``data_gen/library/split.json`` replace the defaults, so the path
    stays inside its room). ``scene``: scene dict, XML path, ``library:<name>`` or loaded
    ``mi.Scene`` (its sensor is moved during the call and put back afterwards). ``width`` /
    ``height`` set the film size of a dict or XML scene (`load_scene`). ``buffers`` (field names)
    chooses what the noisy renders hold (None = every buffer the scene can vary); other keyword
    arguments go to `render_shot` (``max_depth``, ``methods``, ``progress``, ``label``, ...; a
    library scene named ``library:<name>`` is labelled ``library:<name>@<digest>``).

    The frame seed mixes ``seed``, the frame index and the frame's camera matrix, so a changed
    camera path re-renders a frame instead of resuming a stale one. Writes ``out_dir/sequence.json``
    (the cameras and the shots' records) and returns it.
    """
    from jaxdenoise.fsutil import write_json

    from . import library
    from .scenes import load_scene
    from .shot import render_shot

    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise JaxdenoiseError(f"n_frames: expected a positive integer, got {n_frames!r}")
    if isinstance(instances, bool) or not isinstance(instances, (int, np.integer)) or instances < 1:
        raise JaxdenoiseError(f"instances: expected a positive integer, got {instances!r}")
    if (width is not None or height is not None) and not isinstance(scene, (dict, str, os.PathLike)):
        raise JaxdenoiseError("width/height: a loaded mitsuba.Scene keeps its film size; pass the scene dict "
                              "or XML path (or set the size in the scene)")
    lib_name = library.resolve(scene)  # a scene of the scene library: its own fly-through camera
    if library.is_spec(scene):
        shot_kwargs.setdefault("label", library.scene_label(lib_name))
    loaded = load_scene(scene, width=width, height=height)
    if camera is not None:
        params = dict(camera)
    else:
        params = camera_params(loaded)
        if lib_name is not None:
            params.update(library.camera(lib_name))
    origins, targets, up = camera_positions(params, int(n_frames), int(seed))
    frames = camera_path(params, int(n_frames), int(seed))
    import mitsuba as mi

    original = mi.ScalarTransform4f(np.asarray(loaded.sensors()[0].world_transform().matrix,
                                               dtype=np.float64).reshape(4, 4))
    out_dir = Path(out_dir)
    records = []
    try:
        for k, transform in enumerate(frames):
            set_camera(loaded, transform)
            matrix = np.asarray(transform.matrix, dtype=np.float64).reshape(4, 4)
            fseed = derive_seed(seed, "frame", k, np.round(matrix, 6).tolist())
            rec = render_shot(loaded, out_dir / f"frame_{k:04d}", spp=spp, ref_spp=ref_spp,
                              instances=int(instances), buffers=buffers, seed=fseed, **shot_kwargs)
            rec["camera"] = {"origin": origins[k].tolist(), "target": targets[k].tolist(), "up": up.tolist(),
                             "to_world": matrix.tolist()}
            records.append(rec)
    finally:
        set_camera(loaded, original)
    seq = {"n_frames": int(n_frames), "seed": int(seed), "instances": int(instances), "ref_spp": int(ref_spp),
           "camera_params": {k: (np.asarray(v).tolist() if not isinstance(v, (int, float)) else v)
                             for k, v in params.items()},
           "frames": records}
    write_json(out_dir / "sequence.json", seq)
    return seq
