"""Write every texture, environment map and mesh the scene library uses (``data_gen/library``).

    python -m data_gen.library.make_assets            # rewrites data_gen/library/assets/
    python -m data_gen.library.make_assets --out DIR  # somewhere else (the test compares the two)

Deterministic: NumPy only (fixed seeds, float64 arithmetic), written through OpenImageIO with fixed
header values (EXR ``DateTime`` is pinned, which OpenImageIO would otherwise stamp with the clock),
so a run reproduces the committed files byte for byte on the same library versions; across NumPy /
zlib versions the pixel values agree within one 8-bit step (``tests/test_library.py`` checks).

What it writes (``assets/``):

- ``textures/*.png``: 8-bit sRGB albedo textures (Mitsuba's ``bitmap`` converts sRGB to linear),
  values kept in [0.03, 0.85] after linearization so no surface is a perfect absorber or reflector;
- ``envmaps/*.exr``: latitude-longitude skies (half float, linear), each with a small, very bright
  sun disk (the hot spot that makes environment lighting hard for a denoiser);
- ``meshes/*.ply``: binary PLY meshes (float32 positions and vertex normals, int32 triangles):
  surfaces of revolution (closed, outward normals: safe for dielectrics), a torus knot tube, a
  heightfield water surface, a wire bird cage and a cloud of leaves.

Mitsuba's lat-long mapping (checked in the tests): pixel column u in [0, 1) and row v in [0, 1)
(v = 0 at the top) map to the direction ``(sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi))``
with ``phi = 2 pi u`` and ``theta = pi v``; `sky_direction` inverts it, so a sun is placed by its
direction in scene space.
"""
from __future__ import annotations

import argparse
import math
import struct
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "assets"
_DATETIME = "2000:01:01 00:00:00"  # pinned: OpenImageIO stamps EXR files with the clock otherwise

__all__ = ["DEFAULT_OUT", "main", "sky_direction", "write_all"]


# --------------------------------------------------------------------------------------------------
# Noise and colour helpers
# --------------------------------------------------------------------------------------------------
def _value_noise(rng: np.random.Generator, h: int, w: int, cells_y: int, cells_x: int) -> np.ndarray:
    """Tileable smooth value noise in [0, 1] (a random lattice, smoothstep-interpolated, wrapping)."""
    g = rng.random((cells_y, cells_x))
    ty = np.arange(h) * cells_y / h
    tx = np.arange(w) * cells_x / w
    iy, ix = np.floor(ty).astype(int), np.floor(tx).astype(int)
    fy, fx = ty - iy, tx - ix
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    iy1, ix1 = (iy + 1) % cells_y, (ix + 1) % cells_x
    a = g[iy][:, ix] * (1 - fx) + g[iy][:, ix1] * fx
    b = g[iy1][:, ix] * (1 - fx) + g[iy1][:, ix1] * fx
    return a * (1 - fy)[:, None] + b * fy[:, None]


def _fbm(rng: np.random.Generator, h: int, w: int, base: int = 4, octaves: int = 4) -> np.ndarray:
    """Fractal sum of tileable value noise, normalized to [0, 1]."""
    out = np.zeros((h, w))
    amp, total = 1.0, 0.0
    for k in range(octaves):
        c = base * 2 ** k
        out += amp * _value_noise(rng, h, w, c, c)
        total += amp
        amp *= 0.5
    out /= total
    return (out - out.min()) / max(out.max() - out.min(), 1e-12)


def _rgb(hexcode: str) -> np.ndarray:
    """A linear RGB colour from an sRGB hex code (so the palette below reads like a paint chart)."""
    c = np.array([int(hexcode[i:i + 2], 16) / 255.0 for i in (0, 2, 4)])
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, np.float64)[..., None]
    return a * (1 - t) + b * t


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(y, x) pixel-centre coordinates in [0, 1) of an n x n image."""
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n
    return y, x


# --------------------------------------------------------------------------------------------------
# Textures (linear RGB float64, HWC; written as 8-bit sRGB PNG)
# --------------------------------------------------------------------------------------------------
def tex_wood(n: int = 256) -> np.ndarray:
    """Long-grain wood: distorted growth rings along the texture's v axis, fine fibres."""
    rng = np.random.default_rng(101)
    y, x = _grid(n)
    warp = _fbm(rng, n, n, 2, 3)
    rings = np.sin(2 * np.pi * (6 * x + 1.5 * warp + 0.4 * np.sin(2 * np.pi * y)))
    fibre = _value_noise(rng, n, n, 2, 64)
    t = np.clip(0.5 + 0.35 * rings + 0.25 * (fibre - 0.5), 0, 1) ** 1.5
    return _mix(_rgb("b07a48"), _rgb("6b3f1f"), t)


