"""The training-data pipeline of the networks: a decoded cache, random crops and 7-frame sequence
crops, the augmentations of Chaitanya et al. 2017 Sec. 4.3, and a compact export.

**Cache** (`build_cache` / `Cache`): every render of a data folder (`jaxdenoise.data`: shots and
``frame_XXXX/`` sequences) is decoded once, for the buffers a method names, into one float32
``.npy`` per render (channels of the named fields stacked in that order) plus one per reference,
under ``CACHE_DIR/<key>/``; the key hashes the field list and every source file's path, size and
modification time, so a changed data folder gets a new cache and an unchanged one is reused: the
second epoch (and the second run) reads no EXR. Arrays are opened memory-mapped. Files are written
under a temporary name and renamed (an interrupted build leaves no half-written array; the index is
written last).

**Sampling** (`Cache.crops`, `Cache.sequences`): deterministic functions of a
``numpy.random.Generator``; the trainer seeds it from ``(seed, step)``, so a resumed run draws the
same batches. A crop is the same window of every buffer and of the reference; a sequence crop is the
same window of 7 consecutive frames of one noisy video.

**Augmentations** (`augment`), applied consistently to every buffer of a crop / sequence:

- rotation by 0 / 90 / 180 / 270 degrees (Chaitanya 2017 Sec. 4.3) and a horizontal flip (our
  addition; mirrored images are as plausible as rotated ones). World-space vectors (normal,
  position) are left as they are, being independent of the image orientation; the gradient-domain
  differences ``dx`` / ``dy`` are remapped as the forward-difference convention requires (a 90-degree
  turn swaps them, negating one and shifting it by a pixel: `rotate90`, `flip_lr`);
- a per-channel colour modulation in [0, 2] for the whole sequence (Chaitanya 2017): radiance-like
  fields (``color``, the reference, ``dx``, ``dy``) are multiplied by ``m``, ``color_var`` by ``m^2``;
  albedo is not (the modulation tints the illumination, the quantity the network reconstructs);
- forward or backward playback (sequences), and random camera stops: the camera and the target stay
  on one frame for a few frames while the noisy input advances through that frame's other noise
  instances (sequences with several instances per frame).

**Per-frame statistics** (``stats=``): a network that normalizes an input by a statistic of the
frame (DEMC's world-position z-score, RAE's mean linear depth, GradNet's largest depth) must see it
computed on the whole render in training too, not on the crop it is given, or it learns its
features on a scale that inference (which gets the whole frame) never shows it. A method declares
them (``frame_stats(config)``: ``{name: function of a whole frame's buffers -> small per-frame
vector}``, `jaxdenoise.methods.protocol`); `build_cache` evaluates each on every whole cached
render (its cached float32 fields, ``spp`` and camera matrices; never the reference) and stores the
values in the index; every crop, sequence crop and whole render drawn from the cache carries them as
extra entries ``"stat.<name>"`` (`STAT`): ``(n, k)`` for crops, ``(n, T, k)`` for sequence crops,
one value per frame of the sequence, each frame's own. Statistics of quantities the augmentations
only move (positions, depths) pass through `augment` unchanged (backward playback reverses them
with the frames); a statistic named in `RADIANCE_STATS` is a per-channel radiance
``(..., 3)`` (DEMC's clipped mean colour) and is multiplied by the colour modulation ``m`` with the
colour, so a modulated crop carries the statistic of its modulated whole render (exactly where the
statistic is linear in the colour). A method's input builder reads the carried value
(`carried_stat`) and otherwise computes it from the array it is given, which at inference is the
whole frame. A cache built before a statistic was declared gets it on opening, computed from the
cached whole renders, and its index is rewritten (no EXR is decoded again); the name of a statistic
identifies its definition (a changed definition takes a new name).

**Export** (`Cache.export`, `load_export`): a fixed set of crops or sequence crops in one ``.npz``
(float16 for radiance-like and unbounded fields, 8-bit for bounded features as Chaitanya 2017
Sec. 3.2 stores them: normals, albedo, visibility, roughness), at most ``max_mib`` (60 by default):
the number that fits is stated in the file and returned, so a run can move to another machine
(`ExportedCache` samples from it with the same interface, and `render` / `subset` / ``len`` work on
both). ``max_mib`` counts the arrays before compression. A field a method never reads can be left
out (``leave_out``: GradNet's loss has no reference). The per-frame statistics travel in the export
(float32, exact) with each item, so a machine that trains from it gets the values of the whole
renders; an export that lacks a statistic a method declares (one written before the method declared
it) is refused by `open_training_data`, naming the file and the statistic: export it again (its
items may be crops, from which the whole render's value cannot be recovered).
"""
from __future__ import annotations

import copy
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .buffers import CHANNELS, IMAGE_FIELDS, MATRIX_FIELDS
from .fsutil import atomic_path, write_json
from .errors import JaxdenoiseError

__all__ = ["build_cache", "Cache", "ExportedCache", "load_export", "open_training_data", "default_cache_dir", "augment", "rotate90", "flip_lr",
           "carried_stat", "carried_stats", "RADIANCE", "RADIANCE_STATS", "BOUNDED", "STAT"]

