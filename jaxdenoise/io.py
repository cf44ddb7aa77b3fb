"""EXR read/write through OpenImageIO (the only module that imports it), docs/architecture.md "Data contract".

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
import re
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import OpenImageIO as oiio

from .buffers import (CHANNELS, EMISSION_FIELD, GRADIENT_EMISSION_MODES, GRADIENT_FIELDS, IMAGE_FIELDS,
                      MATRIX_HEADERS, Buffers, BuffersError)
from .fsutil import atomic_path
from .errors import JaxdenoiseError, JaxdenoiseWarning

__all__ = [
    "ExrError", "REPAIR_POLICY", "AOV_ALIASES", "LAYER_KEYS", "DISPLAY_SUFFIXES", "parse_channels", "buffers_from_channels", "read_buffers", "read_image", "read_sequence",
    "write_buffers", "write_image", "write_display", "write_output", "read_header",
]

REPAIR_POLICY = (
    "repair='zero': NaN and +/-Inf samples become 0 in every channel; negative values in radiance "
    "(R G B) and in variance channels (var.*, *.var) are clamped to 0. The counts of repaired "
    "pixels per channel are returned in attrs['repaired'] and a RuntimeWarning is issued.")

# Channels that must not be negative: radiance and all variances.
_NONNEGATIVE = {"color", "color_var", "emission", "spp_map"} | {f for f in IMAGE_FIELDS if f.endswith("_var")}
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
                               f"pass repair='zero' (CLI: --repair) to replace them ({REPAIR_POLICY})")
        for i, ch in enumerate(names):
            n_neg = int(bad_neg[..., i].sum())
            if n_neg:
                what = "radiance" if field == "color" else "variance"
                raise ExrError(f"{path}: channel '{ch}' has {n_neg} negative {what} pixel(s) "
                               f"(min {float(arr[..., i].min()):.3g}); pass repair='zero' (CLI: --repair) to clamp them")
    arr = arr.copy()
    for i, ch in enumerate(names):
        count = int((bad_finite[..., i] | bad_neg[..., i]).sum())
        if count:
            repaired[ch] = count
    arr[bad_finite | bad_neg] = 0.0
    return arr


# -- channel names other renderers write --------------------------------------------------------
# A layer's key (what ``channels=`` maps, beside the `Buffers` field names): the contract's channel
# prefix (``N`` for ``N.X N.Y N.Z``, ``var`` for ``var.R ...``), or the channel itself for a
# one-channel layer (``Z``, ``vis``, ``N.var``).
LAYER_KEYS: dict[str, str] = {
    (names[0] if len(names) == 1 else names[0].rpartition(".")[0] or "color"): field
    for field, names in CHANNELS.items()}
# What Mitsuba 3's ``aov`` integrator writes for the buffers it can make, under the names its docs and
# users commonly give them (``aovs="nn:sh_normal,pp:position,dd:depth,albedo:albedo"``): it names an
# AOV's channels ``<name>.X/Y/Z`` (vectors), ``<name>.R/G/B`` (colours) or ``<name>.T`` (one value).
# Used, and reported in ``attrs['channels_from']``, when the contract's own names are absent.
AOV_ALIASES: dict[str, tuple[str, ...]] = {
    "normal": ("nn", "sh_normal", "normal", "normals"),
    "position": ("pp", "position"),
    "depth": ("dd", "depth", "Z"),
    "albedo": ("albedo", "aa"),
}
# Suffixes of a three-component layer, in component order (first complete set wins), and of a
# one-value layer.
_SUFFIXES_3 = (("X", "Y", "Z"), ("R", "G", "B"), ("x", "y", "z"), ("r", "g", "b"))
_SUFFIXES_1 = ("T", "Y", "y", "V", "A")
# Layer prefixes that look like a buffer the reader knows: ignored channels under them are warned of.
_LOOKALIKE = {**dict.fromkeys(("n", "nn", "normal", "normals", "sh_normal", "geo_normal"), "N"),
              **dict.fromkeys(("p", "pp", "pos", "position"), "P"),
              **dict.fromkeys(("d", "dd", "depth", "z", "distance"), "Z"),
              **dict.fromkeys(("albedo", "aa", "diffuse"), "albedo"), **dict.fromkeys(("var", "variance"), "var")}
_CHANNELS_HELP = ("channels={'N': 'nn', 'P': 'pp', 'Z': 'dd'} in the API, --channels N=nn,P=pp,Z=dd "
                  "in the CLI (keys: a layer: N P Z albedo albedo2 var vis rough dx dy color, or a field name; or one channel: "
                  "R=ch00, N.X=ch03)")


def parse_channels(text: str) -> dict[str, str]:
    """``"N=nn,P=pp,Z=dd"`` (the CLI's ``--channels``) as ``{"N": "nn", "P": "pp", "Z": "dd"}``."""
    out: dict[str, str] = {}
    for item in (t.strip() for t in text.split(",")):
        key, eq, value = item.partition("=")
        if not item or not eq or not key.strip() or not value.strip():
            raise JaxdenoiseError(f"--channels '{text}': '{item}' is not KEY=NAME; expected e.g. N=nn,P=pp,Z=dd")
        if key.strip() in out:
            raise JaxdenoiseError(f"--channels '{text}': '{key.strip()}' is mapped twice")
        out[key.strip()] = value.strip()
    return out


def _layer(chans: dict, prefix: str, n: int) -> tuple[str, ...] | None:
    """The file's channels of layer ``prefix`` as an ``n``-component buffer, in component order."""
    if n == 1:
        if prefix in chans:
            return (prefix,)
        for suffix in _SUFFIXES_1:
            if f"{prefix}.{suffix}" in chans:
                return (f"{prefix}.{suffix}",)
        return None
    for suffixes in _SUFFIXES_3:
        names = tuple(f"{prefix}.{x}" for x in suffixes)
        if all(c in chans for c in names):
            return names
    return None


def _resolve_channels(path: Path, chans: dict, channels: Mapping[str, str] | None) -> tuple[dict, dict]:
    """``(field -> the file's channel names, field -> names taken from other than the contract)``:
    explicit ``channels`` first, then the contract's names, then `AOV_ALIASES`."""
    chosen: dict[str, tuple[str, ...]] = {}
    per_channel: dict[str, dict[int, str]] = {}
    channel_keys = {c: (f, i) for f, names in CHANNELS.items() for i, c in enumerate(names) if len(names) > 1}
    for key, value in (channels or {}).items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise JaxdenoiseError(f"channels: entries map a name to a name; got {key!r}: {value!r}")
        if key in channel_keys:
            field, i = channel_keys[key]
            if value not in chans:
                raise ExrError(f"{path}: channels maps '{key}' to '{value}', which the file does not have "
                               f"(it has {sorted(chans)})")
            per_channel.setdefault(field, {})[i] = value
            continue
        field = key if key in CHANNELS else LAYER_KEYS.get(key)
        if field is None:
            raise JaxdenoiseError(f"channels: unknown key '{key}'; expected a layer ({', '.join(LAYER_KEYS)}), "
                                  f"a field ({', '.join(CHANNELS)}) or a channel ({', '.join(channel_keys)})")
        names = _layer(chans, value, len(CHANNELS[field]))
        if names is None:
            under = sorted(c for c in chans if c == value or c.startswith(value + "."))
            raise ExrError(f"{path}: channels maps '{key}' to '{value}', but the file has no "
                           f"{len(CHANNELS[field])}-channel layer '{value}' (channels under it: {under or 'none'}; "
                           f"the file has {sorted(chans)})")
        chosen[field] = names
    for field, parts in per_channel.items():
        if field in chosen:
            raise JaxdenoiseError(f"channels: '{field}' is mapped both as a layer and channel by channel")
        names = CHANNELS[field]
        if len(parts) != len(names):
            raise JaxdenoiseError(f"channels: '{field}' is mapped channel by channel but only "
                                  f"{[names[i] for i in sorted(parts)]}; map all of {list(names)}")
        chosen[field] = tuple(parts[i] for i in range(len(names)))
    sources = {f: list(v) for f, v in chosen.items()}
    for field, names in CHANNELS.items():
        if field in chosen:
            continue
        have = [n for n in names if n in chans]
        if have:
            if len(have) != len(names):
                missing = [n for n in names if n not in chans]
                raise ExrError(f"{path}: layer '{field}' is incomplete: has {have}, missing channel(s) {missing}")
            chosen[field] = names
            continue
        found = {a: _layer(chans, a, len(names)) for a in AOV_ALIASES.get(field, ())}
        found = {a: v for a, v in found.items() if v is not None and not set(v) & {c for u in chosen.values() for c in u}}
        if len(found) > 1:
            raise ExrError(f"{path}: layers {sorted(found)} could each be '{field}'; say which: {_CHANNELS_HELP}")
        if found:
            (names_found,) = found.values()
            chosen[field] = names_found
            sources[field] = list(names_found)
    return chosen, sources


def _unnamed_hint(chans: dict) -> str:
    names = sorted(chans)
    if names and all(re.fullmatch(r"ch\d+", c) for c in names):
        return (f"; its channels are unnamed ({names[0]}..{names[-1]}: mi.Bitmap(tensor).write() writes a bare "
                f"tensor so): write the film instead (scene.sensors()[0].film().write(path) after mi.render), "
                f"or name them, e.g. channels={{'R': 'ch00', 'G': 'ch01', 'B': 'ch02'}} "
                f"(CLI: --channels R=ch00,G=ch01,B=ch02,N.X=ch03,...)")
    rgb = sorted({c.rpartition(".")[0] for c in names if c.endswith((".R", ".G", ".B")) and "." in c})
    if rgb:
        return f"; to read layer '{rgb[0]}' as the colour: channels={{'color': '{rgb[0]}'}} (CLI: --channels color={rgb[0]})"
    return ""


def read_buffers(path: str | os.PathLike, *, repair: str | None = None,
                 required: tuple[str, ...] = ("color",), channels: Mapping[str, str] | None = None,
                 spp: int | None = None) -> tuple[Buffers, dict[str, Any]]:
    """Read one frame into `Buffers` and its header attributes.

    Optional layers absent from the file are ``None`` (never invented zeros). ``required`` lists
    `Buffers` fields that must be present. ``repair`` is ``None`` (fail on bad values) or
    ``"zero"`` (`REPAIR_POLICY`).

    Files from other renderers: ``channels`` maps a layer (``N``, ``P``, ``Z``, ``albedo``, ...,
    `LAYER_KEYS`, or a field name) to the file's layer (``{"N": "nn"}`` reads ``nn.X nn.Y nn.Z``;
    ``.R/G/B``, ``.x/y/z`` and one-value ``.T``/``.Y`` suffixes are understood) or one channel to
    one channel (``{"R": "ch00"}``). Without a mapping, the names Mitsuba's ``aov`` integrator is
    commonly given (`AOV_ALIASES`: ``nn``, ``pp``, ``dd``, ``Z.T``, ...) are read where the contract's
    own are absent; ``attrs['channels_from']`` lists every buffer not read under its own name.
    ``spp`` gives the sample count when the header has none (Mitsuba writes none); a header that
    has a different one is an error. Channels left unread are listed in ``attrs['ignored_channels']``,
    with a `JaxdenoiseWarning` for those that look like a buffer (``n.X``, ``ch03``, ...).
    """
    if repair not in (None, "zero"):
        raise JaxdenoiseError(f"repair={repair!r}; expected None or 'zero'")
    path = Path(path)
    chans, attrs = _read_pixels(path)
    return _from_channels(path, chans, attrs, repair=repair, required=required, channels=channels, spp=spp, file=path)


def buffers_from_channels(chans: Mapping[str, Any], attrs: Mapping[str, Any] | None = None, *,
                          where: str = "channels", repair: str | None = None,
                          required: tuple[str, ...] = ("color",), channels: Mapping[str, str] | None = None,
                          spp: int | None = None) -> tuple[Buffers, dict[str, Any]]:
    """`read_buffers` on channels already in memory: ``chans`` maps a channel name (``R``, ``N.X``,
    ``nn.X``, ``dd.T``, ...) to an (H, W) array, ``attrs`` are header attributes (``spp``, ...).
    The same names, `AOV_ALIASES`, ``channels=`` mappings, checks and repairs as a file, so a frame
    gives the same `Buffers` in memory as after an EXR round trip; ``where`` names the source in
    every error (e.g. ``"mitsuba tensor"``)."""
    if repair not in (None, "zero"):
        raise JaxdenoiseError(f"repair={repair!r}; expected None or 'zero'")
    arrays: dict[str, np.ndarray] = {}
    shape = None
    for name, value in chans.items():
        arr = np.asarray(value, dtype=np.float32)
        if arr.ndim != 2 or (shape is not None and arr.shape != shape):
            raise JaxdenoiseError(f"{where}: channel '{name}' has shape {arr.shape}; expected one (H, W) plane"
                                  + (f" like the others, {shape}" if shape is not None else ""))
        shape = arr.shape
        arrays[str(name)] = arr
    return _from_channels(where, arrays, dict(attrs or {}), repair=repair, required=required, channels=channels,
                          spp=spp, file=None)


def _from_channels(path, chans: dict, attrs: dict, *, repair, required, channels, spp, file) -> tuple[Buffers, dict]:
    chosen, sources = _resolve_channels(path, chans, channels)
    fields: dict[str, Any] = {}
    repaired: dict[str, int] = {}
    for field, names in chosen.items():
        arr = np.stack([chans[n] for n in names], axis=-1)
        fields[field] = _check_values(path, field, names, arr, repair, repaired)
    if "color" not in fields:
        raise ExrError(f"{path}: missing required channel(s) R, G, B (has {sorted(chans)}){_unnamed_hint(chans)}")
    header_spp = attrs.get("spp")
    if header_spp is not None:
        if not isinstance(header_spp, (int, np.integer)) or header_spp < 1:
            raise ExrError(f"{path}: header attribute 'spp' is {header_spp!r}; expected a positive integer")
        if spp is not None and int(spp) != int(header_spp):
            raise ExrError(f"{path}: spp={spp} given, but the header says spp={header_spp}")
    if spp is not None:
        if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
            raise JaxdenoiseError(f"spp={spp!r}; expected a positive integer (samples per pixel of {path})")
        attrs.setdefault("spp", int(spp))
    if attrs.get("spp") is not None:
        fields["spp"] = np.float32(attrs["spp"])
    _check_gradient_emission(path, fields, attrs)
    for field in EXR_MATRICES:
        m = _read_matrix(path, attrs, field) if file is not None else attrs.get(field)
        if m is not None:
            fields[field] = np.asarray(m, np.float32)
    used = {c for names in chosen.values() for c in names}
    ignored = sorted(set(chans) - used)
    if ignored:
        attrs["ignored_channels"] = ignored
        lookalike = [c for c in ignored if c.rpartition(".")[0].lower() in _LOOKALIKE or re.fullmatch(r"ch\d+", c)]
        if lookalike:
            guess = {}
            for c in lookalike:
                layer = c.rpartition(".")[0]
                key = _LOOKALIKE.get(layer.lower())
                if key is not None and LAYER_KEYS[key] not in chosen:
                    guess.setdefault(key, layer)
            how = (f" (here perhaps channels={guess}, CLI --channels {','.join(f'{k}={v}' for k, v in guess.items())})"
                   if guess else "")
            warnings.warn(f"{path}: channel(s) {lookalike} look like a buffer but were not read; to read them, "
                          f"map them{how} with {_CHANNELS_HELP}", JaxdenoiseWarning, stacklevel=3)
    if sources:
        attrs["channels_from"] = {f: " ".join(v) for f, v in sources.items()}
    if repaired:
        attrs["repaired"] = repaired
        warnings.warn(f"{path}: repaired bad pixels {repaired} ({REPAIR_POLICY})", RuntimeWarning, stacklevel=3)
    try:
        buffers = Buffers(**fields).validate(required, where=str(path))
    except BuffersError as e:
        raise ExrError(str(e)) from None
    return buffers, attrs


def _check_gradient_emission(path, fields: dict, attrs: Mapping[str, Any]) -> None:
    """The header's ``gradient_emission`` (how ``dx``/``dy`` were made, data_gen writes it) against the
    channels: ``separate`` needs the ``emission`` layer beside the gradients, ``included`` (or a frame
    from before the attribute, which has none) must not have one."""
    how = attrs.get("gradient_emission")
    if how is None:
        return
    if how not in GRADIENT_EMISSION_MODES:
        raise ExrError(f"{path}: header attribute 'gradient_emission' is {how!r}; expected one of "
                       f"{GRADIENT_EMISSION_MODES}")
    grads = any(f in fields for f in GRADIENT_FIELDS)
    if how == "separate" and grads and EMISSION_FIELD not in fields:
        raise ExrError(f"{path}: the header says gradient_emission='separate' (dx, dy leave the directly seen "
                       f"emission out) but the channels {', '.join(CHANNELS[EMISSION_FIELD])} are missing")
    if how == "included" and EMISSION_FIELD in fields:
        raise ExrError(f"{path}: the header says gradient_emission='included' (dx, dy hold the directly seen "
                       f"emission) but the frame has an emission layer; one of them is wrong")


def read_image(path: str | os.PathLike, *, repair: str | None = None) -> np.ndarray:
    """Read the ``R G B`` channels of an EXR (e.g. a reference) as float32 HWC, validated."""
    buffers, _ = read_buffers(path, repair=repair)
    return buffers.color


def read_sequence(pattern: str, *, repair: str | None = None, channels: Mapping[str, str] | None = None,
                  spp: int | None = None) -> tuple[list[Buffers], list[Path]]:
    """Read every frame matching a glob (sorted by name) into a list of `Buffers` (``channels`` and
    ``spp`` as in `read_buffers`).

    All frames must have the same size and the same set of buffers (the error names the file).
    """
    paths = sorted(Path(p) for p in _glob.glob(pattern))
    if not paths:
        raise ExrError(f"no files match '{pattern}'")
    frames: list[Buffers] = []
    for p in paths:
        b, _ = read_buffers(p, repair=repair, channels=channels, spp=spp)
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
EXR_MATRICES: dict[str, str] = MATRIX_HEADERS


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
    """Write an HWC image with 1 (``Y``), 3 (``R G B``) or 4 (``R G B A``) channels (atomically) as
    linear float EXR; any other suffix is refused (8-bit display images: `write_display`)."""
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise ExrError(f"{path}: write_image writes linear HDR EXR (suffix .exr); got '{path.suffix}'. "
                       f"For a display image use a {'/'.join(DISPLAY_SUFFIXES)} name (written tone-mapped "
                       f"to sRGB by write_display)")
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise ExrError(f"{path}: image has shape {image.shape}; expected (H, W, 1|3|4)")
    names = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}[image.shape[-1]]
    return _write(path, names, image, attrs)