def tex_planks(n: int = 256) -> np.ndarray:
    """Floor planks: 4 planks across, staggered butt joints, per-plank tint, dark seams."""
    rng = np.random.default_rng(102)
    y, x = _grid(n)
    plank = np.floor(x * 4).astype(int)
    offset = rng.random(4)[plank]
    seg = np.floor(y * 2 + offset).astype(int)
    tint = rng.uniform(0.8, 1.15, (4, 3))[plank, :] * rng.uniform(0.9, 1.1, (4, 3, 1))[plank, seg % 3, :]
    warp = _fbm(rng, n, n, 4, 3)
    grain = np.sin(2 * np.pi * (x * 4 * 5 + 2 * warp))
    base = _mix(_rgb("c49a6c"), _rgb("8a5a32"), np.clip(0.5 + 0.4 * grain, 0, 1)) * tint
    seam = (np.minimum((x * 4) % 1, 1 - (x * 4) % 1) < 0.015) | (np.minimum((y * 2 + offset) % 1, 1 - (y * 2 + offset) % 1) < 0.008)
    return np.where(seam[..., None], _rgb("3a2414"), base)


def tex_tiles(n: int = 256) -> np.ndarray:
    """Glazed wall tiles (4 x 4 per texture), slight per-tile tint, grey grout."""
    rng = np.random.default_rng(103)
    y, x = _grid(n)
    ty, tx = np.floor(y * 4).astype(int), np.floor(x * 4).astype(int)
    tint = rng.uniform(0.93, 1.0, (4, 4, 1))[ty, tx] * np.array([1.0, 0.99, 0.96])
    gy, gx = (y * 4) % 1, (x * 4) % 1
    grout = (np.minimum(gx, 1 - gx) < 0.025) | (np.minimum(gy, 1 - gy) < 0.025)
    base = _rgb("e9e4da") * tint
    return np.where(grout[..., None], _rgb("8d8a84"), base)


def tex_marble(n: int = 256) -> np.ndarray:
    """White marble with grey veins (turbulent sine)."""
    rng = np.random.default_rng(104)
    y, x = _grid(n)
    turb = _fbm(rng, n, n, 3, 5)
    v = np.abs(np.sin(2 * np.pi * (x + 0.6 * y + 2.5 * turb)))
    vein = np.clip(1 - v, 0, 1) ** 6
    cloud = _fbm(rng, n, n, 8, 3)
    base = _mix(_rgb("ece9e4"), _rgb("d6d2cb"), cloud)
    return _mix(base, _rgb("5e5d60"), 0.85 * vein)


def tex_floor_tiles(n: int = 256) -> np.ndarray:
    """Corridor floor: a 2 x 2 checker of cream and dark green tiles with grout and wear."""
    rng = np.random.default_rng(105)
    y, x = _grid(n)
    chk = (np.floor(x * 2) + np.floor(y * 2)) % 2
    wear = _fbm(rng, n, n, 8, 3)
    base = _mix(_rgb("d9cfb8"), _rgb("2f5d4a"), chk) * (0.9 + 0.15 * wear)[..., None]
    gy, gx = (y * 2) % 1, (x * 2) % 1
    grout = (np.minimum(gx, 1 - gx) < 0.012) | (np.minimum(gy, 1 - gy) < 0.012)
    return np.where(grout[..., None], _rgb("55534f"), base)


def tex_brick(n: int = 256) -> np.ndarray:
    """Running-bond brick: 8 courses, 4 bricks per course, mortar joints, per-brick colour."""
    rng = np.random.default_rng(106)
    y, x = _grid(n)
    row = np.floor(y * 8).astype(int)
    xs = x * 4 + 0.5 * (row % 2)
    col = np.floor(xs).astype(int) % 4
    tone = rng.uniform(0, 1, (8, 4))[row, col]
    base = _mix(_rgb("9c4a33"), _rgb("6e3424"), tone) * (0.85 + 0.3 * _fbm(rng, n, n, 16, 2))[..., None]
    my, mx = (y * 8) % 1, xs % 1
    mortar = (np.minimum(my, 1 - my) < 0.06) | (np.minimum(mx, 1 - mx) < 0.03)
    return np.where(mortar[..., None], _rgb("b8b0a2"), base)


def tex_ground(n: int = 256) -> np.ndarray:
    """Grass and bare earth (two-scale noise)."""
    rng = np.random.default_rng(107)
    patches = _fbm(rng, n, n, 3, 4)
    blades = _value_noise(rng, n, n, 96, 96)
    grass = _mix(_rgb("4d6b2a"), _rgb("7b9442"), blades)
    return _mix(grass, _rgb("7a6148"), np.clip((patches - 0.55) * 4, 0, 1))