# Fields that scale with radiance (colour modulation multiplies them by m; variances by m^2).
RADIANCE = ("color", "dx", "dy", "emission", "reference")
# Per-frame statistics (by name) that are per-channel radiance, (..., 3): modulated with the colour.
RADIANCE_STATS = ("color_mean",)
# Bounded features stored as 8 bits in an export (value range).
BOUNDED = {"normal": (-1.0, 1.0), "albedo": (0.0, 1.0), "albedo2": (0.0, 1.0), "visibility": (0.0, 1.0),
           "roughness": (0.0, 1.0)}
# View-space vectors (x right, y up in the image): a quarter turn of the image turns their (x, y)
# with it and a mirror negates x. Derived fields that methods add before augmenting (`jaxdenoise.view`).
VIEW_VECTORS = ("normal_view",)
# Derived per-pixel scalars (turned and mirrored like any image).
DERIVED_SCALARS = ("depth_linear",)
CACHE_VERSION = 3  # 2: camera matrices in the index; 3: each render's primal (gradient frames' colour)
# Integer bookkeeping of a whole-render export: each render's video (-1: a single shot) and frame.
_INDEX = ("video", "frame")
# The key prefix under which an item carries a per-frame statistic of its whole render (module
# docstring): ``"stat.<name>"``.
STAT = "stat."
# A method's per-frame statistics: name -> a function of a whole frame's buffers (a dict of its
# fields, ``spp`` and camera matrices) returning a small vector per frame.
FrameStats = Mapping[str, Callable[[Mapping[str, Any]], Any]]


def carried_stat(frame: Any, name: str) -> Any:
    """The per-frame statistic ``name`` that ``frame`` carries (``frame["stat." + name]``: an item
    drawn by this pipeline, the value computed on its whole render), or None: a `Buffers` or a dict
    without it, whose arrays are then the whole frame and the method computes the statistic from
    them."""
    return frame.get(STAT + name) if isinstance(frame, Mapping) else None


def carried_stats(batch: Mapping[str, Any]) -> dict[str, Any]:
    """The per-frame statistics a batch carries (its ``"stat.*"`` entries), for a method's `batch`
    that selects the fields it passes on."""
    return {k: v for k, v in batch.items() if k.startswith(STAT)}


def _per_frame(f: str) -> bool:
    """Whether an item's entry ``f`` is one value per frame (not an image to crop)."""
    return f == "spp" or f in MATRIX_FIELDS or f.startswith(STAT)


def _metadata(entry: dict) -> dict[str, np.ndarray]:
    """A cached render's per-frame metadata from its index entry: ``spp`` and the camera."""
    out = {"spp": np.float32(entry["spp"])}
    for m in MATRIX_FIELDS:  # the frame's camera (a crop keeps it: view-space inputs need it)
        if m in entry:
            out[m] = np.asarray(entry[m], np.float32)
    return out


def _evaluate_stats(stats: FrameStats, frame: dict[str, np.ndarray], where: Any) -> dict[str, list[float]]:
    """Every statistic of ``stats`` on one whole frame, as the index stores them (float32 values in
    a list: exact through JSON)."""
    out = {}
    for name, fn in stats.items():
        try:
            v = np.asarray(fn(frame), np.float32)
        except KeyError as e:
            raise JaxdenoiseError(f"{where}: the per-frame statistic {name!r} reads {e}, which the cache does "
                                  f"not hold (it holds {sorted(frame)})") from None
        if v.ndim != 1:
            raise JaxdenoiseError(f"{where}: the per-frame statistic {name!r} must be one small vector per frame, "
                                  f"got shape {v.shape}")
        out[name] = v.astype(np.float64).tolist()
    return out


def _save_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:  # keeps the .npy suffix, so np.save adds none
        np.save(tmp, array)


def _channels(fields: Sequence[str]) -> dict[str, slice]:
    out, c = {}, 0
    for f in fields:
        n = len(CHANNELS[f])
        out[f] = slice(c, c + n)
        c += n
    return out


# -- geometric transforms (any leading axes, (..., H, W, C)) -----------------------------------------

def rotate90(fields: dict[str, np.ndarray], k: int = 1) -> dict[str, np.ndarray]:
    """Rotate every image by ``k`` quarter turns counter-clockwise (``np.rot90`` on the H, W axes).

    ``dx`` / ``dy`` follow the forward-difference convention (``dx[y, x] = I[y, x+1] - I[y, x]``,
    ``dy[y, x] = I[y+1, x] - I[y, x]``, last column / row 0). For one quarter turn,
    ``I'[i, j] = I[j, W-1-i]``, hence ``dx' = rot(dy)`` and ``dy'[i, j] = -rot(dx)[i+1, j]`` (last row
    0): swapped, one negated and shifted by a pixel."""
    out = dict(fields)
    for _ in range(int(k) % 4):
        rot = {f: np.rot90(v, 1, axes=(-3, -2)) for f, v in out.items()}
        for f in VIEW_VECTORS:
            if f in rot:  # the content turns counter-clockwise: (x, y) -> (-y, x)
                v = np.array(rot[f])
                v[..., 0], v[..., 1] = -rot[f][..., 1], rot[f][..., 0]
                rot[f] = v
        if "dx" in out and "dy" in out:
            rdx = rot["dx"]
            dy = np.zeros_like(rdx)
            dy[..., :-1, :, :] = -rdx[..., 1:, :, :]
            rot["dx"], rot["dy"] = rot["dy"], dy
        elif "dx" in out or "dy" in out:
            raise JaxdenoiseError("rotate90: dx and dy must come together (a rotation mixes them)")
        out = rot
    return {f: np.ascontiguousarray(v) for f, v in out.items()}


