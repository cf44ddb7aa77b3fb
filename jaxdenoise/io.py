"""EXR read/write through OpenImageIO (the only module that imports it), DESIGN.md "Data contract".

One multi-channel EXR per frame. Channel names follow `jaxdenoise.buffers.CHANNELS`
(``R G B``, ``var.R/G/B``, ``albedo.R/G/B``, ``N.X/Y/Z``, ``Z``, ``vis``, ``<layer>.var`` ...);
the header carries an integer ``spp`` and the renderer's settings as plain attributes.

Reading validates and names the file, the channel and the count of bad pixels for: files that
are not (readable) EXR, truncated files, missing required channels, incomplete layers, NaN/Inf,
negative radiance or variance. ``repair="zero"`` is the one documented repair policy (see
`REPAIR_POLICY`): it replaces instead of failing and reports what it changed.
"""
from __future__ import annotations

import glob as _glob
import os
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import OpenImageIO as oiio

from .buffers import CHANNELS, IMAGE_FIELDS, Buffers, BuffersError
from .fsutil import atomic_path
from .errors import JaxdenoiseError

__all__ = [
    "ExrError", "REPAIR_POLICY", "read_buffers", "read_image", "read_sequence", "write_buffers",
    "write_image", "read_header",
]

REPAIR_POLICY = (
    "repair='zero': NaN and +/-Inf samples become 0 in every channel; negative values in radiance "
    "(R G B) and in variance channels (var.*, *.var) are clamped to 0. The counts of repaired "
    "pixels per channel are returned in attrs['repaired'] and a RuntimeWarning is issued.")

# Channels that must not be negative: radiance and all variances.
_NONNEGATIVE = {"color", "color_var"} | {f for f in IMAGE_FIELDS if f.endswith("_var")}
# EXR attributes OpenImageIO adds on its own; not renderer settings.
_HOUSEKEEPING_PREFIXES = ("oiio:", "openexr:", "compression", "PixelAspectRatio", "screenWindow",
                          "DateTime", "Software")


class ExrError(JaxdenoiseError):
    """A file is not a valid frame under the EXR contract (the message names file and channel)."""


def _oiio_message(source: Any = None) -> str:
    """OpenImageIO's last error message. A corrupt header can put bytes that are not UTF-8 into it,
    which the Python binding fails to decode: say so instead of letting UnicodeDecodeError escape."""
    try:
        return (source.geterror() if source is not None else oiio.geterror()).strip()
    except UnicodeDecodeError as e:
        return f"its error message holds bytes that are not UTF-8 ({e.reason} at byte {e.start}): a corrupt header"


def _open(path: Path):
    if not path.exists():
        raise ExrError(f"{path}: no such file")
    try:
        inp = oiio.ImageInput.open(str(path))
    except UnicodeDecodeError as e:
        raise ExrError(f"{path}: the header holds text that is not UTF-8 ({e.reason} at byte {e.start}); "
                       f"the file is corrupt") from None
    if inp is None:
        raise ExrError(f"{path}: cannot be read as an image ({_oiio_message() or 'unknown format'})")
    if inp.format_name() != "openexr":
        inp.close()
        raise ExrError(f"{path}: is a {inp.format_name()} file; expected OpenEXR")
    return inp


def _spec(path: Path, inp) -> tuple[Any, list[str], dict[str, Any]]:
    """(spec, channel names, attributes) with undecodable header text reported as a corrupt header."""
    try:
        spec = inp.spec()
        return spec, list(spec.channelnames), _attrs(spec)
    except UnicodeDecodeError as e:
        raise ExrError(f"{path}: a header attribute or channel name is not UTF-8 text ({e.reason} at byte "
                       f"{e.start}); the header is corrupt") from None