def tex_cobbles(n: int = 256) -> np.ndarray:
    """Paving stones: a tileable Voronoi pattern (48 cells), dark joints, per-stone tint."""
    rng = np.random.default_rng(108)
    pts = rng.random((48, 2))
    y, x = _grid(n)
    d1 = np.full((n, n), np.inf)
    d2 = np.full((n, n), np.inf)
    owner = np.zeros((n, n), int)
    for k, (py, px) in enumerate(pts):
        for oy in (-1, 0, 1):
            for ox in (-1, 0, 1):
                d = np.hypot(y - py - oy, x - px - ox)
                closer = d < d1
                d2 = np.where(closer, d1, np.minimum(d2, d))
                owner = np.where(closer, k, owner)
                d1 = np.minimum(d1, d)
    tone = rng.uniform(0, 1, 48)[owner]
    base = _mix(_rgb("9a948a"), _rgb("6c665e"), tone) * (0.85 + 0.25 * _fbm(rng, n, n, 16, 2))[..., None]
    joint = np.clip((d2 - d1) / 0.02, 0, 1)
    return _mix(_rgb("3b3833"), base, joint)


def tex_fabric(n: int = 256) -> np.ndarray:
    """Tartan tablecloth: crossing bands of red, cream and navy with a twill ripple."""
    y, x = _grid(n)

    def bands(t):
        return (np.sin(2 * np.pi * 4 * t) > 0.3).astype(float), (np.sin(2 * np.pi * 16 * t + 1) > 0.7).astype(float)

    wide_x, thin_x = bands(x)
    wide_y, thin_y = bands(y)
    base = _mix(_rgb("e8dcc4"), _rgb("9e2a2b"), 0.5 * (wide_x + wide_y))
    base = _mix(base, _rgb("1f2a4a"), 0.5 * (thin_x + thin_y))
    twill = 0.92 + 0.08 * np.sin(2 * np.pi * 64 * (x + y))
    return base * twill[..., None]


def tex_wallpaper(n: int = 256) -> np.ndarray:
    """Striped wallpaper with a small dot motif."""
    y, x = _grid(n)
    stripe = (np.floor(x * 8) % 2).astype(float)
    base = _mix(_rgb("d8cfae"), _rgb("bfb58f"), stripe)
    cy, cx = (y * 8) % 1 - 0.5, (x * 8) % 1 - 0.5
    dot = (np.hypot(cy, cx) < 0.12) & (stripe == 0)
    return np.where(dot[..., None], _rgb("7a5a3c"), base)


def tex_pool_tiles(n: int = 256) -> np.ndarray:
    """Pool mosaic: 16 x 16 small tiles in three blues, white grout."""
    rng = np.random.default_rng(109)
    y, x = _grid(n)
    ty, tx = np.floor(y * 16).astype(int), np.floor(x * 16).astype(int)
    palette = np.stack([_rgb("2f7fb3"), _rgb("4ea3cf"), _rgb("1d5f8f")])
    base = palette[rng.integers(0, 3, (16, 16))[ty, tx]] * rng.uniform(0.9, 1.1, (16, 16, 1))[ty, tx]
    gy, gx = (y * 16) % 1, (x * 16) % 1
    grout = (np.minimum(gx, 1 - gx) < 0.06) | (np.minimum(gy, 1 - gy) < 0.06)
    return np.where(grout[..., None], _rgb("d8dde0"), base)


def tex_concrete(n: int = 256) -> np.ndarray:
    """Grey concrete with speckles and stains."""
    rng = np.random.default_rng(110)
    stain = _fbm(rng, n, n, 4, 4)
    speck = _value_noise(rng, n, n, 128, 128)
    base = _mix(_rgb("a3a19c"), _rgb("7c7a76"), stain)
    return base * (0.92 + 0.16 * (speck > 0.8))[..., None]