def flip_lr(fields: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Mirror every image left-right: ``I'[y, x] = I[y, W-1-x]``, hence ``dy' = flip(dy)`` and
    ``dx'[y, x] = -flip(dx)[y, x+1]`` (last column 0)."""
    out = {f: np.ascontiguousarray(v[..., ::-1, :]) for f, v in fields.items()}
    for f in VIEW_VECTORS:
        if f in out:
            out[f] = out[f] * np.array([-1.0, 1.0, 1.0], np.float32)[: out[f].shape[-1]]
    if "dx" in out:
        fdx = out["dx"]
        dx = np.zeros_like(fdx)
        dx[..., :, :-1, :] = -fdx[..., :, 1:, :]
        out["dx"] = dx
    return out


def augment(item: dict[str, np.ndarray], rng: np.random.Generator, *, rotate: bool = True, flip: bool = True,
            modulate: bool = True, reverse: bool = False) -> dict[str, np.ndarray]:
    """One random augmentation (module docstring) of one crop ``(H, W, C)`` or sequence crop
    ``(T, H, W, C)`` (the same for every field and every frame). Non-image entries (``spp``) pass
    through; ``reverse`` (sequences) plays the frames backwards with probability 1/2."""
    images = {f: v for f, v in item.items() if f in IMAGE_FIELDS or f in VIEW_VECTORS or f in DERIVED_SCALARS
              or f == "reference"}
    rest = {f: v for f, v in item.items() if f not in images}
    images = rotate90(images, int(rng.integers(0, 4)) if rotate else 0)
    if flip and rng.random() < 0.5:
        images = flip_lr(images)
    if modulate:
        m = rng.uniform(0.0, 2.0, size=3).astype(np.float32)
        for f in list(images):
            if f in RADIANCE:
                images[f] = images[f] * m
            elif f == "color_var":
                images[f] = images[f] * m * m
        for name in RADIANCE_STATS:
            if STAT + name in rest:
                rest[STAT + name] = np.asarray(rest[STAT + name], np.float32) * m
    if reverse and rng.random() < 0.5:
        images = {f: np.ascontiguousarray(v[::-1]) for f, v in images.items()}
        rest = {f: (v[::-1] if np.ndim(v) >= 1 else v) for f, v in rest.items()}
    return {**images, **rest}


# -- the cache -------------------------------------------------------------------------------------

def _key(fields: Sequence[str], files: list[Path]) -> str:
    h = hashlib.sha256(json.dumps({"v": CACHE_VERSION, "fields": list(fields)}).encode())
    for p in files:
        st = p.stat()
        h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def build_cache(data_dir: str | os.PathLike, fields: Sequence[str], cache_dir: str | os.PathLike, *,
                spps: Sequence[int] | None = None, progress: bool = False,
                fill: dict[str, float] | None = None, repair: str | None = None,
                stats: FrameStats | None = None) -> "Cache":
    """Decode the renders of ``data_dir`` (those at ``spps``, or all) for ``fields`` (``color``
    first, others in the given order) into ``cache_dir`` once; reuse it when nothing changed.
    ``fill`` names the constant a method documents for a field a render left out (data_gen leaves a
    constant buffer out, e.g. roughness in a scene whose BSDFs all share one); the frames filled are
    listed in the index. Any other missing field is an error naming the file. A render with NaN/Inf
    or negative radiance is an error naming the file and channel (`jaxdenoise.io.read_buffers`)
    unless ``repair="zero"``: then its bad values are zeroed and each frame's index entry counts them
    (``repaired``), so that a method can drop such renders (GradNet, Sec. 5.1). ``stats`` are the
    method's per-frame statistics (module docstring), evaluated on every whole render and stored in
    the index (a reused cache gets those it lacks: `Cache`)."""
    fill = dict(fill or {})
    from .data import discover, sequences
    from .io import read_buffers, read_image

    fields = ["color"] + [f for f in fields if f != "color"]
    unknown = [f for f in fields if f not in CHANNELS]
    if unknown:
        raise JaxdenoiseError(f"build_cache: unknown buffer name(s) {unknown}; known: {list(CHANNELS)}")
    shots = discover(data_dir)
    seqs, singles = sequences(shots)
    wanted = None if spps is None else {int(s) for s in spps}
    renders = [(s, r) for s in shots for r in s.renders if wanted is None or r.spp in wanted]
    if not renders:
        raise FileNotFoundError(f"{data_dir}: no render" + (f" at spp {sorted(wanted)}" if wanted else ""))
    files = sorted({r.path for _, r in renders} | {s.reference for s, _ in renders})
    folder = Path(cache_dir) / _key(fields + [f"fill:{k}={v}" for k, v in sorted(fill.items())]
                                    + ([] if repair is None else [f"repair:{repair}"]), files)
    index_path = folder / "index.json"
    if index_path.is_file():
        return Cache(folder, stats=stats)
    folder.mkdir(parents=True, exist_ok=True)
    it = renders
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(renders, desc="decode cache", unit="render")
    names: dict[Path, str] = {}
    frames = []
    for shot, r in it:
        if shot.reference not in names:
            names[shot.reference] = f"ref_{len(names):05d}.npy"
            _save_npy(folder / names[shot.reference], np.asarray(read_image(shot.reference), np.float32)[..., :3])
        b, attrs = read_buffers(r.path, repair=repair)
        filled = [f for f in fields if getattr(b, f) is None and f in fill]
        if filled:
            b = b.replace(**{f: np.full(b.shape + (len(CHANNELS[f]),), fill[f], np.float32) for f in filled})
        missing = [f for f in fields if getattr(b, f) is None]
        if missing:
            raise JaxdenoiseError(f"{r.path}: lacks buffer(s) {missing} that the cache was asked for")
        if r.spp is None:
            raise JaxdenoiseError(f"{r.path}: no integer 'spp' header attribute")
        name = f"frame_{len(frames):06d}.npy"
        array = np.concatenate([np.asarray(getattr(b, f), np.float32) for f in fields], -1)
        _save_npy(folder / name, array)
        label = f"{shot.folder.parent.name}/{shot.name}" if shot.frame is not None else shot.name
        entry = {"array": name, "reference": names[shot.reference], "spp": int(r.spp), "shot": label,
                 "render": r.path.name, "sequence": str(shot.folder.parent) if shot.frame is not None else None,
                 "frame": shot.frame, "filled": filled, "repaired": int(sum(attrs.get("repaired", {}).values())),
                 "primal": r.primal,
                 **{m: np.asarray(getattr(b, m), np.float64).tolist() for m in MATRIX_FIELDS
                    if getattr(b, m) is not None}}
        if stats:
            entry["stats"] = _evaluate_stats(stats, _whole_frame(array, _channels(fields), entry), r.path)
        frames.append(entry)
    index = {"version": CACHE_VERSION, "fields": fields, "data_dir": str(data_dir), "frames": frames,
             "sequences": len(seqs), "shots": len(singles)}
    write_json(index_path, index)
    return Cache(folder, stats=stats)


def _whole_frame(array: np.ndarray, slices: dict[str, slice], entry: dict) -> dict[str, np.ndarray]:
    """A cached render whole, as the per-frame statistics read it: its fields, ``spp`` and camera
    (never the reference: inference has none)."""
    return {**{f: np.asarray(array[..., sl]) for f, sl in slices.items()}, **_metadata(entry)}


def _videos(frames: list[dict]) -> list[dict[int, list[int]]]:
    """Sequences: (sequence folder, spp) -> frame indices in time order, one list per frame (the
    render's noise instances, the other instances serving camera stops)."""
    seq: dict[tuple, dict[int, list[int]]] = {}
    for i, f in enumerate(frames):
        if f["sequence"] is not None:
            seq.setdefault((f["sequence"], f["spp"]), {}).setdefault(f["frame"], []).append(i)
    return [{t: ids for t, ids in sorted(v.items())} for _, v in sorted(seq.items())]


def _sample_sequences(videos: list[dict], item, shape, n: int, size: int, rng: np.random.Generator, *,
                      frames: int, stop_probability: float, max_stop: int, aug: dict, where) -> dict[str, np.ndarray]:
    """The sequence-crop sampler of `Cache.sequences` and `ExportedCache.sequences`: ``videos`` as
    `_videos` gives them (frame -> the keys of its noise instances), ``item(key, y, x, size)`` a
    cropped render, ``shape(key)`` its size."""
    videos = [v for v in videos if len(v) >= frames]
    if not videos:
        raise JaxdenoiseError(f"{where}: no sequence with {frames} frames")
    aug = {"reverse": True, **aug}
    items = []
    for _ in range(int(n)):
        v = videos[int(rng.integers(0, len(videos)))]
        keys = list(v)
        t0 = int(rng.integers(0, len(keys) - frames + 1))
        picks = [(keys[t0 + k], 0) for k in range(frames)]
        if stop_probability and rng.random() < stop_probability and max(len(ids) for ids in v.values()) > 1:
            start = int(rng.integers(0, frames - 1))
            length = int(rng.integers(2, max_stop + 1))
            stop_t = picks[start][0]
            for k in range(start, min(frames, start + length)):
                picks[k] = (stop_t, k - start)
            for k in range(start + length, frames):
                picks[k] = (keys[min(len(keys) - 1, t0 + k - length + 1)], 0)
        h, w = shape(v[picks[0][0]][0])
        c = min(size, h, w)
        y, x = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        seq = [item(v[t][inst % len(v[t])], y, x, c) for t, inst in picks]
        items.append(_augment_maybe({f: np.stack([s[f] for s in seq]) for f in seq[0]}, rng, aug))
    return _stack(items)


class Cache:
    """A decoded cache (`build_cache`): memory-mapped arrays and crop / sequence samplers. Every item
    drawn carries the per-frame statistics of ``stats`` (module docstring; their names in
    ``stat_names``, their values in each frame's index entry); those the index lacks (a cache built
    before the method declared them) are computed here from the cached whole renders and the index
    is rewritten (atomically)."""

    def __init__(self, folder: str | os.PathLike, *, stats: FrameStats | None = None) -> None:
        self.folder = Path(folder)
        index_path = self.folder / "index.json"
        index = json.loads(index_path.read_text())
        self.fields: list[str] = index["fields"]
        self.frames: list[dict] = index["frames"]
        self.slices = _channels(self.fields)
        self._arrays: dict[str, np.ndarray] = {}
        self.videos = _videos(self.frames)
        self.stat_names: tuple[str, ...] = tuple(stats or ())
        todo = [f for f in self.frames if not set(self.stat_names) <= set(f.get("stats", {}))]
        for f in todo:
            lacking = {n: fn for n, fn in stats.items() if n not in f.get("stats", {})}
            whole = _whole_frame(self.array(f["array"]), self.slices, f)
            f["stats"] = {**f.get("stats", {}), **_evaluate_stats(lacking, whole, self.folder / f["array"])}
        if todo:
            try:
                write_json(index_path, {**index, "frames": self.frames})
            except OSError:  # a read-only cache (shared): the values hold for this process, recomputed next time
                pass

    def subset(self, keep: Sequence[int]) -> "Cache":
        """The same cache restricted to the renders ``keep`` (indices into ``frames``), e.g. without
        the renders a method drops (GradNet's illegal patches)."""
        out = copy.copy(self)
        out.frames = [self.frames[int(i)] for i in keep]
        out.videos = _videos(out.frames)
        return out

    def __len__(self) -> int:
        return len(self.frames)

    def primals(self, spps: Sequence[int] | None = None) -> list:
        """The ``primal`` header attributes of the renders (at ``spps``, or all), each once: what a
        gradient frame's colour is (data_gen ``--primal``: "base" or "gpt"; None where the header has
        none: a frame without gradients, or one rendered before data_gen recorded it)."""
        return sorted({f.get("primal") for f in self.frames if spps is None or f["spp"] in set(spps)}, key=str)

    def render(self, i: int) -> dict[str, np.ndarray]:
        """Render ``i`` whole and unaugmented: every cached field, its reference, ``spp``, the camera
        and the per-frame statistics."""
        h, w = self.array(self.frames[i]["array"]).shape[:2]
        return self._item(i, 0, 0, max(h, w))

    def array(self, name: str) -> np.ndarray:
        if name not in self._arrays:
            self._arrays[name] = np.load(self.folder / name, mmap_mode="r")
        return self._arrays[name]

    def _item(self, i: int, y: int, x: int, size: int) -> dict[str, np.ndarray]:
        f = self.frames[i]
        a = self.array(f["array"])[y:y + size, x:x + size]
        out = {name: np.array(a[..., sl]) for name, sl in self.slices.items()}
        out["reference"] = np.array(self.array(f["reference"])[y:y + size, x:x + size])
        out.update(_metadata(f))
        for n in self.stat_names:  # of the whole render, whatever the window
            out[STAT + n] = np.asarray(f["stats"][n], np.float32)
        return out

    def crops(self, n: int, size: int, rng: np.random.Generator, *, spps: Sequence[int] | None = None,
              **aug: Any) -> dict[str, np.ndarray]:
        """``n`` random ``size x size`` crops (one random render each, at ``spps`` if given), augmented
        (`augment` keywords; ``augment=False`` for none), stacked: ``{field: (n, size, size, C),
        "reference": ..., "spp": (n,), "stat.<name>": (n, k)}`` (the statistics of each crop's whole
        render)."""
        pool = [i for i, f in enumerate(self.frames) if spps is None or f["spp"] in set(spps)]
        if not pool:
            raise JaxdenoiseError(f"{self.folder}: no cached render" + (f" at spp {list(spps)}" if spps else ""))
        items = []
        for _ in range(int(n)):
            i = pool[int(rng.integers(0, len(pool)))]
            h, w = self.array(self.frames[i]["array"]).shape[:2]
            c = min(size, h, w)
            item = self._item(i, int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1)), c)
            items.append(_augment_maybe(item, rng, aug))
        return _stack(items)

    def sequences(self, n: int, size: int, rng: np.random.Generator, *, frames: int = 7,
                  stop_probability: float = 0.0, max_stop: int = 3, **aug: Any) -> dict[str, np.ndarray]:
        """``n`` random ``frames``-long sequence crops ``{field: (n, frames, size, size, C), ...}`` of
        the cached videos (``"stat.<name>": (n, frames, k)``: each frame's whole-render value); with
        ``stop_probability`` a camera stop (module docstring) of 2..``max_stop`` frames is inserted,
        cycling through the stopped frame's noise instances (sequences whose frames have one
        instance get none). ``reverse`` playback is on by default here."""
        return _sample_sequences(self.videos, self._item, lambda i: self.array(self.frames[i]["array"]).shape[:2],
                                 n, size, rng, frames=frames, stop_probability=stop_probability,
                                 max_stop=max_stop, aug=aug, where=self.folder)

    def _pool(self, spps: Sequence[int] | None, instances: int | None = None) -> list[int]:
        """Indices of the renders at ``spps`` (all if None), keeping at most the first ``instances``
        noise instances of each sequence frame."""
        pool = [i for i, f in enumerate(self.frames) if spps is None or f["spp"] in set(spps)]
        if instances is not None:
            seen: dict[tuple, int] = {}
            keep = []
            for i in pool:
                f = self.frames[i]
                k = (f.get("sequence"), f["spp"], f.get("frame"), f["shot"] if f.get("sequence") is None else None)
                seen[k] = seen.get(k, 0) + 1
                if f.get("sequence") is None or seen[k] <= instances:
                    keep.append(i)
            pool = keep
        if not pool:
            raise JaxdenoiseError(f"{self.folder}: no cached render" + (f" at spp {list(spps)}" if spps else ""))
        return pool

    def whole(self, spps: Sequence[int] | None = None, instances: int | None = None) -> dict[str, np.ndarray]:
        """Every cached render (at ``spps``, or all; at most ``instances`` noise instances of each
        sequence frame) whole, in cache order, stacked like `crops` (the renders must share one
        size), with each render's ``video`` (index of its sequence, -1 for a single shot) and
        ``frame`` (its frame number, -1) so that an export keeps the videos."""
        pool = self._pool(spps, instances)
        sizes = {self.array(self.frames[i]["array"]).shape[:2] for i in pool}
        if len(sizes) != 1:
            raise JaxdenoiseError(f"{self.folder}: renders of several sizes {sorted(sizes)}; whole frames need one")
        (h, w), = sizes
        out = _stack([self._item(i, 0, 0, max(h, w)) for i in pool])
        names = sorted({self.frames[i]["sequence"] for i in pool if self.frames[i].get("sequence") is not None})
        out["video"] = np.asarray([names.index(self.frames[i]["sequence"]) if self.frames[i].get("sequence") is not None
                                   else -1 for i in pool], np.int32)
        out["frame"] = np.asarray([-1 if self.frames[i].get("frame") is None else self.frames[i]["frame"]
                                   for i in pool], np.int32)
        return out

    def export(self, path: str | os.PathLike, *, n: int, size: int = 0, rng: np.random.Generator | None = None,
               frames: int | None = None, max_mib: float = 60.0, spps: Sequence[int] | None = None,
               whole: bool = False, instances: int | None = None, leave_out: Sequence[str] = ()) -> dict:
        """Write ``n`` crops (or ``frames``-long sequence crops) without augmentation to one compact
        ``.npz`` (module docstring), keeping as many as fit in ``max_mib``; returns its summary
        (``count``, ``bytes``, ``per_item_bytes``), also stored in the file. ``spps`` restricts the
        renders; ``whole=True`` exports the first ``n`` renders whole (`whole`) instead of random
        crops (validation frames; training sets small enough to travel as they are; videos keep their
        order, frames and noise instances, at most ``instances`` of each frame, so that
        `ExportedCache.sequences` samples them as `sequences` does here). ``leave_out`` names fields
        not written, e.g. ``("reference",)`` for a method whose loss never reads one (GradNet). The
        per-frame statistics the cache carries go with every item (float32)."""
        leave_out = set(leave_out)
        unknown = sorted(leave_out - {*self.fields, "reference"})
        if unknown:
            raise JaxdenoiseError(f"export: leave_out names {unknown}, which are not fields of {self.folder} "
                             f"(it holds {['color', *self.fields, 'reference']})")
        if "color" in leave_out:
            raise JaxdenoiseError("export: leave_out cannot hold 'color' (every method reads it)")
        if whole:
            every = self.whole(spps, instances)
            size = int(every["color"].shape[1])
            n = min(int(n), len(every["color"]))
            draw = lambda k: {f: v[:k] for f, v in every.items()}
        elif frames is None:
            draw = lambda k: self.crops(k, size, rng, spps=spps, augment=False)
        else:
            draw = lambda k: self.sequences(k, size, rng, frames=frames, augment=False)
        if leave_out:
            full = draw
            draw = lambda k: {f: v for f, v in full(k).items() if f not in leave_out}  # noqa: E731
        probe = _encode(draw(1))
        per_item = sum(a.nbytes for a in probe.values())
        fit = int(max_mib * 2**20 // max(per_item, 1))
        count = min(int(n), fit)
        if count < 1:
            raise JaxdenoiseError(f"export: one item takes {per_item / 2**20:.1f} MiB, more than max_mib={max_mib}")
        enc = _encode(draw(count))
        summary = {"count": count, "requested": int(n), "fit": fit, "per_item_bytes": per_item, "size": size,
                   "frames": frames, "fields": self.fields, "max_mib": max_mib, "whole": bool(whole),
                   "instances": instances, "left_out": sorted(leave_out), "stats": list(self.stat_names),
                   "spps": None if spps is None else [int(s) for s in spps], "primals": self.primals(spps),
                   "source": str(json.loads((self.folder / "index.json").read_text())["data_dir"])}
        enc["summary"] = np.frombuffer(json.dumps(summary).encode(), np.uint8)
        path = Path(path)
        with atomic_path(path) as tmp:
            np.savez_compressed(tmp, **enc)
        summary["bytes"] = path.stat().st_size
        return summary


def _augment_maybe(item, rng, aug):
    aug = dict(aug)
    if aug.pop("augment", True) is False:
        return item
    return augment(item, rng, **aug)


def _stack(items: list[dict]) -> dict[str, np.ndarray]:
    return {f: np.stack([it[f] for it in items]) for f in items[0]}


def _encode(batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for f, v in batch.items():
        if f in BOUNDED:
            lo, hi = BOUNDED[f]
            out[f"u8_{f}"] = np.round((np.clip(v, lo, hi) - lo) / (hi - lo) * 255).astype(np.uint8)
        elif _per_frame(f):
            out[f] = np.asarray(v, np.float32)
        elif f in _INDEX:
            out[f] = np.asarray(v, np.int32)
        else:
            out[f"f16_{f}"] = np.asarray(v, np.float16)
    return out


def load_export(path: str | os.PathLike) -> "ExportedCache":
    """Open a file written by `Cache.export` (needs only numpy: no OpenImageIO on the other machine)."""
    return ExportedCache(path)


class ExportedCache:
    """The crops or sequence crops of an export, decoded to float32, sampled like `Cache`'s:
    ``items`` holds the buffers, the reference and the per-frame metadata, ``stats`` the per-frame
    statistics by name (``(count, k)``, or ``(count, frames, k)`` for sequence crops), which every
    item drawn carries as ``"stat.<name>"`` entries, as a cache's do."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        z = np.load(path)
        self.summary = json.loads(bytes(z["summary"]).decode())
        self.items: dict[str, np.ndarray] = {}
        self.stats: dict[str, np.ndarray] = {}
        for k in z.files:
            if k.startswith("u8_"):
                f = k[3:]
                lo, hi = BOUNDED[f]
                self.items[f] = z[k].astype(np.float32) / 255 * (hi - lo) + lo
            elif k.startswith("f16_"):
                self.items[k[4:]] = z[k].astype(np.float32)
            elif k.startswith(STAT):
                self.stats[k[len(STAT):]] = z[k].astype(np.float32)
            elif k == "spp" or k in MATRIX_FIELDS:
                self.items[k] = z[k]
        self.index = {k: z[k] for k in _INDEX if k in z.files}
        self.count = int(self.summary["count"])
        self.videos = self._videos()

    def _videos(self) -> list[dict]:
        if self.summary.get("frames"):  # fixed sequence crops: each is a video of one instance per frame
            return [{t: [(i, t)] for t in range(int(self.summary["frames"]))} for i in range(self.count)]
        if "video" in self.index:  # whole renders that keep their videos (`Cache.whole`)
            return _videos([{"sequence": None if v < 0 else int(v), "spp": float(s), "frame": int(t)}
                            for v, s, t in zip(self.index["video"], self.items["spp"], self.index["frame"])])
        return []

    def __len__(self) -> int:
        return self.count

    def primals(self, spps: Sequence[int] | None = None) -> list | None:
        """`Cache.primals` of the cache it was exported from (over its exported rates; ``spps`` is
        accepted for the same call and not narrowed further); None for an export written before
        the summary recorded them."""
        return self.summary.get("primals")

    def subset(self, keep: Sequence[int]) -> "ExportedCache":
        """The same export restricted to the items ``keep`` (as `Cache.subset`)."""
        keep = np.asarray(keep, np.int64)
        out = copy.copy(self)
        out.items = {f: v[keep] for f, v in self.items.items()}
        out.stats = {n: v[keep] for n, v in self.stats.items()}
        out.index = {k: v[keep] for k, v in self.index.items()}
        out.count = int(keep.size)
        out.videos = out._videos()
        return out

    def render(self, i: int) -> dict[str, np.ndarray]:
        """Item ``i`` whole and unaugmented (as `Cache.render`; an export of crops gives the crop)."""
        if self.summary.get("frames"):
            raise JaxdenoiseError(f"{self.path}: holds sequence crops; render() needs single frames")
        h, w = self._shape(i)
        return self._item(i, 0, 0, max(h, w))

    def _item(self, key, y: int, x: int, size: int) -> dict[str, np.ndarray]:
        """Render ``key`` (an index, or ``(item, frame)`` of a sequence-crop export) cropped."""
        i, t = key if isinstance(key, tuple) else (key, None)
        out = {}
        for f, v in self._entries().items():
            v = v[i] if t is None else v[i, t]
            out[f] = v if _per_frame(f) else np.array(v[y:y + size, x:x + size])
        return out

    def _entries(self) -> dict[str, np.ndarray]:
        """Every exported array under the name an item carries it by (statistics as ``stat.<name>``)."""
        return {**self.items, **{STAT + n: v for n, v in self.stats.items()}}

    def _shape(self, key) -> tuple[int, int]:
        return tuple(self.items["color"].shape[-3:-1])

    def sequences(self, n: int, size: int, rng: np.random.Generator, *, frames: int = 7,
                  stop_probability: float = 0.0, max_stop: int = 3, **aug: Any) -> dict[str, np.ndarray]:
        """As `Cache.sequences`, on an export of whole videos (`Cache.export(whole=True)`: camera stops
        use the exported noise instances) or of sequence crops (no other instance: no stops)."""
        return _sample_sequences(self.videos, self._item, self._shape, n, size, rng, frames=frames,
                                 stop_probability=stop_probability, max_stop=max_stop, aug=aug, where=self.path)

    def sample(self, n: int, rng: np.random.Generator, **aug: Any) -> dict[str, np.ndarray]:
        """``n`` items drawn with replacement, each augmented (`augment` keywords)."""
        idx = rng.integers(0, self.count, size=int(n))
        entries = self._entries()
        items = [{f: v[i] for f, v in entries.items()} for i in idx]
        return _stack([_augment_maybe(it, rng, aug) for it in items])

    def crops(self, n: int, size: int, rng: np.random.Generator, *, spps: Sequence[int] | None = None,
              **aug: Any) -> dict[str, np.ndarray]:
        """As `Cache.crops`: ``n`` random ``size x size`` windows of random exported items (at
        ``spps`` if given), augmented; the same call on a cache or on its export."""
        if self.summary.get("frames"):
            raise JaxdenoiseError(f"{self.path}: holds sequence crops; crops() needs single frames")
        pool = np.arange(self.count) if spps is None else np.flatnonzero(np.isin(self.items["spp"], list(spps)))
        if pool.size == 0:
            raise JaxdenoiseError(f"{self.path}: no exported item" + (f" at spp {list(spps)}" if spps else ""))
        h, w = self.items["color"].shape[1:3]
        c = min(int(size), h, w)
        entries = self._entries()
        items = []
        for _ in range(int(n)):
            i = int(pool[int(rng.integers(0, pool.size))])
            y, x = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
            item = {f: (v[i] if _per_frame(f) else v[i, y:y + c, x:x + c]) for f, v in entries.items()}
            items.append(_augment_maybe(item, rng, aug))
        return _stack(items)


def default_cache_dir() -> Path:
    """Where training caches go unless a caller names a folder: ``$JAXDENOISE_CACHE``, else
    ``~/.cache/jaxdenoise/pipeline``."""
    env = os.environ.get("JAXDENOISE_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "jaxdenoise" / "pipeline"


def open_training_data(source: str | os.PathLike, fields: Sequence[str], *, spps: Sequence[int] | None = None,
                       cache_dir: str | os.PathLike | None = None, progress: bool = False,
                       fill: dict[str, float] | None = None, reference: bool = True,
                       repair: str | None = None, stats: FrameStats | None = None) -> "Cache | ExportedCache":
    """A data_gen folder (decoded once into a `Cache` under ``cache_dir``; ``repair`` and ``stats``
    as in `build_cache`) or an export ``.npz`` (`load_export`; it must hold ``fields``, the
    reference unless ``reference=False`` (a method whose loss never reads one), and every per-frame
    statistic named in ``stats``: an export without them is refused, not recomputed, since its items
    may be crops): the one entry point of the networks' ``make_dataset``, so the same training
    command runs here and on a machine that has only the export."""
    source = Path(source)
    if source.suffix == ".npz":
        if not source.is_file():
            raise FileNotFoundError(f"{source}: no such export file")
        ex = load_export(source)
        # a field the method fills with a constant where a render lacks it may be absent from an export too
        missing = [f for f in ["color", *fields, *(["reference"] if reference else [])]
                   if f not in ex.items and f not in (fill or {})]
        if missing:
            raise JaxdenoiseError(f"{source}: the export lacks {missing} (it holds {sorted(ex.items)})")
        lacking = [n for n in (stats or ()) if n not in ex.stats]
        if lacking:
            raise JaxdenoiseError(
                f"{source}: the export lacks the per-frame statistic(s) {lacking} that the method computes on each "
                f"whole render (it holds {sorted(ex.stats)}); it was written without them: export it again from "
                "a cache opened with the method's statistics (its make_dataset)")
        return ex
    return build_cache(source, fields, cache_dir or default_cache_dir(), spps=spps, progress=progress, fill=fill,
                       repair=repair, stats=stats)
