"""Scenes: loading (dict, XML file, loaded scene), the built-in default scene, procedural families
randomized by seed, and the scene analysis that decides which buffers a
scene can vary (camera fly-through sequences are in `data_gen.sequences`).

Every procedural scene is built from Mitsuba's built-in shapes, BSDFs and emitters; textures are
generated with NumPy (no downloads). Families (``FAMILIES``):

- ``rooms``: a textured room lit mostly indirectly (the light faces the ceiling);
- ``objects``: object sets mixing diffuse, rough conductor, (rough) plastic and dielectric;
- ``dof``: objects at several depths seen through a thin-lens camera (depth of field);
- ``thin``: thin geometry (thin cylinders, slats) in front of a textured wall;
- ``fireflies``: a dark room with small, very bright lights and glossy surfaces;
- ``envmap``: objects on a ground plane under a procedural environment map;
- ``mixed``: one of the above, chosen by the seed (the training sets use it).
"""
from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from .mitsuba_setup import setup_mitsuba
from jaxdenoise.errors import JaxdenoiseError

FAMILIES: tuple[str, ...] = ("rooms", "objects", "dof", "thin", "fireflies", "envmap")
ALL_FAMILIES: tuple[str, ...] = FAMILIES + ("mixed",)


class SceneError(JaxdenoiseError):
    """A scene cannot be loaded or built (names the file or argument and what was expected)."""


