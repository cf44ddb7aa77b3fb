"""View-space quantities from a frame's camera: the one place that derives them.

**Conventions.** A frame's camera travels as metadata of `jaxdenoise.Buffers` (``world_to_camera``,
``world_to_ndc``), read from and written to OpenEXR's standard ``worldToCamera`` / ``worldToNDC``
header attributes by `jaxdenoise.io` (data_gen writes them for every render, `data_gen.render.
camera_matrices`). Both are 4x4 matrices acting on **column** vectors, ``p_cam = M @ [x, y, z, 1]``
(OpenEXR stores the transpose: it multiplies row vectors). Camera space is OpenEXR's: origin at the
camera, +x to the image's right, +y up, +z along the viewing direction (left-handed). NDC: ``x, y``
in [-1, 1] from the left to the right edge and from the bottom to the top edge of the image after
the division by ``w``; ``z`` = ``1 - near / z_cam``.

**Derived quantities** (Chaitanya et al. 2017 Sec. 4.1 feed the view-space shading normal and the
linear depth to their network):

- `view_normals`: the world-space shading normal in camera space (the inverse transpose of the
  camera rotation, renormalized); pixels without a hit (normal 0, data_gen's convention) stay 0;
- `linear_depth`: the distance along the view axis, ``z_cam`` of the world position (not the
  Euclidean camera distance of the ``depth`` buffer); pixels without a hit are 0.
"""
from __future__ import annotations

from typing import Any

import jax.numpy as jnp
from .errors import JaxdenoiseError

__all__ = ["to_camera", "view_normals", "linear_depth", "has_hit"]


def _matrix(m: Any, lead: tuple[int, ...]) -> jnp.ndarray:
    """``(4, 4)`` or one matrix per frame, broadcast to ``lead + (1, 1, 4, 4)`` against (..., H, W, C)."""
    m = jnp.asarray(m, jnp.float32)
    if m.shape[-2:] != (4, 4):
        raise JaxdenoiseError(f"camera matrix has shape {tuple(m.shape)}; expected (..., 4, 4)")
    return m.reshape(m.shape[:-2] + (1, 1, 4, 4)) if m.ndim > 2 else m


def has_hit(normal: Any) -> jnp.ndarray:
    """``(..., H, W, 1)`` mask of pixels whose primary ray hit a surface (non-zero shading normal)."""
    return jnp.sum(jnp.square(jnp.asarray(normal, jnp.float32)), axis=-1, keepdims=True) > 0


def to_camera(points: Any, world_to_camera: Any) -> jnp.ndarray:
    """World-space points ``(..., H, W, 3)`` in camera space."""
    p = jnp.asarray(points, jnp.float32)
    m = _matrix(world_to_camera, p.shape[:-3])
    return jnp.einsum("...ij,...j->...i", m[..., :3, :3], p) + m[..., :3, 3]


def view_normals(normal: Any, world_to_camera: Any) -> jnp.ndarray:
    """World-space normals ``(..., H, W, 3)`` in camera space, unit length (0 where there is no hit)."""
    n = jnp.asarray(normal, jnp.float32)
    m = _matrix(world_to_camera, n.shape[:-3])
    r = m[..., :3, :3]
    it = jnp.swapaxes(jnp.linalg.inv(r), -1, -2)  # normals transform by the inverse transpose
    v = jnp.einsum("...ij,...j->...i", it, n)
    norm = jnp.sqrt(jnp.sum(jnp.square(v), axis=-1, keepdims=True))
    return jnp.where(has_hit(n) & (norm > 0), v / jnp.where(norm > 0, norm, 1.0), 0.0)


def linear_depth(position: Any, normal: Any, world_to_camera: Any) -> jnp.ndarray:
    """``(..., H, W, 1)`` view-axis depth ``z_cam`` of the world position (0 where there is no hit)."""
    z = to_camera(position, world_to_camera)[..., 2:3]
    return jnp.where(has_hit(normal), z, 0.0)
