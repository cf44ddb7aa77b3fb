"""The scene library: Mitsuba 3 XML scenes written for this project (docs/data_gen.md "Scene library").

Every scene is ``data_gen/library/<name>.xml`` with its assets under ``assets/`` (written by
``python -m data_gen.library.make_assets``). ``split.json`` is the one sidecar: it assigns every
scene to exactly one split (``train``; ``val``, small, for model selection; ``eval``, never trained on
nor used to select) and gives each scene its fly-through camera (``camera``: the look-at ``target``
of the scene's own view, ``radius`` and ``target_radius`` of `data_gen.sequences.camera_positions`,
chosen so that a path stays inside the room and looks at the content; checked by
``tests/test_library.py``) and its feature list (documentation).

Naming a scene: ``library:<name>`` wherever data_gen takes a scene (``python -m data_gen render
library:kitchen``, `data_gen.render_shot`, `data_gen.load_scene`, `data_gen.sequences.render_sequence`);
the XML's own path works too (and gets the same fly-through camera). A split is rendered with
``python -m data_gen dataset --library train ...`` (`data_gen.generate_dataset`, ``library=``).

This module imports nothing from data_gen (its errors are `LibraryError`, a `JaxdenoiseError`), so
every data_gen module may use it.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from jaxdenoise.errors import JaxdenoiseError

__all__ = ["LIBRARY_DIR", "PREFIX", "SPLITS", "SPLIT_FILE", "LibraryError", "camera", "default_size", "film_size", "index",
           "is_spec", "resolve", "scene_digest", "scene_label", "scene_names", "scene_path", "split_of"]

LIBRARY_DIR = Path(__file__).resolve().parent
SPLIT_FILE = LIBRARY_DIR / "split.json"
SPLITS: tuple[str, ...] = ("train", "val", "eval")
PREFIX = "library:"
_CAMERA_KEYS = {"target", "radius", "target_radius", "n_keys"}


class LibraryError(JaxdenoiseError):
    """A library scene or split that does not exist, or a malformed split file (names what was expected)."""


def index(path: str | os.PathLike = SPLIT_FILE) -> dict:
    """The parsed, validated split file: ``{"splits": {split: [names]}, "scenes": {name: entry}}``.

    Checked: the three splits exist and are lists of names, no scene is in two splits or twice in
    one, every scene of a split has an entry (and every entry a split), and every scene file exists.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise LibraryError(f"scene library: split file '{path}' does not exist") from None
    except json.JSONDecodeError as exc:
        raise LibraryError(f"scene library: split file '{path}' is not valid JSON: {exc}") from None
    splits, scenes = data.get("splits"), data.get("scenes")
    if not isinstance(splits, dict) or sorted(splits) != sorted(SPLITS):
        raise LibraryError(f"scene library: '{path}': 'splits' must have exactly the keys {list(SPLITS)}, "
                           f"got {sorted(splits) if isinstance(splits, dict) else type(splits).__name__}")
    if not isinstance(scenes, dict):
        raise LibraryError(f"scene library: '{path}': 'scenes' must map scene names to entries")
    seen: dict[str, str] = {}
    for split in SPLITS:
        names = splits[split]
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise LibraryError(f"scene library: '{path}': split '{split}' must be a non-empty list of scene names")
        for n in names:
            if n in seen:
                raise LibraryError(f"scene library: '{path}': scene '{n}' is listed in split '{seen[n]}' and "
                                   f"again in '{split}' (every scene belongs to exactly one split)")
            seen[n] = split
    missing = sorted(set(seen) - set(scenes))
    extra = sorted(set(scenes) - set(seen))
    if missing or extra:
        raise LibraryError(f"scene library: '{path}': scenes without an entry {missing}, entries in no split {extra}")
    for name, entry in scenes.items():
        if not re.fullmatch(r"[a-z0-9_]+", name):
            raise LibraryError(f"scene library: '{path}': scene name '{name}' must be lower-case letters, digits, _")
        xml = path.parent / f"{name}.xml"
        if not xml.is_file():
            raise LibraryError(f"scene library: '{path}': scene '{name}' has no scene file '{xml}'")
        cam = entry.get("camera") if isinstance(entry, dict) else None
        if not isinstance(cam, dict) or not {"target", "radius", "target_radius"} <= set(cam) or set(cam) - _CAMERA_KEYS:
            raise LibraryError(f"scene library: '{path}': scene '{name}' needs a 'camera' with keys target, radius, "
                               f"target_radius (optional n_keys), got {cam!r}")
    return {"splits": {s: list(splits[s]) for s in SPLITS}, "scenes": scenes}