# --------------------------------------------------------------------------------------------------
# Procedural textures
# --------------------------------------------------------------------------------------------------
def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth value noise in [0, 1]: a random grid upsampled bilinearly (wrapping)."""
    g = rng.random((cells, cells))
    t = np.arange(size) * cells / size
    i0 = np.floor(t).astype(int)
    f = t - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    a = g[i0][:, i0] * (1 - f)[None, :] + g[i0][:, i1] * f[None, :]
    b = g[i1][:, i0] * (1 - f)[None, :] + g[i1][:, i1] * f[None, :]
    return a * (1 - f)[:, None] + b * f[:, None]


def procedural_texture(rng: np.random.Generator, size: int = 64, kind: str | None = None) -> np.ndarray:
    """An RGB float32 texture (HWC, values in [0.02, 0.9]) of a random kind: checker, stripes,
    value noise, marble or tiles."""
    kinds = ("checker", "stripes", "noise", "marble", "tiles")
    kind = kind or kinds[int(rng.integers(len(kinds)))]
    c1, c2 = rng.uniform(0.05, 0.85, 3), rng.uniform(0.05, 0.85, 3)
    y, x = np.mgrid[0:size, 0:size] / size
    if kind == "checker":
        n = int(rng.integers(2, 9))
        m = ((np.floor(x * n) + np.floor(y * n)) % 2)[..., None]
    elif kind == "stripes":
        n = int(rng.integers(3, 12))
        m = (0.5 + 0.5 * np.sin(2 * np.pi * n * (x + 0.3 * y)))[..., None]
    elif kind == "noise":
        m = (0.6 * _value_noise(rng, size, 4) + 0.4 * _value_noise(rng, size, 16))[..., None]
    elif kind == "marble":
        m = (0.5 + 0.5 * np.sin(2 * np.pi * (3 * x + 4 * _value_noise(rng, size, 6))))[..., None]
    elif kind == "tiles":
        n = int(rng.integers(3, 8))
        gx, gy = (x * n) % 1, (y * n) % 1
        m = ((gx > 0.08) & (gy > 0.08)).astype(float)[..., None] * (0.7 + 0.3 * _value_noise(rng, size, n))[..., None]
    else:
        raise SceneError(f"procedural_texture: kind must be one of {kinds}, got {kind!r}")
    img = c1 * m + c2 * (1 - m)
    return np.clip(img, 0.02, 0.9).astype(np.float32)


def _bitmap(rng, size=64, kind=None) -> dict:
    import mitsuba as mi

    return {"type": "bitmap", "bitmap": mi.Bitmap(procedural_texture(rng, size, kind)), "filter_type": "bilinear"}


def procedural_envmap(rng: np.random.Generator, width: int = 128) -> np.ndarray:
    """A latitude-longitude sky: gradient sky, noisy clouds and a small bright sun (float32 HWC)."""
    h = width // 2
    v, u = np.mgrid[0:h, 0:width] + 0.5
    theta = v / h * np.pi  # 0 = up
    sky_top, sky_hor = rng.uniform(0.1, 0.6, 3), rng.uniform(0.5, 1.2, 3)
    t = np.clip(np.cos(theta), 0, 1)[..., None]
    img = sky_hor * (1 - t) + sky_top * t
    clouds = _value_noise(rng, width, 8)[:h]
    img = img * (0.7 + 0.6 * clouds[..., None])
    img[theta > np.pi / 2] = rng.uniform(0.05, 0.2, 3)  # ground
    su, sv = rng.uniform(0, width), rng.uniform(0.1, 0.4) * h
    d2 = (u - su) ** 2 + (v - sv) ** 2
    img += (d2 < (width / 128) ** 2 * 4)[..., None] * rng.uniform(50, 300)
    return img.astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------------------
def _T():
    import mitsuba as mi

    return mi.ScalarTransform4f()


def _camera(width, height, origin, target, *, fov=40.0, lens=None, spp=4):
    sensor = {
        "type": "perspective", "fov": float(fov),
        "to_world": _T().look_at(origin=list(map(float, origin)), target=list(map(float, target)), up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }
    if lens is not None:
        sensor["type"] = "thinlens"
        sensor["aperture_radius"] = float(lens[0])
        sensor["focus_distance"] = float(lens[1])
    return sensor


def _random_bsdf(rng, kinds=("diffuse", "tex", "conductor", "plastic", "roughplastic", "dielectric")) -> dict:
    kind = kinds[int(rng.integers(len(kinds)))]
    col = {"type": "rgb", "value": rng.uniform(0.05, 0.85, 3).tolist()}
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": col}
    if kind == "tex":
        return {"type": "diffuse", "reflectance": _bitmap(rng)}
    if kind == "conductor":
        mat = ["Au", "Cu", "Al", "Ag", "Cr"][int(rng.integers(5))]
        return {"type": "roughconductor", "material": mat, "distribution": "ggx",
                "alpha": float(rng.uniform(0.03, 0.4))}
    if kind == "plastic":
        return {"type": "plastic", "diffuse_reflectance": col, "int_ior": 1.5}
    if kind == "roughplastic":
        return {"type": "roughplastic", "diffuse_reflectance": col, "distribution": "ggx",
                "alpha": float(rng.uniform(0.05, 0.3))}
    if kind == "dielectric":
        return {"type": "dielectric", "int_ior": float(rng.uniform(1.3, 1.6))}
    raise SceneError(f"unknown BSDF kind {kind!r}")


def _random_object(rng, center, scale, bsdf) -> dict:
    kind = ["sphere", "cube", "cylinder"][int(rng.integers(3))]
    c = [float(v) for v in center]
    if kind == "sphere":
        return {"type": "sphere", "center": c, "radius": float(scale), "bsdf": bsdf}
    ang = float(rng.uniform(0, 360))
    if kind == "cube":
        return {"type": "cube", "bsdf": bsdf,
                "to_world": _T().translate(c).rotate([0, 1, 0], ang).scale(float(scale) * 0.8)}
    return {"type": "cylinder", "radius": float(scale) * 0.6, "bsdf": bsdf,
            "p0": [c[0], c[1] - scale, c[2]], "p1": [c[0], c[1] + scale, c[2]]}


def _room(rng, *, textured=True, size=1.0) -> dict:
    """Floor, ceiling, back, left and right walls of a box [-size, size]^3 (open towards +z)."""
    def mat():
        if textured and rng.random() < 0.7:
            return {"type": "diffuse", "reflectance": _bitmap(rng)}
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rng.uniform(0.1, 0.8, 3).tolist()}}

    s = float(size)
    T = _T
    return {
        "floor": {"type": "rectangle", "bsdf": mat(), "to_world": T().translate([0, -s, 0]).rotate([1, 0, 0], -90).scale(s)},
        "ceiling": {"type": "rectangle", "bsdf": mat(), "to_world": T().translate([0, s, 0]).rotate([1, 0, 0], 90).scale(s)},
        "back": {"type": "rectangle", "bsdf": mat(), "to_world": T().translate([0, 0, -s]).scale(s)},
        "left": {"type": "rectangle", "bsdf": mat(), "to_world": T().translate([-s, 0, 0]).rotate([0, 1, 0], 90).scale(s)},
        "right": {"type": "rectangle", "bsdf": mat(), "to_world": T().translate([s, 0, 0]).rotate([0, 1, 0], -90).scale(s)},
    }


def _area_light(center, size, radiance, *, facing_up=False) -> dict:
    rot = -90 if facing_up else 90
    return {"type": "rectangle",
            "to_world": _T().translate([float(v) for v in center]).rotate([1, 0, 0], rot).scale(float(size)),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [float(v) for v in radiance]}}}


def _objects_on_floor(rng, n, *, floor_y=-1.0, spread=0.7, kinds=None) -> dict:
    out = {}
    for i in range(n):
        scale = float(rng.uniform(0.15, 0.35))
        center = [rng.uniform(-spread, spread), floor_y + scale, rng.uniform(-spread, spread * 0.8)]
        bsdf = _random_bsdf(rng) if kinds is None else _random_bsdf(rng, kinds)
        out[f"obj{i}"] = _random_object(rng, center, scale, bsdf)
    return out


# --------------------------------------------------------------------------------------------------
# Families
# --------------------------------------------------------------------------------------------------
def _room_camera(rng, width, height, spp, lens=None):
    origin = [rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.3), rng.uniform(3.2, 3.9)]
    target = [rng.uniform(-0.2, 0.2), rng.uniform(-0.4, 0.0), 0.0]
    return _camera(width, height, origin, target, fov=float(rng.uniform(36, 44)), lens=lens, spp=spp)


def build_scene(family: str, seed: int, *, width: int = 128, height: int = 128, spp: int = 4) -> dict:
    """A procedural scene dict of ``family`` (see module docstring) randomized by ``seed``."""
    setup_mitsuba()
    if family not in ALL_FAMILIES:
        raise SceneError(f"family must be one of {list(ALL_FAMILIES)}, got {family!r}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SceneError(f"seed must be an int >= 0, got {seed!r}")
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or v < 1:
            raise SceneError(f"{name} must be an int >= 1, got {v!r}")
    rng = np.random.default_rng([int(seed), ALL_FAMILIES.index(family)])
    if family == "mixed":
        family = FAMILIES[int(seed) % len(FAMILIES)]
        rng = np.random.default_rng([int(seed), 99])
    scene: dict[str, Any] = {"type": "scene", "integrator": {"type": "path", "max_depth": 8}}
    if family == "rooms":
        scene.update(_room(rng, textured=True))
        scene["light"] = _area_light([rng.uniform(-0.4, 0.4), 0.9, rng.uniform(-0.5, 0.2)], rng.uniform(0.15, 0.3),
                                     rng.uniform(30, 80) * np.array([1.0, rng.uniform(0.8, 1), rng.uniform(0.6, 1)]),
                                     facing_up=True)
        scene.update(_objects_on_floor(rng, int(rng.integers(1, 4)), kinds=("diffuse", "tex", "roughplastic")))
        scene["sensor"] = _room_camera(rng, width, height, spp)
    elif family == "objects":
        scene.update(_room(rng, textured=rng.random() < 0.5))
        scene["light"] = _area_light([0, 0.99, 0], rng.uniform(0.2, 0.4), [rng.uniform(8, 15)] * 3)
        scene.update(_objects_on_floor(rng, int(rng.integers(3, 7))))
        scene["sensor"] = _room_camera(rng, width, height, spp)
    elif family == "dof":
        scene.update(_room(rng, textured=True))
        scene["light"] = _area_light([0, 0.99, 0], 0.3, [12, 12, 12])
        scene.update(_objects_on_floor(rng, int(rng.integers(3, 6)), spread=0.8))
        cam_z = float(rng.uniform(3.2, 3.8))
        lens = (float(rng.uniform(0.05, 0.2)), float(cam_z - rng.uniform(-0.7, 0.7)))
        scene["sensor"] = _camera(width, height, [0, 0, cam_z], [0, -0.3, 0], fov=40, lens=lens, spp=spp)
    elif family == "thin":
        scene.update(_room(rng, textured=True))
        scene["light"] = _area_light([0, 0.99, 0], 0.3, [12, 12, 12])
        n = int(rng.integers(6, 16))
        mat = _random_bsdf(rng, ("diffuse", "conductor"))
        for i in range(n):
            x = -0.8 + 1.6 * i / max(n - 1, 1)
            r = float(rng.uniform(0.004, 0.015))
            scene[f"wire{i}"] = {"type": "cylinder", "radius": r, "p0": [x, -1.0, float(rng.uniform(-0.5, 0.5))],
                                 "p1": [x + float(rng.uniform(-0.3, 0.3)), 1.0, float(rng.uniform(-0.5, 0.5))],
                                 "bsdf": mat}
        for j in range(int(rng.integers(3, 8))):
            y = float(rng.uniform(-0.8, 0.8))
            scene[f"slat{j}"] = {"type": "rectangle", "bsdf": _random_bsdf(rng, ("diffuse", "tex")),
                                 "to_world": _T().translate([0, y, 0.3]).rotate([1, 0, 0], float(rng.uniform(-80, -20)))
                                 .scale([0.9, 0.02, 1.0])}
        scene["sensor"] = _room_camera(rng, width, height, spp)
    elif family == "fireflies":
        scene.update(_room(rng, textured=True))
        for k in range(int(rng.integers(1, 4))):
            p = [rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.9), rng.uniform(-0.8, 0.5)]
            scene[f"spark{k}"] = {"type": "sphere", "center": [float(v) for v in p], "radius": float(rng.uniform(0.01, 0.03)),
                                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value":
                                              (rng.uniform(150, 1000) * rng.uniform(0.6, 1, 3)).tolist()}}}
        scene.update(_objects_on_floor(rng, int(rng.integers(2, 5)), kinds=("conductor", "roughplastic", "dielectric", "diffuse")))
        scene["sensor"] = _room_camera(rng, width, height, spp)
    elif family == "envmap":
        scene["ground"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": _bitmap(rng)},
                           "to_world": _T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(6)}
        scene.update(_objects_on_floor(rng, int(rng.integers(3, 7)), spread=1.0))
        import mitsuba as mi
        scene["env"] = {"type": "envmap", "bitmap": mi.Bitmap(procedural_envmap(rng)), "scale": float(rng.uniform(0.5, 1.5))}
        origin = [rng.uniform(-1, 1), rng.uniform(0.0, 0.8), rng.uniform(3.5, 4.5)]
        scene["sensor"] = _camera(width, height, origin, [0, -0.6, 0], fov=float(rng.uniform(35, 45)), spp=spp)
    scene["__family__"] = family
    return scene


def default_scene(*, width: int = 128, height: int = 128) -> dict:
    """A small built-in scene: a Cornell-box-like room with a textured back wall, a glossy
    (rough conductor) sphere and a diffuse box, lit by a ceiling area light. Good for a 128x128 demo."""
    setup_mitsuba()
    rng = np.random.default_rng(7)
    T = _T
    red = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.57, 0.04, 0.04]}}
    green = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1, 0.45, 0.08]}}
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.7, 0.7]}}
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": _camera(width, height, [0, 0, 3.9], [0, 0, 0], fov=39.3),
        "floor": {"type": "rectangle", "bsdf": white, "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)},
        "ceiling": {"type": "rectangle", "bsdf": white, "to_world": T().translate([0, 1, 0]).rotate([1, 0, 0], 90)},
        "back": {"type": "rectangle", "to_world": T().translate([0, 0, -1]),
                 "bsdf": {"type": "diffuse", "reflectance": _bitmap(rng, 128, "checker")}},
        "left": {"type": "rectangle", "bsdf": red, "to_world": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90)},
        "right": {"type": "rectangle", "bsdf": green, "to_world": T().translate([1, 0, 0]).rotate([0, 1, 0], -90)},
        "light": _area_light([0, 0.99, 0], 0.25, [17, 12, 4]),
        "glossy": {"type": "sphere", "center": [-0.4, -0.65, -0.2], "radius": 0.35,
                   "bsdf": {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.15}},
        "box": {"type": "cube", "bsdf": white,
                "to_world": T().translate([0.45, -0.7, 0.3]).rotate([0, 1, 0], 25).scale(0.3)},
    }


# --------------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------------
_FILE_PLUGINS_ATTR = "filename"


def check_xml(path: str | os.PathLike) -> None:
    """Fail early with a clear message: the file exists, parses as XML, and every ``filename``
    it references (textures, meshes, environment maps) exists relative to the scene folder."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file '{path}' does not exist")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"scene file '{path}' is not well-formed XML: {exc}") from None
    if root.tag != "scene":
        raise SceneError(f"scene file '{path}': root element is <{root.tag}>, expected <scene>")
    defaults = {d.get("name"): d.get("value") for d in root.iter("default")}
    for el in root.iter("string"):
        if el.get("name") != _FILE_PLUGINS_ATTR:
            continue
        value = el.get("value", "")
        value = re.sub(r"\$(\w+)", lambda m: defaults.get(m.group(1)) or m.group(0), value)
        if "$" in value:
            continue  # a parameter given at load time; Mitsuba reports it
        ref = Path(value)
        if not ref.is_absolute():
            ref = path.parent / ref
        if not ref.exists():
            raise SceneError(f"scene file '{path}' references missing file '{value}' "
                             f"(looked for '{ref}'); put it there or fix the filename")