def tex_painting(n: int = 256) -> np.ndarray:
    """An abstract canvas: coloured blocks with black bars and brush noise."""
    rng = np.random.default_rng(111)
    y, x = _grid(n)
    img = np.ones((n, n, 3)) * _rgb("efe9dc")
    for col, (y0, y1, x0, x1) in zip(("c8322b", "2a54a0", "e3b632", "2f8f5b", "c8322b"),
                                     ((0.05, 0.45, 0.05, 0.55), (0.55, 0.95, 0.6, 0.95), (0.6, 0.9, 0.1, 0.4),
                                      (0.1, 0.35, 0.65, 0.9), (0.45, 0.55, 0.3, 0.7))):
        m = (y >= y0) & (y < y1) & (x >= x0) & (x < x1)
        img[m] = _rgb(col)
    bars = (np.abs(x - 0.58) < 0.012) | (np.abs(y - 0.5) < 0.012) | (np.abs(x - 0.05) < 0.008)
    img[bars] = _rgb("1a1a1a")
    return img * (0.9 + 0.2 * _fbm(rng, n, n, 32, 2))[..., None]


def tex_pegboard(n: int = 256) -> np.ndarray:
    """Hardboard with a grid of dark holes (a texture, not geometry)."""
    rng = np.random.default_rng(112)
    y, x = _grid(n)
    cy, cx = (y * 12) % 1 - 0.5, (x * 12) % 1 - 0.5
    hole = np.hypot(cy, cx) < 0.14
    base = _rgb("a07850") * (0.9 + 0.2 * _fbm(rng, n, n, 8, 3))[..., None]
    return np.where(hole[..., None], _rgb("1c140d"), base)


TEXTURES = {
    "wood": tex_wood, "planks": tex_planks, "tiles": tex_tiles, "marble": tex_marble,
    "floor_tiles": tex_floor_tiles, "brick": tex_brick, "ground": tex_ground, "cobbles": tex_cobbles,
    "fabric": tex_fabric, "wallpaper": tex_wallpaper, "pool_tiles": tex_pool_tiles, "concrete": tex_concrete,
    "painting": tex_painting, "pegboard": tex_pegboard,
}