# 8-bit display formats: written tone-mapped (exposure, clip to [0, 1], the sRGB curve), never linear.
DISPLAY_SUFFIXES = (".png", ".jpg", ".jpeg")


def write_display(path: str | os.PathLike, image: Any, *, exposure: float = 0.0,
                  attrs: Mapping[str, Any] | None = None) -> Path:
    """Write an HWC RGB image as an 8-bit sRGB PNG or JPEG (atomically), for viewing: the linear
    radiance is scaled by ``2 ** exposure`` (stops), clipped to [0, 1] and encoded with the sRGB curve
    (`jaxdenoise.color.srgb`), then rounded. A display image is not radiance: the library never reads
    it back as a frame (keep the EXR for that). ``attrs`` (str/int/float) go into the file's metadata
    where the format has room for them (PNG text chunks)."""
    from .color import srgb

    path = Path(path)
    if path.suffix.lower() not in DISPLAY_SUFFIXES:
        raise ExrError(f"{path}: write_display writes {'/'.join(DISPLAY_SUFFIXES)}; got '{path.suffix}' "
                       f"(linear HDR: write_image, .exr)")
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ExrError(f"{path}: image has shape {image.shape}; expected (H, W, 3)")
    if not np.isfinite(exposure):
        raise ExrError(f"{path}: exposure={exposure}; expected a finite number of stops")
    if not np.all(np.isfinite(image)):
        raise ExrError(f"{path}: the image has {int((~np.isfinite(image)).sum())} NaN/Inf value(s); "
                       f"a display image needs finite radiance")
    scaled = np.clip(image * np.float32(2.0 ** exposure), 0.0, 1.0)
    data = np.round(np.asarray(srgb(scaled)) * 255.0).astype(np.uint8)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    spec.attribute("oiio:ColorSpace", "sRGB")
    for k, v in (attrs or {}).items():
        _header_value(spec, k, v, path)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(path))  # the format from the real suffix, not the temporary name
        if out is None:
            raise ExrError(f"{path}: cannot create a {path.suffix} writer ({oiio.geterror().strip()})")
        ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(data))
        err = out.geterror()
        out.close()
        if not ok:
            raise ExrError(f"{path}: writing failed ({err.strip()})")
    return path


def write_output(path: str | os.PathLike, image: Any, *, exposure: float = 0.0,
                 attrs: Mapping[str, Any] | None = None) -> Path:
    """A denoised image to ``path`` by its suffix: ``.exr`` linear (`write_image`), PNG/JPEG
    tone-mapped sRGB (`write_display`, ``exposure`` in stops); anything else is refused by name."""
    suffix = Path(path).suffix.lower()
    if suffix in DISPLAY_SUFFIXES:
        return write_display(path, image, exposure=exposure, attrs=attrs)
    if suffix != ".exr":
        raise ExrError(f"{path}: unknown output format '{suffix}'; expected .exr (linear HDR) or "
                       f"{'/'.join(DISPLAY_SUFFIXES)} (tone-mapped sRGB, 8 bits)")
    return write_image(path, image, attrs)