def _declared_defaults(path: Path) -> set[str]:
    """The names of the ``<default name=...>`` parameters an XML scene declares at its top level."""
    return {e.get("name") for e in ET.parse(path).getroot().findall("default")}


def _load_resized(mi, path: Path, width: int | None, height: int | None):
    """``path`` loaded with its sensors' film width/height replaced (`load_scene`)."""
    root = ET.parse(path).getroot()
    films = [f for sensor in root.iter("sensor") for f in sensor.findall("film")]
    if not films:
        raise SceneError(f"scene file '{path}': --width/--height need a <film type=\"hdrfilm\"> inside its "
                         f"<sensor> (it has none; Mitsuba's default film is 768x576), or declare "
                         f"<default name=\"resx\" value=\"256\"/> and <default name=\"resy\" value=\"256\"/> and "
                         f"use $resx / $resy as the film's width and height")
    for film in films:
        for name, value in (("width", width), ("height", height)):
            if value is None:
                continue
            entry = next((e for e in film if e.get("name") == name), None)
            if entry is None:
                entry = ET.SubElement(film, "integer", {"name": name})
            entry.tag = "integer"
            entry.set("value", str(int(value)))
    resolver = mi.file_resolver()
    saved = mi.FileResolver(resolver)
    resolver.prepend(str(path.resolve().parent))
    try:
        return mi.load_string(ET.tostring(root, encoding="unicode"))
    finally:
        mi.Thread.thread().set_file_resolver(saved)