# --------------------------------------------------------------------------------------------------
# Environment maps (linear float, lat-long)
# --------------------------------------------------------------------------------------------------
def sky_direction(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Scene-space unit direction of lat-long texture coordinates (u, v) in [0, 1) (module docstring)."""
    phi, theta = 2 * np.pi * u, np.pi * v
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)


def _sky(width: int, *, seed: int, zenith: str, horizon: str, ground: str, sun_dir, sun_radiance: float,
         sun_color: str, sun_radius_deg: float, clouds: float, glow: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h = width // 2
    v, u = (np.mgrid[0:h, 0:width] + 0.5) / np.array([h, width])[:, None, None]
    d = sky_direction(u, v)
    up = d[..., 1]
    t = np.clip(up, 0, 1) ** 0.5
    sky = _mix(_rgb(horizon), _rgb(zenith), t)
    sun = np.asarray(sun_dir, np.float64)
    sun = sun / np.linalg.norm(sun)
    cosang = np.clip(d @ sun, -1, 1)
    ang = np.degrees(np.arccos(cosang))
    sky = sky + glow * _rgb(sun_color) * np.exp(-ang / 12.0)[..., None]  # forward scattering halo
    cl = _value_noise(rng, h, width, 6, 24) * 0.6 + _value_noise(rng, h, width, 12, 48) * 0.4
    cover = np.clip((cl - (1 - clouds)) * 3, 0, 1) * np.clip(up * 6, 0, 1)
    sky = _mix(sky, 0.9 * _rgb("f2f2f2") * (0.6 + 0.5 * np.clip(up, 0, 1))[..., None], cover)
    below = up < 0
    gnd = _rgb(ground) * (0.6 + 0.4 * _value_noise(rng, h, width, 8, 32))[..., None]
    sky = np.where(below[..., None], gnd * (1 - np.exp(up * 20))[..., None] + sky * np.exp(up * 20)[..., None], sky)
    # The sun: a disk with a one-pixel soft edge (anti-aliased), far brighter than the sky.
    px = 360.0 / width
    disk = np.clip((sun_radius_deg - ang) / px + 0.5, 0, 1)
    sky = sky + sun_radiance * _rgb(sun_color) * disk[..., None]
    return sky


ENVMAPS = {
    # Midday: sun 50 degrees up, partly cloudy blue sky, grass-coloured ground below the horizon.
    "sky_day": lambda: _sky(512, seed=201, zenith="3d6fb6", horizon="b9d3ea", ground="5b6b3a",
                            sun_dir=(0.45, 0.766, -0.46), sun_radiance=4000.0, sun_color="fff4e0",
                            sun_radius_deg=1.6, clouds=0.45, glow=0.6),
    # Late afternoon: sun 25 degrees up towards -x (and a little +z), warm horizon; the window room
    # (window in its x = -2 wall) is lit through the window by it.
    "sky_evening": lambda: _sky(256, seed=202, zenith="34558f", horizon="f0b77e", ground="4a4338",
                                sun_dir=(-0.85, 0.42, 0.3), sun_radiance=8000.0, sun_color="ffd29a",
                                sun_radius_deg=2.2, clouds=0.25, glow=1.5),
}


# --------------------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------------------
class _Mesh:
    def __init__(self) -> None:
        self.p: list[np.ndarray] = []
        self.n: list[np.ndarray] = []
        self.f: list[np.ndarray] = []
        self.count = 0

    def add(self, p: np.ndarray, n: np.ndarray, f: np.ndarray) -> None:
        self.p.append(np.asarray(p, np.float64).reshape(-1, 3))
        nn = np.asarray(n, np.float64).reshape(-1, 3)
        self.n.append(nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12))
        self.f.append(np.asarray(f, np.int64).reshape(-1, 3) + self.count)
        self.count += self.p[-1].shape[0]

    def arrays(self):
        return np.concatenate(self.p), np.concatenate(self.n), np.concatenate(self.f)


def _grid_faces(rows: int, cols: int, wrap_cols: bool) -> np.ndarray:
    """Two triangles per cell of a rows x cols vertex grid (columns optionally wrapping)."""
    faces = []
    cmax = cols if wrap_cols else cols - 1
    for i in range(rows - 1):
        for j in range(cmax):
            a, b = i * cols + j, i * cols + (j + 1) % cols
            c, d = a + cols, b + cols
            faces += [(a, c, b), (b, c, d)]
    return np.array(faces)


def _lathe(mesh: _Mesh, pieces, segments: int) -> None:
    """Revolve profile pieces about +y. Each piece is a smooth polyline of (r, y) points; normals
    are the profile's 2D normals (to the right of the walking direction) revolved, so a closed
    profile walked counter-clockwise in the (r, y) half-plane (up the outside, down the inside)
    gives outward normals. Pieces meet at sharp creases (their shared points are duplicated)."""
    ang = 2 * np.pi * np.arange(segments) / segments
    ca, sa = np.cos(ang), np.sin(ang)
    for piece in pieces:
        pr = np.asarray(piece, np.float64)
        tang = np.gradient(pr, axis=0)
        nrm = np.stack([tang[:, 1], -tang[:, 0]], -1)  # (dy, -dr): to the right of the direction
        pts = np.stack([pr[:, None, 0] * ca[None], np.repeat(pr[:, None, 1], segments, 1), pr[:, None, 0] * sa[None]], -1)
        nor = np.stack([nrm[:, None, 0] * ca[None], np.repeat(nrm[:, None, 1], segments, 1), nrm[:, None, 0] * sa[None]], -1)
        faces = _grid_faces(len(pr), segments, True)
        mesh.add(pts, nor, faces)  # counter-clockwise seen from outside: matches the normals


def _cap(mesh: _Mesh, r: float, y: float, up: bool, segments: int) -> None:
    """A flat disk closing a lathe profile at height y (normal +y if ``up``)."""
    ang = 2 * np.pi * np.arange(segments) / segments
    pts = np.concatenate([[[0, y, 0]], np.stack([r * np.cos(ang), np.full(segments, y), r * np.sin(ang)], -1)])
    nor = np.tile([0.0, 1.0 if up else -1.0, 0.0], (segments + 1, 1))
    f = np.array([(0, 1 + (j + 1) % segments, 1 + j) if up else (0, 1 + j, 1 + (j + 1) % segments)
                  for j in range(segments)])
    mesh.add(pts, nor, f)


def _arc(r0, y0, r1, y1, n):
    t = np.linspace(0, 1, n)
    return np.stack([r0 + (r1 - r0) * t, y0 + (y1 - y0) * t], -1)


def mesh_vase() -> _Mesh:
    """A closed vase (solid; outside surface, rim, inside) 0.3 high, radius <= 0.11."""
    t = np.linspace(0, 1, 32)
    r_out = 0.05 + 0.055 * np.sin(np.pi * (0.15 + 0.85 * t)) ** 1.5 + 0.015 * t ** 4
    y = 0.3 * t
    outside = np.stack([r_out, y], -1)
    inside = np.stack([np.maximum(r_out - 0.008, 0.01), np.maximum(y, 0.02)], -1)[::-1][:-6]
    m = _Mesh()
    segs = 40
    _lathe(m, [outside, _arc(r_out[-1], 0.3, inside[0, 0], inside[0, 1], 4), inside], segs)
    _cap(m, inside[-1, 0], inside[-1, 1], True, segs)
    _cap(m, r_out[0], 0.0, False, segs)
    return m


def mesh_goblet() -> _Mesh:
    """A wine glass as one closed solid (foot, stem, bowl with a 3 mm wall), 0.2 high."""
    foot = _arc(0.035, 0.0, 0.035, 0.004, 2)
    foot_top = _arc(0.035, 0.004, 0.006, 0.012, 6)
    stem = _arc(0.006, 0.012, 0.006, 0.08, 8)
    t = np.linspace(0, 1, 24)
    bowl_r = 0.006 + 0.04 * np.sin(np.pi / 2 * t) ** 0.8 - 0.004 * t ** 2
    bowl_y = 0.08 + 0.12 * t
    bowl_out = np.stack([bowl_r, bowl_y], -1)
    bowl_in = np.stack([np.maximum(bowl_r - 0.003, 0.002), np.maximum(bowl_y, 0.095)], -1)[::-1][:-3]
    rim = _arc(bowl_r[-1], 0.2, bowl_in[0, 0], bowl_in[0, 1], 3)
    m = _Mesh()
    segs = 40
    _lathe(m, [foot, foot_top, stem, bowl_out, rim, bowl_in], segs)
    _cap(m, bowl_in[-1, 0], bowl_in[-1, 1], True, segs)
    _cap(m, 0.035, 0.0, False, segs)
    return m


def mesh_bowl() -> _Mesh:
    """A shallow fruit bowl (closed solid, 5 mm wall), radius 0.18, 0.08 high."""
    t = np.linspace(0, 1, 20)
    r = 0.06 + 0.12 * np.sin(np.pi / 2 * t)
    y = 0.08 * t ** 1.6
    outside = np.stack([r, y], -1)
    inside = np.stack([r - 0.005, np.maximum(y, 0.008)], -1)[::-1][:-1]
    m = _Mesh()
    segs = 48
    _lathe(m, [outside, _arc(r[-1], 0.08, inside[0, 0], inside[0, 1], 3), inside], segs)
    _cap(m, inside[-1, 0], inside[-1, 1], True, segs)
    _cap(m, r[0], 0.0, False, segs)
    return m


def mesh_bottle() -> _Mesh:
    """A solid bottle (a glass block in the shape of a bottle: no cavity), 0.3 high."""
    body = _arc(0.05, 0.0, 0.05, 0.18, 6)
    t = np.linspace(0, 1, 12)
    shoulder = np.stack([0.05 - 0.034 * np.sin(np.pi / 2 * t) ** 2, 0.18 + 0.06 * t], -1)
    neck = _arc(0.016, 0.24, 0.016, 0.3, 4)
    m = _Mesh()
    segs = 40
    _lathe(m, [body, shoulder, neck], segs)
    _cap(m, 0.016, 0.3, True, segs)
    _cap(m, 0.05, 0.0, False, segs)
    return m


def mesh_pawn() -> _Mesh:
    """A chess pawn (closed solid of revolution), 4.5 cm high, base radius 1.6 cm."""
    a = np.radians(np.linspace(-20, 90, 12))
    head = np.stack([0.0085 * np.cos(a), 0.037 + 0.0085 * np.sin(a)], -1)
    body = np.array([(0.016, 0.005), (0.013, 0.008), (0.0095, 0.012), (0.0065, 0.022), (0.0055, 0.029),
                     (0.0095, 0.030), (0.0095, 0.032)])
    m = _Mesh()
    _lathe(m, [_arc(0.016, 0.0, 0.016, 0.005, 2), body, np.concatenate([[(0.0095, 0.032)], head])], 32)
    _cap(m, 0.016, 0.0, False, 32)
    return m


def mesh_king() -> _Mesh:
    """A chess king without its cross (a cube in the scene), 8 cm high, base radius 2 cm."""
    body = np.array([(0.02, 0.006), (0.016, 0.01), (0.011, 0.016), (0.008, 0.04), (0.0075, 0.055),
                     (0.012, 0.057), (0.012, 0.06), (0.009, 0.062), (0.012, 0.075)])
    top = _arc(0.012, 0.075, 0.0, 0.08, 4)
    m = _Mesh()
    _lathe(m, [_arc(0.02, 0.0, 0.02, 0.006, 2), body, top], 32)
    _cap(m, 0.02, 0.0, False, 32)
    return m


def mesh_cove() -> _Mesh:
    """A photo studio's cyclorama cove: a quarter cylinder joining a floor (y = 0, z >= 1) to a back
    wall (z = 0, y >= 1), x in [-1, 1], its normals facing the studio (towards the axis)."""
    a = np.linspace(0, np.pi / 2, 24)
    x = np.array([-1.0, 1.0])
    pts = np.stack([np.repeat(x[None], len(a), 0), np.repeat((1 - np.cos(a))[:, None], 2, 1),
                    np.repeat((1 - np.sin(a))[:, None], 2, 1)], -1)
    nor = np.stack([np.zeros((len(a), 2)), np.repeat(np.cos(a)[:, None], 2, 1), np.repeat(np.sin(a)[:, None], 2, 1)], -1)
    m = _Mesh()
    m.add(pts, nor, _grid_faces(len(a), 2, False)[:, [0, 2, 1]])
    return m


def _tube(mesh: _Mesh, path: np.ndarray, radius: float, sides: int, closed: bool) -> None:
    """A tube of ``radius`` along a polyline (parallel-transported frame); open ends are left open
    (the tubes here are thin opaque wires)."""
    path = np.asarray(path, np.float64)
    tang = np.gradient(path, axis=0)
    if closed:
        tang = np.roll(path, -1, 0) - np.roll(path, 1, 0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(tang[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n0 = np.cross(tang[0], ref)
    n0 /= np.linalg.norm(n0)
    normals = [n0]
    for i in range(1, len(path)):
        nn = normals[-1] - tang[i] * np.dot(normals[-1], tang[i])
        normals.append(nn / np.linalg.norm(nn))
    nrm = np.array(normals)
    bin_ = np.cross(tang, nrm)
    ang = 2 * np.pi * np.arange(sides) / sides
    ring = np.cos(ang)[None, :, None] * nrm[:, None] + np.sin(ang)[None, :, None] * bin_[:, None]
    pts = path[:, None] + radius * ring
    rows = len(path)
    faces = _grid_faces(rows, sides, True)
    if closed:
        extra = [(((rows - 1) * sides + j), j, ((rows - 1) * sides + (j + 1) % sides)) for j in range(sides)]
        extra += [(((rows - 1) * sides + (j + 1) % sides), j, (j + 1) % sides) for j in range(sides)]
        faces = np.concatenate([faces, np.array(extra)])
    mesh.add(pts, ring, faces[:, [0, 2, 1]])


def mesh_torus_knot() -> _Mesh:
    """A (2, 3) torus knot tube, about 0.9 across (the metal sculpture)."""
    t = np.linspace(0, 2 * np.pi, 240, endpoint=False)
    p, q = 2, 3
    r = 0.28 + 0.12 * np.cos(q * t)
    path = np.stack([r * np.cos(p * t), 0.12 * np.sin(q * t), r * np.sin(p * t)], -1)
    m = _Mesh()
    _tube(m, path, 0.055, 14, True)
    return m


def mesh_water() -> _Mesh:
    """A wavy water surface over [-1, 1]^2 (x, z) at y ~ 0: sum of four sine waves, 0.6 cm high,
    smooth analytic normals (one-sided: normals up; the pool's water is a closed box below it)."""
    n = 56
    z, x = np.mgrid[0:n, 0:n] / (n - 1) * 2 - 1
    waves = ((0.004, 7.0, 0.3, 0.0), (0.003, 11.0, 2.1, 1.0), (0.002, 17.0, 4.0, 2.0), (0.0015, 23.0, 5.5, 0.5))
    h = np.zeros_like(x)
    hx = np.zeros_like(x)
    hz = np.zeros_like(x)
    for a, k, th, ph in waves:
        kx, kz = k * np.cos(th), k * np.sin(th)
        s = kx * x + kz * z + ph
        h += a * np.sin(s)
        hx += a * kx * np.cos(s)
        hz += a * kz * np.cos(s)
    pts = np.stack([x, h, z], -1)
    nor = np.stack([-hx, np.ones_like(x), -hz], -1)
    m = _Mesh()
    m.add(pts, nor, _grid_faces(n, n, False))
    return m


def mesh_cage() -> _Mesh:
    """A bird cage of 2 mm wires: 20 vertical bars bowed into a dome and four horizontal rings."""
    m = _Mesh()
    bars = 20
    s = np.linspace(0, 1, 24)
    height, radius = 0.5, 0.16
    for j in range(bars):
        a = 2 * np.pi * j / bars
        prof_r = radius * np.where(s < 0.7, 1.0, np.cos((s - 0.7) / 0.3 * np.pi / 2))
        prof_y = np.where(s < 0.7, s / 0.7 * 0.35, 0.35 + 0.15 * np.sin((s - 0.7) / 0.3 * np.pi / 2))
        prof_r = np.maximum(prof_r, 0.004)
        path = np.stack([prof_r * np.cos(a), prof_y * height / 0.5, prof_r * np.sin(a)], -1)
        _tube(m, path, 0.002, 6, False)
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    for y in (0.0, 0.12, 0.24, 0.35):
        path = np.stack([radius * np.cos(t), np.full_like(t, y), radius * np.sin(t)], -1)
        _tube(m, path, 0.0025, 6, True)
    return m


def mesh_leaves() -> _Mesh:
    """About 700 leaves (small two-triangle quads, random orientation) in three crowns of a tree
    whose trunk (a cylinder in the scene) stands at the origin; needs a ``twosided`` BSDF."""
    rng = np.random.default_rng(301)
    m = _Mesh()
    crowns = ((0.0, 2.2, 0.0, 0.9), (0.45, 1.8, 0.3, 0.6), (-0.4, 1.9, -0.25, 0.6))
    for cx, cy, cz, cr in crowns:
        for _ in range(int(700 * cr / 2.1)):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            c = np.array([cx, cy, cz]) + d * cr * rng.uniform(0.55, 1.0) ** 0.5 * np.array([1, 0.75, 1])
            nrm = rng.normal(size=3) + np.array([0, 1.5, 0]) + 0.8 * d
            nrm /= np.linalg.norm(nrm)
            tang = np.cross(nrm, rng.normal(size=3))
            tang /= np.linalg.norm(tang)
            bit = np.cross(nrm, tang)
            size = rng.uniform(0.05, 0.08)
            quad = np.array([c + size * (-tang), c + size * 0.45 * bit, c + size * tang, c - size * 0.45 * bit])
            m.add(quad, np.tile(nrm, (4, 1)), np.array([(0, 2, 1), (0, 3, 2)]))
    return m


MESHES = {
    "vase": mesh_vase, "goblet": mesh_goblet, "bowl": mesh_bowl, "bottle": mesh_bottle,
    "pawn": mesh_pawn, "king": mesh_king, "cove": mesh_cove, "torus_knot": mesh_torus_knot, "water": mesh_water, "cage": mesh_cage, "leaves": mesh_leaves,
}


# --------------------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------------------
def _srgb8(img: np.ndarray) -> np.ndarray:
    lin = np.clip(img, 0.03, 0.85)  # no perfect absorbers or reflectors (module docstring)
    s = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    return np.clip(np.round(s * 255), 0, 255).astype(np.uint8)


def _write_image(path: Path, pixels: np.ndarray, fmt, attrs: dict) -> None:
    import OpenImageIO as oiio

    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    for k, v in attrs.items():
        spec.attribute(k, v)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp" + path.suffix)
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), spec):
        raise OSError(f"make_assets: cannot write '{path}': {oiio.geterror()}")
    ok = out.write_image(np.ascontiguousarray(pixels))
    out.close()
    if not ok:
        raise OSError(f"make_assets: cannot write '{path}': {oiio.geterror()}")
    tmp.replace(path)