def _memory_limit() -> int:
    """Bytes a single frame may take: half the machine's physical memory."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError):
        return 8 << 30


def read_header(path: str | os.PathLike) -> dict[str, Any]:
    """Header attributes of an EXR (``spp`` and renderer settings), without reading pixels."""
    path = Path(path)
    inp = _open(path)
    try:
        spec, names, attrs = _spec(path, inp)
        attrs["channels"] = names
        attrs["width"], attrs["height"] = spec.width, spec.height
        return attrs
    finally:
        inp.close()


def _attrs(spec) -> dict[str, Any]:
    out = {}
    for a in spec.extra_attribs:
        if a.name.startswith(_HOUSEKEEPING_PREFIXES):
            continue
        out[a.name] = a.value
    return out


def _read_pixels(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    inp = _open(path)
    try:
        spec, names, attrs = _spec(path, inp)
        if len(set(names)) != len(names):
            raise ExrError(f"{path}: duplicate channel names {names}")
        # Refuse before allocating: a corrupt or hostile header can claim any size.
        need = int(spec.width) * int(spec.height) * int(spec.nchannels) * 4
        if spec.width <= 0 or spec.height <= 0 or need > _memory_limit():
            raise ExrError(f"{path}: the header claims {spec.width}x{spec.height} pixels x {spec.nchannels} "
                           f"channel(s) = {need / 2**30:.1f} GiB as float32, over this machine's limit of "
                           f"{_memory_limit() / 2**30:.1f} GiB (half its memory); refusing to allocate")
        data = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if data is None:
            raise ExrError(f"{path}: pixel data cannot be read, the file is truncated or corrupt "
                           f"({_oiio_message(inp) or _oiio_message()})")
        data = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    finally:
        inp.close()
    return {n: data[..., i] for i, n in enumerate(names)}, attrs


def _check_values(path: Path, field: str, names: tuple[str, ...], arr: np.ndarray,
                  repair: str | None, repaired: dict[str, int]) -> np.ndarray:
    """Reject (or repair, by policy) non-finite and negative samples, naming file, channel and count."""
    bad_finite = ~np.isfinite(arr)
    bad_neg = (arr < 0) if field in _NONNEGATIVE else np.zeros_like(bad_finite)
    if not (bad_finite.any() or bad_neg.any()):
        return arr
    if repair is None:
        for i, ch in enumerate(names):
            n_nan = int(np.isnan(arr[..., i]).sum())
            n_inf = int(np.isinf(arr[..., i]).sum())
            if n_nan or n_inf:
                raise ExrError(f"{path}: channel '{ch}' has {n_nan} NaN and {n_inf} Inf pixel(s); "
                               f"pass repair='zero' to replace them ({REPAIR_POLICY})")
        for i, ch in enumerate(names):
            n_neg = int(bad_neg[..., i].sum())
            if n_neg:
                what = "radiance" if field == "color" else "variance"
                raise ExrError(f"{path}: channel '{ch}' has {n_neg} negative {what} pixel(s) "
                               f"(min {float(arr[..., i].min()):.3g}); pass repair='zero' to clamp them")
    arr = arr.copy()
    for i, ch in enumerate(names):
        count = int((bad_finite[..., i] | bad_neg[..., i]).sum())
        if count:
            repaired[ch] = count
    arr[bad_finite | bad_neg] = 0.0
    return arr


def read_buffers(path: str | os.PathLike, *, repair: str | None = None,
                 required: tuple[str, ...] = ("color",)) -> tuple[Buffers, dict[str, Any]]:
    """Read one frame into `Buffers` and its header attributes.

    Optional layers absent from the file are ``None`` (never invented zeros). ``required`` lists
    `Buffers` fields that must be present. ``repair`` is ``None`` (fail on bad values) or
    ``"zero"`` (`REPAIR_POLICY`). Channels outside the contract are ignored and listed in
    ``attrs['ignored_channels']``.
    """
    if repair not in (None, "zero"):
        raise JaxdenoiseError(f"repair={repair!r}; expected None or 'zero'")
    path = Path(path)
    chans, attrs = _read_pixels(path)
    fields: dict[str, Any] = {}
    known: set[str] = set()
    repaired: dict[str, int] = {}
    for field, names in CHANNELS.items():
        have = [n for n in names if n in chans]
        known.update(have)
        if not have:
            continue
        if len(have) != len(names):
            missing = [n for n in names if n not in chans]
            raise ExrError(f"{path}: layer '{field}' is incomplete: has {have}, missing channel(s) {missing}")
        arr = np.stack([chans[n] for n in names], axis=-1)
        fields[field] = _check_values(path, field, names, arr, repair, repaired)
    if "color" not in fields:
        raise ExrError(f"{path}: missing required channel(s) R, G, B (has {sorted(chans)})")
    spp = attrs.get("spp")
    if spp is not None:
        if not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ExrError(f"{path}: header attribute 'spp' is {spp!r}; expected a positive integer")
        fields["spp"] = np.float32(spp)
    for field in EXR_MATRICES:
        m = _read_matrix(path, attrs, field)
        if m is not None:
            fields[field] = m
    ignored = sorted(set(chans) - known)
    if ignored:
        attrs["ignored_channels"] = ignored
    if repaired:
        attrs["repaired"] = repaired
        warnings.warn(f"{path}: repaired bad pixels {repaired} ({REPAIR_POLICY})", RuntimeWarning, stacklevel=2)
    try:
        buffers = Buffers(**fields).validate(required, where=str(path))
    except BuffersError as e:
        raise ExrError(str(e)) from None
    return buffers, attrs


def read_image(path: str | os.PathLike, *, repair: str | None = None) -> np.ndarray:
    """Read the ``R G B`` channels of an EXR (e.g. a reference) as float32 HWC, validated."""
    buffers, _ = read_buffers(path, repair=repair)
    return buffers.color


def read_sequence(pattern: str, *, repair: str | None = None) -> tuple[list[Buffers], list[Path]]:
    """Read every frame matching a glob (sorted by name) into a list of `Buffers`.

    All frames must have the same size and the same set of buffers (the error names the file).
    """
    paths = sorted(Path(p) for p in _glob.glob(pattern))
    if not paths:
        raise ExrError(f"no files match '{pattern}'")
    frames: list[Buffers] = []
    for p in paths:
        b, _ = read_buffers(p, repair=repair)
        if frames:
            if b.shape != frames[0].shape:
                raise ExrError(f"{p}: size {b.shape[1]}x{b.shape[0]} differs from {paths[0]} "
                               f"({frames[0].shape[1]}x{frames[0].shape[0]})")
            if b.present() != frames[0].present():
                raise ExrError(f"{p}: buffers {sorted(b.present())} differ from {paths[0]}'s "
                               f"{sorted(frames[0].present())}")
        frames.append(b)
    return frames, paths


# Frame metadata stored as OpenEXR's standard matrix attributes. OpenEXR multiplies row vectors
# (``p' = p M``); `Buffers` holds the column-vector matrix, the transpose (`jaxdenoise.view`).
EXR_MATRICES: dict[str, str] = {"world_to_camera": "worldToCamera", "world_to_ndc": "worldToNDC"}


def _read_matrix(path: Path, attrs: dict, field: str) -> np.ndarray | None:
    name = EXR_MATRICES[field]
    if name not in attrs:
        return None
    try:
        m = np.asarray(attrs[name], np.float64).reshape(4, 4).T
    except (TypeError, ValueError):
        raise ExrError(f"{path}: header attribute '{name}' is {attrs[name]!r}; expected a 4x4 matrix") from None
    if not np.all(np.isfinite(m)):
        raise ExrError(f"{path}: header attribute '{name}' has non-finite entries")
    return m.astype(np.float32)


def _header_value(spec, name: str, value: Any, path: Path) -> None:
    if isinstance(value, np.ndarray) and value.shape == (4, 4):
        spec.attribute(name, oiio.TypeDesc("matrix"), tuple(float(v) for v in value.T.reshape(-1)))
    elif isinstance(value, (bool, np.bool_)):
        spec.attribute(name, int(value))
    elif isinstance(value, (int, np.integer)):
        spec.attribute(name, int(value))
    elif isinstance(value, (float, np.floating)):
        spec.attribute(name, float(value))
    elif isinstance(value, str):
        spec.attribute(name, value)
    else:
        raise ExrError(f"{path}: header attribute '{name}' has type {type(value).__name__}; "
                       f"expected int, float, str or a 4x4 matrix")


def _write(path: Path, names: list[str], data: np.ndarray, attrs: Mapping[str, Any] | None) -> Path:
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, "float")
    spec.channelnames = tuple(names)
    spec.attribute("compression", "zip")
    spec.attribute("DateTime", "")  # no write-time stamp: identical pixels give identical files
    for k, v in (attrs or {}).items():
        _header_value(spec, k, v, path)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ExrError(f"{path}: cannot create an EXR writer ({oiio.geterror().strip()})")
        ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(data, dtype=np.float32))
        err = out.geterror()
        out.close()
        if not ok:
            raise ExrError(f"{path}: writing failed ({err.strip()})")
    return path


def write_buffers(path: str | os.PathLike, buffers: Buffers, attrs: Mapping[str, Any] | None = None) -> Path:
    """Write every present buffer of one frame as a multi-channel EXR (atomically).

    ``buffers.spp`` becomes the integer header attribute ``spp`` and the camera matrices OpenEXR's
    ``worldToCamera`` / ``worldToNDC``; ``attrs`` (int/float/str) are written as further header
    attributes (the renderer's settings).
    """
    path = Path(path)
    buffers = buffers.to_numpy()
    buffers.validate(where=str(path))
    if buffers.color.ndim != 3:
        raise ExrError(f"{path}: write_buffers takes one frame (H, W, C); got color of shape {buffers.color.shape}")
    names: list[str] = []
    planes: list[np.ndarray] = []
    for field, chans in CHANNELS.items():
        value = getattr(buffers, field)
        if value is None:
            continue
        names.extend(chans)
        planes.append(np.asarray(value, dtype=np.float32))
    header = dict(attrs or {})
    if buffers.spp is not None:
        spp = float(np.asarray(buffers.spp))
        if spp != int(spp) or spp < 1:
            raise ExrError(f"{path}: spp={spp} is not a positive integer")
        header["spp"] = int(spp)
    for field, name in EXR_MATRICES.items():
        m = getattr(buffers, field)
        if m is not None:
            m = np.asarray(m, np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise ExrError(f"{path}: '{field}' must be one finite 4x4 matrix, got shape {m.shape}")
            header[name] = m
    return _write(path, names, np.concatenate(planes, axis=-1), header)


def write_image(path: str | os.PathLike, image: Any, attrs: Mapping[str, Any] | None = None) -> Path:
    """Write an HWC image with 1 (``Y``), 3 (``R G B``) or 4 (``R G B A``) channels (atomically)."""
    path = Path(path)
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise ExrError(f"{path}: image has shape {image.shape}; expected (H, W, 1|3|4)")
    names = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}[image.shape[-1]]
    return _write(path, names, image, attrs)