def load_scene(scene: Any, *, width: int | None = None, height: int | None = None):
    """A loaded ``mi.Scene`` from a scene dict, an XML path, ``"library:<name>"`` (a scene of the
    scene library, `data_gen.library`) or a loaded scene.

    ``width`` / ``height`` override the film size of dicts and XML files: an XML that declares both
    ``<default name="resx">`` and ``"resy"`` gets them as those parameters (the convention of
    Mitsuba's own scenes and of the scene library); any other XML has its sensor's ``<film>`` width
    and height entries replaced in a copy of its text, loaded with the file's folder first on
    Mitsuba's file resolver (so its relative paths resolve as before). An XML without a ``<film>``
    in a ``<sensor>`` cannot be resized: the error says what to add.
    """
    setup_mitsuba()
    import mitsuba as mi

    if isinstance(scene, mi.Scene):
        return scene
    if isinstance(scene, str) and scene.startswith("library:"):  # a scene of data_gen/library
        from .library import LibraryError, scene_path

        try:
            scene = scene_path(scene)
        except LibraryError as exc:
            raise SceneError(str(exc)) from None
    if isinstance(scene, (str, os.PathLike)):
        check_xml(scene)
        declared = _declared_defaults(Path(scene))
        sized = width is not None or height is not None
        try:
            if not sized or {"resx", "resy"} <= declared:
                kwargs = {k: int(v) for k, v in (("resx", width), ("resy", height)) if v is not None}
                return mi.load_file(os.fspath(scene), **kwargs)
            return _load_resized(mi, Path(scene), width, height)
        except SceneError:
            raise
        except Exception as exc:  # noqa: BLE001 - Mitsuba raises RuntimeError with a long message
            msg = str(exc).strip().splitlines()
            raise SceneError(f"Mitsuba could not load scene file '{scene}': {msg[-1] if msg else exc}") from None
    if isinstance(scene, dict):
        d = {k: v for k, v in scene.items() if not k.startswith("__")}
        if width is not None or height is not None:
            if "sensor" not in d:
                raise SceneError("load_scene: width/height given but the scene dict has no 'sensor'")
            sensor = dict(d["sensor"])
            film = dict(sensor.get("film", {"type": "hdrfilm"}))
            if width is not None:
                film["width"] = int(width)
            if height is not None:
                film["height"] = int(height)
            sensor["film"] = film
            d["sensor"] = sensor
        try:
            return mi.load_dict(d)
        except Exception as exc:  # noqa: BLE001
            msg = str(exc).strip().splitlines()
            raise SceneError(f"Mitsuba could not build the scene dict: {msg[-1] if msg else exc}") from None
    raise SceneError(f"scene must be a scene dict, an XML path or a mitsuba.Scene, got {type(scene).__name__}")


