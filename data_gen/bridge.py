"""Mitsuba renders handed to `jaxdenoise` in memory, and its JAX denoisers inside Dr.Jit's AD graph (issue 39).

Two directions, no EXR on the way:

- **Renders to Buffers.** `data_gen.render_frame` renders data_gen's own buffers into `jaxdenoise.Buffers`;
  `buffers_from_tensor` turns the tensor of Mitsuba's ``aov`` integrator (``mi.render(scene)`` with
  ``{"type": "aov", "aovs": "nn:sh_normal,dd:depth,...", "inner": {...}}``) into `Buffers` under the
  same channel names, aliases and checks as a file (`jaxdenoise.io.buffers_from_channels`).
- **A differentiable denoise.** `differentiable(method)` returns a `Denoiser`: a registered JAX method,
  its parameters bound, wrapped with ``drjit.wrap(source="drjit", target="jax")`` so that Dr.Jit code
  calls it on a render (``mi.render(scene, params, integrator=prb)``) and ``dr.backward`` reaches the
  scene parameters through it (Dr.Jit's custom operation calls ``jax.vjp`` of the method's ``apply``).

The colour must come from one of Mitsuba's differentiable integrators (``prb``, ``direct_projective``,
...): data_gen's buffer integrator runs a symbolic ``dr.while_loop`` and accumulates on the host, so
it has no reverse mode. The auxiliary buffers a method reads (albedo, normals, depth, variances) come
from a *detached* pass of data_gen's integrator (`Denoiser.aux`): their dependence on the parameters
is left out of the gradient, a bias that is largest when the parameter is what a buffer records
(an albedo, which the ``albedo`` buffer shows directly), measured in docs/drjit_bridge.md.
`jaxdenoise` itself never imports Mitsuba or Dr.Jit; this module is where they meet.
"""
from __future__ import annotations

import functools
import os
from typing import Any, Iterable, Mapping

import numpy as np

from jaxdenoise.errors import JaxdenoiseError

__all__ = ["Denoiser", "buffers_from_tensor", "differentiable", "tensor_channel_names"]


# --------------------------------------------------------------------------------------------------
# Tensors of Mitsuba's aov integrator
# --------------------------------------------------------------------------------------------------
def tensor_channel_names(integrator, n_channels: int) -> list[str]:
    """The channel names of the ``(H, W, n_channels)`` tensor ``mi.render`` returns with ``integrator``
    (``scene.integrator()`` of a scene whose integrator is ``aov``): ``R G B`` when the integrator has
    an inner integrator, then its AOVs' channels in order (``nn.X nn.Y nn.Z dd.T ...``). Mitsuba
    lists the inner integrator's own channels (``inner.R`` ...) among ``aov_names()`` but does not put
    them in the tensor."""
    aovs = [str(n) for n in integrator.aov_names() if not str(n).startswith("inner.")]
    if n_channels == len(aovs):
        return aovs
    if n_channels == len(aovs) + 3:
        return ["R", "G", "B"] + aovs
    raise JaxdenoiseError(f"a tensor of {n_channels} channel(s) does not fit integrator "
                          f"'{integrator.class_().name() if hasattr(integrator, 'class_') else type(integrator).__name__}' "
                          f"(AOV channels {aovs}, plus R G B with an inner integrator); pass names= explicitly")


