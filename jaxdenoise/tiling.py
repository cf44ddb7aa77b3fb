"""Tiled inference: a frame whose program would need more memory than a budget is denoised in
overlapping tiles (OIDN's ``maxMemoryMB``), one compiled program for every tile.

A method can be tiled when its output at a pixel depends on a bounded neighbourhood: the networks,
whose module declares ``TILE_MARGIN`` (pixels of context a tile needs on each side, chosen by
measurement: docs/results/tiling/). Methods that solve for the whole frame (the screened-Poisson
solvers) or read it through unbounded filters do not declare it and are never tiled.

- **Grid.** Along each side the frame is cut into cores of ``tile`` pixels, or the same number made
  equal (rounded up to a multiple of 64 pixels) where that computes fewer pixels, so no window is
  spent on a sliver of a core; each core is denoised inside a window of its side + 2 margin pixels
  around it, shifted inward at the frame's border, so every window has the same shape (one compile) and
  lies inside the frame (no padding the untiled run would not see). Cores whose windows would
  coincide (at the far border, or along a side no longer than a window) are merged into one, so no
  window is computed twice. The output keeps each window's core: no blending, every output pixel
  comes from exactly one tile.
- **Whole-frame statistics.** A method that normalises by statistics of the whole frame
  (``frame_stats``: DEMC's position moments, GradNet's largest depth, RAE's mean depth) gets them
  computed once on the whole frame and carried by every tile (``stat.<name>``, the mechanism training
  crops use: `jaxdenoise.pipeline.carried_stat`), so a tile is normalised as the frame is.
- **Budget.** `plan` picks the largest tile (a multiple of 64 pixels) whose program XLA estimates
  (arguments + outputs + temporaries, `inference.Compiled`) within ``max_bytes``; the whole frame
  when it fits.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .buffers import ALL_FIELDS, METADATA_FIELDS, Buffers
from .errors import JaxdenoiseError
from .methods import Method

__all__ = ["margin", "window_shape", "windows", "frame_stat_values", "tile_frame", "denoise_tiled", "plan", "infer",
           "TILE_STEP"]

TILE_STEP = 64  # tile sides are multiples of this (every network's stride divides it)


def margin(m: Method) -> int | None:
    """The context in pixels a tile of ``m`` needs on each side (the module's ``TILE_MARGIN``), or
    None when ``m`` cannot be tiled."""
    value = getattr(m.module, "TILE_MARGIN", None)
    return None if value is None else int(value)


def _segments(n: int, tile: int, pad: int) -> tuple[int, list[tuple[int, int, int]]]:
    """Along one side of ``n`` pixels: the window side and ``(window start, core start, core end)`` per
    window. Cores of ``tile`` pixels, or the same number made equal (rounded up to a multiple of
    `TILE_STEP` when ``tile`` is one) so the last is not a sliver whose window is mostly context;
    cores whose windows (shifted inward at the border) coincide merged; of the two, the grid that
    computes fewer pixels along the side (ties: fewer windows)."""
    if tile < 1 or pad < 0:
        raise JaxdenoiseError(f"tiling: expected tile >= 1 and margin >= 0, got tile={tile}, margin={pad}")
    k = -(-n // tile)
    even = -(-n // k)
    if tile % TILE_STEP == 0:
        even = min(tile, -(-even // TILE_STEP) * TILE_STEP)
    best = None
    for step in dict.fromkeys((tile, even)):
        side = min(step + 2 * pad, n)
        segs: list[tuple[int, int, int]] = []
        for c0 in range(0, n, step):
            c1, start = min(c0 + step, n), min(max(c0 - pad, 0), n - side)
            if segs and segs[-1][0] == start:
                segs[-1] = (start, segs[-1][1], c1)
            else:
                segs.append((start, c0, c1))
        if best is None or (len(segs) * side, len(segs)) < (len(best[1]) * best[0], len(best[1])):
            best = (side, segs)
    return best


def window_shape(h: int, w: int, tile: int, pad: int) -> tuple[int, int]:
    """The one window shape of every tile of an ``h`` x ``w`` frame (`windows`)."""
    return _segments(h, tile, pad)[0], _segments(w, tile, pad)[0]


def windows(h: int, w: int, tile: int, pad: int) -> list[tuple[int, int, int, int, int, int]]:
    """The tiles of an ``h`` x ``w`` frame: ``(wy, wx, cy0, cx0, cy1, cx1)`` per tile, the window's
    top-left corner (the same `window_shape` for every tile) and the core ``[cy0, cy1) x [cx0, cx1)``
    the tile's output is kept on, in frame coordinates. Along each side the cores are at most ``tile``
    pixels, each inside a window with ``pad`` pixels of context where the frame has them; of cores of
    ``tile`` and the same number made equal, the grid computing fewer pixels. The cores partition the
    frame; cores whose windows would coincide (near the border, or along a side no longer than a
    window) are merged, so no window is computed twice."""
    return [(wy, wx, cy0, cx0, cy1, cx1) for wy, cy0, cy1 in _segments(h, tile, pad)[1]
            for wx, cx0, cx1 in _segments(w, tile, pad)[1]]


def frame_stat_values(m: Method, buffers: Buffers) -> dict[str, Any]:
    """The per-frame statistics ``m`` normalises by (its module's ``frame_stats``), computed on the
    whole frame, as the ``stat.<name>`` entries a tile carries."""
    from .pipeline import STAT

    fns = getattr(m.module, "frame_stats", None)
    if fns is None:
        return {}
    frame = buffers.to_dict()
    return {STAT + name: np.asarray(fn(frame), np.float32) for name, fn in fns(m.config).items()}


def tile_frame(buffers: Buffers, stats: dict, wy: int, wx: int, wh: int, ww: int) -> Any:
    """The window ``[wy, wy + wh) x [wx, wx + ww)`` of a frame with its metadata: a `Buffers`, or the
    dict frame a method reads whole-frame statistics from (``stats``: `frame_stat_values`)."""
    out = {}
    for f in ALL_FIELDS:
        v = getattr(buffers, f)
        if v is not None:
            out[f] = v if f in METADATA_FIELDS else np.asarray(v)[wy:wy + wh, wx:wx + ww]
    return {**out, **stats} if stats else Buffers(**out)


def denoise_tiled(fn, m: Method, params: Any, buffers: Buffers, *, tile: int, pad: int | None = None) -> np.ndarray:
    """``m``'s output on one prepared frame (`inference.prepare`), computed tile by tile with
    ``fn(params, tile_frame)`` (`inference.inference_fn`); ``pad`` defaults to `margin`. Returns the
    float32 image."""
    if np.ndim(buffers.color) != 3:
        raise JaxdenoiseError(f"{m.name}: tiled inference takes one frame (H, W, C), got color of shape "
                              f"{np.shape(buffers.color)}")
    pad = margin(m) if pad is None else int(pad)
    if pad is None:  # no margin declared, none given
        raise JaxdenoiseError(f"{m.name}: cannot be tiled (its output depends on the whole frame); denoise the "
                              "frame whole or crop it")
    h, w = np.shape(buffers.color)[:2]
    stats = frame_stat_values(m, buffers)
    tiles = windows(h, w, int(tile), pad)
    wh, ww = window_shape(h, w, int(tile), pad)
    out = np.zeros((h, w, 3), np.float32)
    for wy, wx, cy0, cx0, cy1, cx1 in tiles:
        y = np.asarray(fn(params, tile_frame(buffers, stats, wy, wx, wh, ww)), np.float32)
        out[cy0:cy1, cx0:cx1] = y[cy0 - wy:cy1 - wy, cx0 - wx:cx1 - wx]
    return out


def plan(fn, m: Method, params: Any, buffers: Buffers, max_bytes: int) -> tuple[int | None, int | None]:
    """``(tile, bytes)``: the tile side for ``m`` on this prepared frame under ``max_bytes`` of XLA's
    estimate (None: the whole frame fits and is not tiled) and that estimate for the program that will
    run (one tile's, or the whole frame's). ``fn`` is the method's `inference.Compiled`; each candidate
    is compiled (and kept for the run). Raises when even a ``TILE_STEP`` tile does not fit."""
    h, w = np.shape(buffers.color)[:2]
    whole = fn.compile(params, buffers, check=False).xla_bytes
    if whole is None or whole <= max_bytes:
        return None, whole
    pad = margin(m)
    if pad is None:
        raise JaxdenoiseError(f"{m.name}: this frame needs {whole / 2**20:.0f} MiB by XLA's estimate, over the "
                              f"{max_bytes / 2**20:.0f} MiB budget, and the method cannot be tiled (its output depends "
                              "on the whole frame)")
    stats = frame_stat_values(m, buffers)
    per_pixel = whole / (h * w)
    # first guess: the largest tile whose window (capped at the frame's sides) fits at the whole frame's bytes
    # per pixel; XLA's estimate for it is then checked, and the tile shrinks until it fits
    tile = TILE_STEP
    for t in range(-(-max(h, w) // TILE_STEP) * TILE_STEP, TILE_STEP - 1, -TILE_STEP):
        wh, ww = window_shape(h, w, t, pad)
        if wh * ww * per_pixel <= max_bytes:
            tile = t
            break
    while True:
        wh, ww = window_shape(h, w, tile, pad)
        need = fn.compile(params, tile_frame(buffers, stats, 0, 0, wh, ww), check=False).xla_bytes
        if need is None or need <= max_bytes:
            return tile, need
        if tile == TILE_STEP:
            raise JaxdenoiseError(f"{m.name}: even a {TILE_STEP}-pixel tile with its {pad}-pixel margin needs "
                                  f"{need / 2**20:.0f} MiB by XLA's estimate, over the {max_bytes / 2**20:.0f} MiB "
                                  "budget; raise the budget")
        tile = max(TILE_STEP, tile - TILE_STEP)


def infer(m: Method, params: Any, prepared: Buffers, *, tile: int | None = None,
          max_memory_mb: float | None = None) -> Any:
    """``m``'s output on a prepared frame (`inference.prepare`): whole, or in tiles of side ``tile``,
    or in the largest tiles whose program stays within ``max_memory_mb`` MiB of XLA's estimate
    (`plan`; whole when the frame fits). The one entry point of the API and the CLI."""
    from .inference import inference_fn

    fn = inference_fn(m)
    if tile is None and max_memory_mb is None:
        return fn(params, prepared)
    if not m.jittable:
        raise JaxdenoiseError(f"{m.name}: foreign code, not compiled here: it cannot be tiled or budgeted "
                              "(drop tile / max_memory_mb)")
    if tile is not None and (isinstance(tile, bool) or int(tile) != tile or tile < 1):
        raise JaxdenoiseError(f"tile: expected a positive number of pixels, got {tile!r}")
    if max_memory_mb is not None and not (float(max_memory_mb) > 0):
        raise JaxdenoiseError(f"max_memory_mb: expected a positive number of MiB, got {max_memory_mb!r}")
    if tile is None:
        tile, _ = plan(fn, m, params, prepared, int(float(max_memory_mb) * 2**20))
        if tile is None:
            return fn(params, prepared)
    return denoise_tiled(fn, m, params, prepared, tile=int(tile))
