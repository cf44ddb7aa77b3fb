"""Data folders (docs/architecture.md "Error against run time": data folders): shots, their renders, sequences.

A folder is walked recursively (linked folders followed); every folder holding a ``reference.exr``
is one **shot**, and every other EXR in it is a noisy **render** of that shot. A render's sample
count is its integer ``spp`` header attribute, never a guess from its file name. Its render time
is its ``render_seconds`` header attribute or, for data_gen output (whose EXRs keep no timings so
they stay byte-identical across runs), the ``seconds`` of its entry in the shot's ``shot.json``
(data_gen excludes Dr.Jit's one-off kernel compilation from it); without either it is unknown. A
gradient frame also carries the time of a buffer-only render of it (``buffer_seconds``, same
sources; data_gen renders gradient frames in one pass and times the buffer pass beside it; older
two-pass folders give ``seconds - gradient_seconds``), which, with whether the colour came from
the gradient render (the ``primal`` header attribute), lets `bench` charge each method only what
made what it read.

A **sequence** is a folder whose shots are named ``frame_0000/``, ``frame_0001/``, ... (in frame
order); its renders are matched across frames by file name (``spp0004_00.exr`` of every frame is
one noisy video).

This module is the one place that knows the layout: `bench`, the trainer's validation, and the
methods' ``make_dataset`` all read data folders through it.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from .errors import JaxdenoiseError

__all__ = ["REFERENCE", "SHOT_RECORD", "Render", "Shot", "Sequence", "discover", "sequences", "renders_by_spp"]

REFERENCE = "reference.exr"
SHOT_RECORD = "shot.json"  # data_gen's per-shot manifest (render timings)
_FRAME = re.compile(r"^frame_(\d+)$")


@dataclasses.dataclass(frozen=True)
class Render:
    path: Path
    spp: int | None
    render_seconds: float | None  # the whole frame, as written (a gradient frame: colour, features, dx, dy)
    buffer_seconds: float | None = None  # a gradient frame: a buffer-only render of it (no dx, dy), when known
    primal: str | None = None  # "gpt": the colour came from the gradient pass (data_gen --primal gpt)
    sampling: str | None = None  # adaptive frames: the map's spec (header 'adaptive'); None: uniform


@dataclasses.dataclass(frozen=True)
class Shot:
    folder: Path
    reference: Path
    renders: tuple[Render, ...]

    @property
    def name(self) -> str:
        return self.folder.name

    @property
    def frame(self) -> int | None:
        """The frame index when the shot is a ``frame_XXXX/`` folder of a sequence, else None."""
        m = _FRAME.match(self.folder.name)
        return int(m.group(1)) if m else None


@dataclasses.dataclass(frozen=True)
class Sequence:
    """The ``frame_XXXX/`` shots of one folder, in frame order."""

    folder: Path
    shots: tuple[Shot, ...]

    @property
    def name(self) -> str:
        return self.folder.name

    def render_names(self) -> list[str]:
        """File names of the renders every frame has (one noisy video each), sorted."""
        common = set.intersection(*({r.path.name for r in s.renders} for s in self.shots))
        return sorted(common)


def _timings(manifest: Path) -> dict[str, dict]:
    """Each file's entry of a shot record (``seconds``, ``buffer_seconds``, ...)."""
    if not manifest.is_file():
        return {}
    try:
        files = json.loads(manifest.read_text()).get("files", {})
        return {k: v for k, v in files.items() if isinstance(v, dict)}
    except (json.JSONDecodeError, AttributeError) as e:
        raise JaxdenoiseError(f"{manifest}: not a valid shot record ({e})") from None


def _buffer_seconds(header: dict, entry: dict, frame_seconds) -> float | None:
    """A gradient frame's buffer-only render time (module docstring): ``buffer_seconds``, or from an
    older two-pass record the frame's time less its gradient pass (``gradient_seconds``)."""
    bs = header.get("buffer_seconds", entry.get("buffer_seconds"))
    if bs is not None:
        return float(bs)
    gs = header.get("gradient_seconds", entry.get("gradient_seconds"))
    if gs and frame_seconds is not None:
        return max(0.0, float(frame_seconds) - float(gs))
    return None


def discover(data_dir: str | os.PathLike) -> list[Shot]:
    """Every shot under ``data_dir``, sorted by path (module docstring)."""
    from .io import read_header

    root = Path(data_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a folder")
    shots = []
    refs = sorted(Path(d) / REFERENCE for d, _, files in os.walk(root, followlinks=True) if REFERENCE in files)
    for ref in refs:  # os.walk with followlinks: shot folders linked into ``root`` count too
        timings = _timings(ref.parent / SHOT_RECORD)
        renders = []
        for p in sorted(ref.parent.glob("*.exr")):
            if p.name == REFERENCE or p.name.startswith("."):
                continue
            h = read_header(p)
            entry = timings.get(p.name, {})
            rs = h.get("render_seconds", entry.get("seconds"))
            renders.append(Render(p, h.get("spp"), float(rs) if rs is not None else None,
                                  _buffer_seconds(h, entry, rs), h.get("primal"), h.get("adaptive")))
        shots.append(Shot(ref.parent, ref, tuple(renders)))
    if not shots:
        raise FileNotFoundError(f"{root}: no shot found (a shot is a folder holding {REFERENCE} and noisy EXRs)")
    return shots


def sequences(shots: list[Shot]) -> tuple[list[Sequence], list[Shot]]:
    """Split `discover`'s shots into sequences (``frame_XXXX/`` siblings, in frame order) and the
    remaining single shots. Frame numbers must be consecutive (a gap is an error naming it)."""
    groups: dict[Path, list[Shot]] = {}
    singles = []
    for s in shots:
        if s.frame is None:
            singles.append(s)
        else:
            groups.setdefault(s.folder.parent, []).append(s)
    seqs = []
    for parent, members in sorted(groups.items()):
        members.sort(key=lambda s: s.frame)
        idx = [s.frame for s in members]
        if idx != list(range(idx[0], idx[0] + len(idx))):
            raise JaxdenoiseError(f"{parent}: sequence frames {idx} are not consecutive")
        seqs.append(Sequence(parent, tuple(members)))
    return seqs, singles


def renders_by_spp(shot: Shot, spps=None) -> dict[int, list[Render]]:
    """The shot's renders grouped by their header ``spp`` (name order within a rate), limited to
    ``spps`` when given. A render without an ``spp`` attribute is an error naming the file."""
    out: dict[int, list[Render]] = {}
    for r in shot.renders:
        if r.spp is None:
            raise JaxdenoiseError(f"{r.path}: no integer 'spp' header attribute; cannot tell its sample count")
        if spps is None or r.spp in spps:
            out.setdefault(int(r.spp), []).append(r)
    return out