def scene_names(split: str | None = None) -> list[str]:
    """The scenes of ``split`` in split-file order (``None``: every scene, train then val then eval)."""
    idx = index()
    if split is None:
        return [n for s in SPLITS for n in idx["splits"][s]]
    if split not in SPLITS:
        raise LibraryError(f"scene library: unknown split {split!r}; the splits are {list(SPLITS)}")
    return list(idx["splits"][split])


def split_of(name: str) -> str:
    """The split a scene belongs to."""
    for split, names in index()["splits"].items():
        if name in names:
            return split
    raise LibraryError(f"scene library: no scene named {name!r}; the scenes are {scene_names()}")


def scene_path(name: str) -> Path:
    """The XML file of library scene ``name`` (``library:`` prefix allowed)."""
    name = name[len(PREFIX):] if name.startswith(PREFIX) else name
    split_of(name)  # raises, listing the scenes, for an unknown name
    return LIBRARY_DIR / f"{name}.xml"


def is_spec(scene: Any) -> bool:
    """Whether ``scene`` is a ``library:<name>`` string."""
    return isinstance(scene, str) and scene.startswith(PREFIX)


def resolve(scene: Any) -> str | None:
    """The library name ``scene`` refers to: a ``library:<name>`` string (unknown names raise) or a path
    to one of the library's XML files; ``None`` for anything else."""
    if is_spec(scene):
        name = scene[len(PREFIX):]
        split_of(name)
        return name
    if isinstance(scene, (str, os.PathLike)):
        p = Path(scene)
        if p.suffix == ".xml" and p.is_file() and p.resolve().parent == LIBRARY_DIR:
            name = p.stem
            if name in index()["scenes"]:
                return name
    return None


def camera(name: str) -> dict:
    """The scene's fly-through camera keys (``target``, ``radius``, ``target_radius``): merged over
    `data_gen.sequences.camera_params` of the loaded scene, which supplies ``origin`` and ``up``."""
    split_of(name)
    return dict(index()["scenes"][name]["camera"])


def _referenced_files(xml: Path) -> list[Path]:
    root = ET.parse(xml).getroot()
    files = {xml.parent / el.get("value", "") for el in root.iter("string") if el.get("name") == "filename"}
    return sorted(files)


def scene_digest(name: str) -> str:
    """SHA-256 over the scene's XML and every file it references (hex): an edited scene or asset
    changes it, so renders keyed on `scene_label` are redone instead of resumed."""
    xml = scene_path(name)
    h = hashlib.sha256()
    for p in [xml] + _referenced_files(xml):
        h.update(p.relative_to(LIBRARY_DIR).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def scene_label(name: str) -> str:
    """``library:<name>@<first 12 hex of scene_digest>``: the scene's name in records and resume keys."""
    return f"{PREFIX}{name}@{scene_digest(name)[:12]}"


def default_size(name: str) -> tuple[int, int]:
    """(width, height) the scene renders at by default (its ``resx`` / ``resy`` defaults)."""
    root = ET.parse(scene_path(name)).getroot()
    d = {e.get("name"): e.get("value") for e in root.iter("default")}
    try:
        return int(d["resx"]), int(d["resy"])
    except (KeyError, TypeError, ValueError):
        raise LibraryError(f"scene library: '{scene_path(name)}' must declare integer <default name=\"resx\"> "
                           "and <default name=\"resy\">") from None


def film_size(name: str, width: int | None = None, height: int | None = None) -> tuple[int | None, int | None]:
    """The film size to render library scene ``name`` at: its own (``(None, None)``: the XML's
    defaults) when neither is given; one of them alone keeps the scene's aspect ratio."""
    if width is None and height is None:
        return None, None
    for label, v in (("width", width), ("height", height)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise LibraryError(f"scene library: {label} must be an int >= 1, got {v!r}")
    w0, h0 = default_size(name)
    if height is None:
        height = max(1, round(width * h0 / w0))
    elif width is None:
        width = max(1, round(height * w0 / h0))
    return int(width), int(height)
