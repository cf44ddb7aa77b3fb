"""`input`: no denoising; the raw Monte Carlo estimate. The baseline every table starts from."""
from __future__ import annotations

import dataclasses

from ..buffers import Buffers


@dataclasses.dataclass(frozen=True)
class Config:
    """No hyperparameters."""


def needs(config: Config) -> frozenset[str]:
    return frozenset({"color"})


def init(key, config: Config) -> dict:
    return {}


def apply(params: dict, buffers: Buffers, config: Config):
    return buffers.color