def buffers_from_tensor(tensor: Any, names: Iterable[str] | None = None, *, integrator=None, spp: int | None = None,
                        color: Any = None, channels: Mapping[str, str] | None = None, repair: str | None = None,
                        camera_scene=None):
    """`jaxdenoise.Buffers` from a rendered ``(H, W, C)`` tensor (``mi.TensorXf``, NumPy or anything
    ``np.asarray`` takes), without writing a file.

    ``names``: the tensor's channel names (``R G B nn.X nn.Y nn.Z dd.T ...``), or ``integrator``
    (``scene.integrator()``) to take them from an ``aov`` integrator (`tensor_channel_names`).
    Channels are read as a file's are (`jaxdenoise.io.buffers_from_channels`: the contract's names,
    Mitsuba's usual AOV names, ``channels=`` mappings, NaN/negative checks, ``repair``), so the result
    equals reading the same channels from an EXR. ``color``: an ``(H, W, 3)`` radiance image for a
    tensor without ``R G B`` (an ``aov`` integrator without inner integrator). ``spp``: the frame's
    samples per pixel (Mitsuba's tensor does not carry it; methods that read it require it).
    ``camera_scene``: a loaded ``mi.Scene`` whose first sensor's matrices go into the frame
    (`jaxdenoise.view`'s convention, as data_gen's headers)."""
    from jaxdenoise.io import buffers_from_channels

    arr = _numpy(tensor)
    if arr.ndim != 3:
        raise JaxdenoiseError(f"buffers_from_tensor: expected an (H, W, C) tensor, got shape {arr.shape}")
    if names is None:
        if integrator is None:
            raise JaxdenoiseError("buffers_from_tensor: pass names= (one per channel) or integrator= "
                                  "(scene.integrator() of an aov integrator) to name the tensor's channels")
        names = tensor_channel_names(integrator, arr.shape[-1])
    names = [str(n) for n in names]
    if len(names) != arr.shape[-1]:
        raise JaxdenoiseError(f"buffers_from_tensor: {len(names)} name(s) {names} for a tensor of {arr.shape[-1]} channel(s)")
    chans = {n: arr[..., i] for i, n in enumerate(names)}
    if color is not None:
        rgb = _numpy(color)
        if rgb.shape != arr.shape[:2] + (3,):
            raise JaxdenoiseError(f"buffers_from_tensor: color has shape {rgb.shape}; expected {arr.shape[:2] + (3,)}")
        taken = [c for c in ("R", "G", "B") if c in chans]
        if taken:
            raise JaxdenoiseError(f"buffers_from_tensor: color= given but the tensor has channel(s) {taken} too")
        chans.update({c: rgb[..., i] for i, c in enumerate(("R", "G", "B"))})
    attrs: dict[str, Any] = {}
    if camera_scene is not None:
        from .render import camera_matrices

        attrs.update({k: v for k, v in camera_matrices(camera_scene).items() if v is not None})
    buffers, _ = buffers_from_channels(chans, attrs, where="mitsuba tensor", repair=repair, channels=channels, spp=spp)
    return buffers


def _numpy(value: Any) -> np.ndarray:
    if hasattr(value, "numpy") and not isinstance(value, np.ndarray):
        value = value.numpy()
    return np.asarray(value, dtype=np.float32)