def scene_from_label(label: str, *, width: int, height: int):
    """The loaded scene a render's record names (``key["scene"]`` of a shot.json): ``family:seed`` (a
    procedural scene, `build_scene`) or ``library:<name>@<digest>`` (a library scene; an edited scene,
    whose digest no longer matches, is refused: it is not the scene that was rendered), at the
    render's ``width`` x ``height``."""
    from .library import PREFIX, scene_label

    if label.startswith(PREFIX):
        name = label[len(PREFIX):].split("@", 1)[0]
        if scene_label(name) != label:
            raise SceneError(f"scene {label!r}: the library's '{name}' has changed since that render "
                             f"(now {scene_label(name)!r})")
        return load_scene(f"{PREFIX}{name}", width=width, height=height)
    family, _, seed = label.partition(":")
    if family not in ALL_FAMILIES or not seed.isdigit():
        raise SceneError(f"scene {label!r}: expected 'family:seed' with a family of {ALL_FAMILIES} or "
                         f"'{PREFIX}<name>@<digest>'")
    return load_scene(build_scene(family, int(seed), width=width, height=height))


def describe(scene) -> dict:
    """What a loaded scene contains: camera type, emitters, textures, BSDF kinds, roughness values."""
    import mitsuba as mi

    from .integrator import bsdf_roughness, scene_bsdfs

    sensor = scene.sensors()[0]
    emitters = scene.emitters()
    bsdfs = scene_bsdfs(scene)
    params = mi.traverse(scene)
    textured = any(k.endswith(".data") and ".bsdf" in k or (".bsdf." in k and k.endswith("data")) for k in params.keys())
    return {
        "camera": sensor.class_name() if hasattr(sensor, "class_name") else str(sensor).split("[")[0].strip(),
        "lens": bool(sensor.needs_aperture_sample()),
        "emitters": len(emitters),
        "infinite_emitters": sum(mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) for e in emitters),
        "textured": bool(textured),
        "bsdfs": len(bsdfs),
        "roughness_values": sorted({round(bsdf_roughness(b), 6) for b in bsdfs}),
        "delta_bsdfs": sum(1 for b in bsdfs if not mi.has_flag(b.flags(), mi.BSDFFlags.Smooth)),
    }
