"""`Buffers`: the frozen pytree of per-pixel inputs every method reads (docs/architecture.md "Data contract").

Arrays are float32, height x width x channels; a batch adds a leading axis and a sequence a
leading time axis, so validation compares every dimension but the last across fields. A buffer
the scene does not have is ``None`` (it is then not a leaf of the pytree, so ``jit`` specializes on
which buffers are present).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Iterable, Mapping

import jax
import numpy as np
from .errors import JaxdenoiseError

# field -> EXR channel names, in order (docs/architecture.md "Data contract"). Feature variances are one
# channel per layer (the mean of the per-channel variances of the pixel mean).
CHANNELS: dict[str, tuple[str, ...]] = {
    "color": ("R", "G", "B"),
    "color_var": ("var.R", "var.G", "var.B"),
    "albedo": ("albedo.R", "albedo.G", "albedo.B"),
    "albedo_var": ("albedo.var",),
    "albedo2": ("albedo2.R", "albedo2.G", "albedo2.B"),
    "albedo2_var": ("albedo2.var",),
    "normal": ("N.X", "N.Y", "N.Z"),
    "normal_var": ("N.var",),
    "position": ("P.X", "P.Y", "P.Z"),
    "position_var": ("P.var",),
    "depth": ("Z",),
    "depth_var": ("Z.var",),
    "visibility": ("vis",),
    "visibility_var": ("vis.var",),
    "roughness": ("rough",),
    "roughness_var": ("rough.var",),
    "dx": ("dx.R", "dx.G", "dx.B"),
    "dy": ("dy.R", "dy.G", "dy.B"),
    "emission": ("emission.R", "emission.G", "emission.B"),
    "spp_map": ("spp",),
}
IMAGE_FIELDS: tuple[str, ...] = tuple(CHANNELS)
# Features whose variance is a separate field (Kalantari 2015 Eq. 12 uses a per-feature variance).
FEATURES: tuple[str, ...] = ("albedo", "albedo2", "normal", "position", "depth", "visibility", "roughness")
# Per-frame metadata: travels with the frame through every path (`Buffers.only`, `stack`, batches,
# sequences) whatever a method reads, so no selection of buffers can drop it (docs/architecture.md "Methods").
METADATA_FIELDS: tuple[str, ...] = ("spp", "world_to_camera", "world_to_ndc")
# Metadata that is a 4x4 matrix per frame (`jaxdenoise.view` documents the conventions).
MATRIX_FIELDS: tuple[str, ...] = ("world_to_camera", "world_to_ndc")
ALL_FIELDS: tuple[str, ...] = IMAGE_FIELDS + METADATA_FIELDS
# The per-pixel sample count of an adaptively sampled frame (EXR layer ``spp``; the header's ``spp`` is
# its mean). Like the header's count it travels with the frame: `Buffers.only` never drops it.
SAMPLE_COUNT_FIELD = "spp_map"
# The directly seen emission that a gradient frame's ``dx``/``dy`` leave out (Kettunen et al. 2015's tracer;
# `data_gen.gradient.render_gradients`): present exactly when they do, so it travels with them (`Buffers.only`)
# and every reconstruction from them solves for ``color - emission`` and adds it back.
EMISSION_FIELD = "emission"
# How a gradient frame's dx, dy treat that emission (the EXR header's ``gradient_emission``): left out
# (the layer present) or included (no layer; a frame without the attribute reads so).
GRADIENT_EMISSION_MODES: tuple[str, ...] = ("separate", "included")
# What a gradient frame's colour is (the header's ``primal``): the plain path-traced base, or the G-PT
# primal (Kettunen et al. 2015's MIS combination of the base and offset paths: data_gen --primal gpt).
PRIMALS: tuple[str, ...] = ("base", "gpt")
GRADIENT_FIELDS: tuple[str, ...] = ("dx", "dy")
# The OpenEXR standard header attribute that carries each matrix (`jaxdenoise.io` reads and writes them).
MATRIX_HEADERS: dict[str, str] = {"world_to_camera": "worldToCamera", "world_to_ndc": "worldToNDC"}


class BuffersError(JaxdenoiseError):
    """A `Buffers` is malformed or lacks what a method needs."""


@dataclasses.dataclass(frozen=True)
class Buffers:
    """Per-pixel inputs of one frame (or a batch / sequence of frames).

    Fields (``None`` when absent): ``color`` (linear HDR radiance, the only required one),
    ``color_var`` (variance of the pixel mean), ``albedo`` / ``albedo2`` (first / second non-specular
    hit texture value), ``normal`` (world-space shading normal in [-1, 1]), ``position`` (world),
    ``depth`` (camera distance), ``visibility`` (direct-light visibility fraction), ``roughness``,
    ``dx`` / ``dy`` (``I[y, x+1] - I[y, x]`` and ``I[y+1, x] - I[y, x]``), ``emission`` (the directly
    seen emission, part of ``color``, where ``dx``/``dy`` leave it out: they are then the differences of
    ``color - emission``), ``<feature>_var`` (one
    channel, variance of the feature's pixel mean), ``spp_map`` (one channel, the samples each pixel
    got where sampling was adaptive, `data_gen.adaptive`; None where every pixel got ``spp``) and the
    frame's metadata: ``spp`` (samples per pixel, scalar or one per frame; the mean of ``spp_map``),
    ``world_to_camera`` and ``world_to_ndc`` (the camera, 4x4 matrices acting on column vectors,
    ``(4, 4)`` or one per frame; OpenEXR's ``worldToCamera`` / ``worldToNDC`` header attributes; conventions and the view-space quantities derived from them in
    `jaxdenoise.view`).
    """

    color: Any
    color_var: Any = None
    albedo: Any = None
    albedo_var: Any = None
    albedo2: Any = None
    albedo2_var: Any = None
    normal: Any = None
    normal_var: Any = None
    position: Any = None
    position_var: Any = None
    depth: Any = None
    depth_var: Any = None
    visibility: Any = None
    visibility_var: Any = None
    roughness: Any = None
    roughness_var: Any = None
    dx: Any = None
    dy: Any = None
    emission: Any = None
    spp_map: Any = None
    spp: Any = None
    world_to_camera: Any = None
    world_to_ndc: Any = None

    def __post_init__(self) -> None:
        # Only check concrete shapes; JAX's tree utilities may rebuild the class with placeholders.
        if all(hasattr(v, "shape") for v in self._present_values()):
            self.validate()

    def _present_values(self) -> list:
        return [getattr(self, f) for f in ALL_FIELDS if getattr(self, f) is not None]

    # -- validation --------------------------------------------------------------------------------
    def validate(self, required: Iterable[str] = ("color",), *, where: str = "Buffers") -> "Buffers":
        """Check channel counts, matching pixel grids, and that ``required`` buffers are present.

        Raises `BuffersError` naming the offending field (and ``where``, e.g. a file name).
        """
        missing = sorted(f for f in required if f not in ALL_FIELDS or getattr(self, f) is None)
        if missing:
            unknown = [f for f in missing if f not in ALL_FIELDS]
            if unknown:
                raise BuffersError(f"{where}: unknown buffer name(s) {unknown}; known: {list(ALL_FIELDS)}")
            have = sorted(self.present())
            raise BuffersError(f"{where}: missing required buffer(s) {missing} (present: {have})")
        grid = None
        grid_field = None
        for name in IMAGE_FIELDS:
            value = getattr(self, name)
            if value is None:
                continue
            shape = tuple(value.shape)
            want = len(CHANNELS[name])
            if len(shape) < 3:
                raise BuffersError(f"{where}: buffer '{name}' has shape {shape}; expected (..., H, W, {want})")
            if shape[-1] != want:
                raise BuffersError(
                    f"{where}: buffer '{name}' has {shape[-1]} channel(s); expected {want} {CHANNELS[name]}")
            if grid is None:
                grid, grid_field = shape[:-1], name
            elif shape[:-1] != grid:
                raise BuffersError(
                    f"{where}: buffer '{name}' has pixel grid {shape[:-1]} but '{grid_field}' has {grid}")
        if self.spp is not None and hasattr(self.spp, "shape") and grid is not None:
            lead = grid[:-2]
            if tuple(self.spp.shape) not in ((), tuple(lead)):
                raise BuffersError(f"{where}: 'spp' has shape {tuple(self.spp.shape)}; expected () or {lead}")
        for name in MATRIX_FIELDS:
            m = getattr(self, name)
            if m is None or not hasattr(m, "shape") or grid is None:
                continue
            lead = tuple(grid[:-2])
            if tuple(m.shape) not in ((4, 4), lead + (4, 4)):
                raise BuffersError(f"{where}: '{name}' has shape {tuple(m.shape)}; expected (4, 4) or {lead + (4, 4)}")
        return self

    def check_needs(self, needs: Iterable[str], method: str, *, where: str | None = None) -> None:
        """Raise a clear error when ``method`` needs buffers (or metadata such as ``spp``) this frame
        lacks; ``where`` (e.g. the file name) prefixes the message."""
        missing = sorted(f for f in needs if getattr(self, f, None) is None)
        if not missing:
            return
        prefix = f"{where}: " if where else ""
        meta = [f for f in missing if f in METADATA_FIELDS]
        bufs = [f for f in missing if f not in METADATA_FIELDS]
        parts = []
        if bufs:
            parts.append(f"buffer(s) {bufs}")
        if meta:
            hows = []
            if "spp" in meta:
                hows.append("the sample count: the integer 'spp' header attribute, which data_gen writes; for a file "
                            "without one read_buffers(..., spp=N), CLI --spp N, or Buffers(spp=...)")
            cams = [f for f in meta if f in MATRIX_FIELDS]
            if cams:
                names = " and ".join(f"'{MATRIX_HEADERS[f]}'" for f in cams)
                hows.append(f"the camera: the 4x4 EXR header matrix attribute(s) {names}, which data_gen writes "
                            f"(Mitsuba's own films carry none), or Buffers({', '.join(f + '=...' for f in cams)})")
            parts.append(f"the frame's {meta} ({'; '.join(hows)}; never guessed)")
        raise BuffersError(
            f"{prefix}method '{method}' needs {' and '.join(parts)}, which this input lacks "
            f"(present: {sorted(self.present())}); render them with `python -m data_gen render SCENE "
            f"--methods {method}` or pick another method")

    # -- conveniences ------------------------------------------------------------------------------
    def present(self) -> frozenset[str]:
        return frozenset(f for f in ALL_FIELDS if getattr(self, f) is not None)

    @property
    def shape(self) -> tuple[int, ...]:
        """Pixel grid (leading batch/time axes included, channels excluded)."""
        return tuple(self.color.shape[:-1])

    def replace(self, **changes: Any) -> "Buffers":
        return dataclasses.replace(self, **changes)

    def only(self, names: Iterable[str]) -> "Buffers":
        """A copy keeping ``color``, the given buffers and the frame's sample counts and metadata
        (``spp``, ``spp_map``: never dropped, whatever ``names`` says), with ``dx``/``dy`` the
        ``emission`` they leave out, every other buffer set to ``None``."""
        keep = set(names) | {"color", SAMPLE_COUNT_FIELD} | set(METADATA_FIELDS)
        if keep & set(GRADIENT_FIELDS):
            keep.add(EMISSION_FIELD)
        return Buffers(**{f: (getattr(self, f) if f in keep else None) for f in ALL_FIELDS})

    def astype(self, dtype: Any) -> "Buffers":
        return jax.tree_util.tree_map(lambda a: a.astype(dtype) if hasattr(a, "astype") else a, self)

    def to_numpy(self) -> "Buffers":
        return jax.tree_util.tree_map(np.asarray, self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Buffers":
        unknown = sorted(set(data) - set(ALL_FIELDS))
        if unknown:
            raise BuffersError(f"unknown buffer name(s) {unknown}; known: {list(ALL_FIELDS)}")
        return cls(**dict(data))

    def to_dict(self) -> dict[str, Any]:
        return {f: getattr(self, f) for f in ALL_FIELDS if getattr(self, f) is not None}


jax.tree_util.register_dataclass(Buffers, data_fields=list(ALL_FIELDS), meta_fields=[])


def with_variances(fields: Iterable[str]) -> frozenset[str]:
    """The given fields plus their variance buffers (``color`` -> ``color_var``, ``normal`` -> ``normal_var``)."""
    out = set(fields)
    for f in list(out):
        if f"{f}_var" in CHANNELS:
            out.add(f"{f}_var")
    return frozenset(out)


def stack(frames: Iterable[Buffers]) -> Buffers:
    """Stack frames with identical present buffers along a new leading axis."""
    frames = list(frames)
    if not frames:
        raise BuffersError("stack: no frames given")
    first = frames[0].present()
    for i, f in enumerate(frames[1:], 1):
        if f.present() != first:
            raise BuffersError(
                f"stack: frame {i} has buffers {sorted(f.present())} but frame 0 has {sorted(first)}")
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *frames)


def map_frames(fn: Any, buffers: Buffers) -> Any:
    """``fn(frame) -> (H, W, C)`` over every frame of ``buffers``: a single ``(H, W, C)`` frame goes
    straight to ``fn``; leading axes are a batch of independent frames (docs/architecture.md "Methods"), run one
    frame at a time with ``jax.lax.map`` (the memory of one frame's intermediates, one compiled
    body). A scalar ``spp`` (or a single camera matrix) applies to every frame of the batch."""
    lead = tuple(np.shape(buffers.color)[:-3])
    if not lead:
        return fn(buffers)
    n = int(np.prod(lead))
    fields = {k: v for k, v in buffers.to_dict().items() if k not in METADATA_FIELDS}
    flat = {k: jax.numpy.reshape(v, (n,) + tuple(np.shape(v)[len(lead):])) for k, v in fields.items()}
    for k in METADATA_FIELDS:
        v = getattr(buffers, k)
        if v is not None:
            tail = (4, 4) if k in MATRIX_FIELDS else ()
            flat[k] = jax.numpy.reshape(jax.numpy.broadcast_to(jax.numpy.asarray(v), lead + tail), (n,) + tail)
    out = jax.lax.map(lambda d: fn(Buffers(**d)), flat)
    return out.reshape(lead + tuple(out.shape[1:]))