def write_ply(path: Path, mesh: _Mesh) -> None:
    """Binary little-endian PLY: float32 x y z nx ny nz, uchar-count int32 triangle lists."""
    p, n, f = mesh.arrays()
    header = ("ply\nformat binary_little_endian 1.0\ncomment data_gen scene library (make_assets.py)\n"
              f"element vertex {len(p)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    verts = np.concatenate([p, n], 1).astype("<f4")
    faces = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = f
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(verts.tobytes())
        fh.write(faces.tobytes())
    tmp.replace(path)


def write_all(out: str | Path = DEFAULT_OUT, *, only: set[str] | None = None) -> list[Path]:
    """Write every asset (or those whose stem is in ``only``) under ``out``; returns the paths."""
    import OpenImageIO as oiio

    out = Path(out)
    written = []
    for name, fn in TEXTURES.items():
        if only is None or name in only:
            p = out / "textures" / f"{name}.png"
            _write_image(p, _srgb8(fn()), oiio.UINT8, {"oiio:ColorSpace": "sRGB"})
            written.append(p)
    for name, fn in ENVMAPS.items():
        if only is None or name in only:
            p = out / "envmaps" / f"{name}.exr"
            _write_image(p, fn().astype(np.float32), oiio.HALF, {"compression": "zip", "DateTime": _DATETIME})
            written.append(p)
    for name, fn in MESHES.items():
        if only is None or name in only:
            p = out / "meshes" / f"{name}.ply"
            write_ply(p, fn())
            written.append(p)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m data_gen.library.make_assets", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(DEFAULT_OUT), help=f"output folder (default {DEFAULT_OUT})")
    a = ap.parse_args(argv)
    paths = write_all(a.out)
    size = sum(p.stat().st_size for p in paths)
    print(f"make_assets: {len(paths)} files -> {a.out} ({size / 2**20:.2f} MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
