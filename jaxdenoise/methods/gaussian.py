"""`gaussian`: an isotropic Gaussian blur of the noisy colour (the simplest linear baseline).

It ignores every auxiliary buffer, so it shows what edge-awareness (bilateral, LBF) and learning
buy. The default sigma is a choice (see docs/methods/gaussian.md), not a paper value.
"""
from __future__ import annotations

import dataclasses

from ..buffers import Buffers, map_frames
from ..filters import gaussian as gaussian_filter


@dataclasses.dataclass(frozen=True)
class Config:
    sigma: float = 1.0     # pixels; 0 gives the identity
    radius: int | None = None  # None: ceil(3 * sigma)


def needs(config: Config) -> frozenset[str]:
    return frozenset({"color"})


def init(key, config: Config) -> dict:
    return {}


def apply(params: dict, buffers: Buffers, config: Config):
    """Blur one frame, or each frame of a batch (leading axes) on its own."""
    return map_frames(lambda b: gaussian_filter(b.color, config.sigma, radius=config.radius), buffers)
