"""`oidn`: Intel Open Image Denoise through `pyoidn`, the peer a user would otherwise pick.

Not JAX (``JITTABLE = False``): it runs OIDN's pretrained "RT" filter on the CPU with ``hdr=True``,
passing albedo and normal when the frame has them (OIDN needs albedo to use normals). Install with
``pip install 'jaxdenoise[oidn]'`` (from a clone: ``pip install -e '.[oidn]'``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..buffers import Buffers
from ..errors import MissingDependency

JITTABLE = False


@dataclasses.dataclass(frozen=True)
class Config:
    quality: str = "high"        # OIDN quality preset: high | balanced | fast
    use_albedo: bool = True
    use_normal: bool = True
    clean_aux: bool = False      # our aux buffers are Monte Carlo estimates: let OIDN prefilter them


def requirements() -> str | None:
    try:
        import pyoidn  # noqa: F401
    except ImportError as e:
        return (f"method 'oidn' needs the pyoidn package (pip install 'jaxdenoise[oidn]'; from a clone: "
                f"pip install -e '.[oidn]'): {e}")
    return None


def needs(config: Config) -> frozenset[str]:
    out = {"color"}
    if config.use_albedo:
        out.add("albedo")
        if config.use_normal:
            out.add("normal")
    return frozenset(out)


def required(config: Config) -> frozenset[str]:
    """OIDN runs on colour alone; albedo and normal improve it when the frame has them."""
    return frozenset({"color"})


def init(key, config: Config) -> dict:
    return {}


def _aux(buffers: Buffers, config: Config) -> tuple:
    """The auxiliary images OIDN will use (albedo clipped to its documented [0, 1] range)."""
    albedo = normal = None
    if config.use_albedo and buffers.albedo is not None:
        albedo = np.clip(np.asarray(buffers.albedo, np.float32), 0.0, 1.0)
        if config.use_normal and buffers.normal is not None:
            normal = np.asarray(buffers.normal, np.float32)
    return albedo, normal


def apply(params: dict, buffers: Buffers, config: Config):
    why = requirements()
    if why:
        raise MissingDependency(why)
    import pyoidn

    color = np.asarray(buffers.color, np.float32)
    albedo, normal = _aux(buffers, config)
    h, w, c = color.shape[-3:]
    frames = [a.reshape(-1, h, w, c) if a is not None else None for a in (color, albedo, normal)]
    out = [
        pyoidn.denoise(np.ascontiguousarray(frames[0][i]),
                       None if frames[1] is None else np.ascontiguousarray(frames[1][i]),
                       None if frames[2] is None else np.ascontiguousarray(frames[2][i]),
                       hdr=True, clean_aux=config.clean_aux, quality=config.quality)
        for i in range(frames[0].shape[0])  # batches / sequences: frame by frame
    ]
    return np.stack(out).reshape(color.shape)