# --------------------------------------------------------------------------------------------------
# A differentiable denoise for Dr.Jit
# --------------------------------------------------------------------------------------------------
class Denoiser:
    """A registered JAX method callable from Dr.Jit code, differentiable (reverse and forward mode)
    with respect to every Dr.Jit array it is given (`differentiable` makes one).

    ``den(image, aux)`` returns the denoised ``mi.TensorXf``: ``image`` is the ``(H, W, 3)`` render
    (grad-enabled when it comes from ``mi.render(scene, params, ...)``), ``aux`` a dict of the other
    buffers the method reads (`aux` renders them) and the frame's ``spp``. Dr.Jit arrays in ``aux``
    are differentiated too (a grad-enabled AOV); NumPy arrays and ``spp`` are constants. The method's
    raw ``apply`` runs: the output policy of the API (negatives set to 0) is not applied, since it
    would cut the gradient where it acts.
    """

    def __init__(self, method: str, *, weights: str | os.PathLike | None = None, params: Any = None) -> None:
        from jaxdenoise import compile_cache
        from jaxdenoise.api import resolve
        from jaxdenoise.methods import get, names as method_names

        m = get(method)
        if not m.jittable:
            jax_methods = [n for n in method_names() if get(n).jittable]
            raise JaxdenoiseError(f"method '{m.name}' runs foreign code outside JAX, which has no derivative for "
                                  f"Dr.Jit to call; a differentiable denoise needs a JAX method: {', '.join(jax_methods)}")
        if params is None:
            m, params = resolve(m, weights)
        self.method = m
        self.params = params
        compile_cache.enable()
        self._apply = _jitted_apply(m.module, m.config)

    # -- what it reads ----------------------------------------------------------------------------
    def needs(self) -> frozenset[str]:
        """Every buffer the method reads (``color`` included), as `jaxdenoise` methods define it."""
        return self.method.needs()

    def aux(self, scene, *, spp: int, seed: int = 0, max_depth: int = 8, rr_depth: int = 5,
            samples_per_pass: int | None = None) -> dict[str, Any]:
        """The buffers the method reads besides the colour, from a detached pass of data_gen's
        integrator on the loaded ``scene`` at ``spp`` (its own samples, ``seed``): ``mi.TensorXf``
        per image buffer (``color_var`` and feature variances included where the method reads them:
        ``spp >= 2``), the camera matrices as NumPy and ``spp``. Rendered with gradients suspended:
        their dependence on the scene parameters is not differentiated (the module's docstring)."""
        import drjit as dr
        import mitsuba as mi

        from jaxdenoise.buffers import MATRIX_FIELDS

        from .integrator import FEATURES, PathSettings
        from .render import DEFAULT_SAMPLES_PER_PASS, camera_matrices, render_buffers

        want = self.needs() - {"color", "spp"}
        if spp < 2 and any(f.endswith("_var") for f in want):
            raise JaxdenoiseError(f"method '{self.method.name}' reads variances "
                                  f"{sorted(f for f in want if f.endswith('_var'))}, which need spp >= 2; got spp={spp}")
        if want & {"dx", "dy"}:
            raise JaxdenoiseError(f"method '{self.method.name}' reads gradient buffers (dx, dy), which data_gen "
                                  f"renders with its gradient-domain tracer, not in this detached pass")
        record = [f for f in FEATURES if f in want or f"{f}_var" in want]
        with dr.suspend_grad():
            data = render_buffers(scene, spp=int(spp), seed=int(seed), settings=PathSettings(int(max_depth), int(rr_depth)),
                                  record=record, samples_per_pass=samples_per_pass or DEFAULT_SAMPLES_PER_PASS)
        # A required buffer the pass cannot make is named by the call's check (jaxdenoise's prepare).
        out: dict[str, Any] = {k: mi.TensorXf(np.ascontiguousarray(v)) for k, v in data.items() if k in want}
        cams = camera_matrices(scene)
        out.update({k: cams[k] for k in MATRIX_FIELDS if k in want and cams.get(k) is not None})
        out["spp"] = int(spp)
        return out

    # -- the pure JAX function and its Dr.Jit wrapper -----------------------------------------------
    def jax_fn(self, aux: Mapping[str, Any] | None = None):
        """``f(color, arrays) -> denoised``: the pure JAX function the Dr.Jit wrapper runs, with the
        constants of ``aux`` (NumPy arrays, ``spp``) bound; ``arrays`` holds the rest of ``aux`` as
        JAX arrays. `jax.vjp` of it is what ``dr.backward`` evaluates."""
        from jaxdenoise.buffers import Buffers

        consts = {k: (np.float32(v) if k == "spp" else np.asarray(v, np.float32))
                  for k, v in (aux or {}).items() if not _is_drjit(v)}

        def f(color, arrays):
            return self._apply(self.params, Buffers(color=color, **arrays, **consts))

        return f

    def __call__(self, image: Any, aux: Mapping[str, Any] | None = None):
        import drjit as dr

        from jaxdenoise.buffers import Buffers
        from jaxdenoise.inference import buffers_read, prepare

        aux = dict(aux or {})
        unknown = sorted(set(aux) - set(Buffers.__dataclass_fields__))
        if unknown:
            raise JaxdenoiseError(f"aux: unknown buffer name(s) {unknown}; expected jaxdenoise.Buffers fields")
        if not _is_drjit(image):
            raise JaxdenoiseError(f"image: expected a Dr.Jit tensor (mi.render's result), got {type(image).__name__}")
        # Checked on the detached values, as jaxdenoise.denoise checks a frame: every buffer it needs, finite.
        frame = Buffers(color=_numpy(image), **{k: (np.float32(v) if k == "spp" else _numpy(v)) for k, v in aux.items()})
        prepare(self.method, frame, where="dr.wrap denoise")
        used = set(buffers_read(self.method, frame)) | {"spp"}
        aux = {k: v for k, v in aux.items() if k in used}
        arrays = {k: v for k, v in aux.items() if _is_drjit(v)}
        for k, v in arrays.items():
            if not dr.is_tensor_v(v):
                raise JaxdenoiseError(f"aux['{k}']: expected a Dr.Jit tensor (mi.TensorXf), got {type(v).__name__}")
        return dr.wrap(source="drjit", target="jax")(self.jax_fn(aux))(image, arrays)


@functools.lru_cache(maxsize=32)
def _jitted_apply(module, config):
    """The method's ``apply`` jitted once per module and config, shared by every `Denoiser` of it."""
    import jax

    return jax.jit(lambda params, buffers: module.apply(params, buffers, config))


def _is_drjit(value: Any) -> bool:
    import drjit as dr

    return dr.is_array_v(value)


def differentiable(method: str, *, weights: str | os.PathLike | None = None, params: Any = None) -> Denoiser:
    """A registered JAX method as a `Denoiser` Dr.Jit code can call and differentiate through (its
    shipped weights, or ``weights`` / ``params``). Foreign methods (``oidn``) are refused: their code
    has no derivative. Needs an AD variant of Mitsuba (``llvm_ad_rgb``; `data_gen.setup_mitsuba`)."""
    return Denoiser(method, weights=weights, params=params)
