"""A registered-for-one-test trainable method with BatchNorm: its loss returns the running
statistics as aux updates, which the trainer merges into the params (jaxdenoise.nn.state)."""
import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxdenoise import nn


@dataclasses.dataclass(frozen=True)
class Config:
    channels: int = 3


def _net():
    return nn.serial(nn.Conv(3, 1), nn.BatchNorm(momentum=0.9))


def needs(config):
    return frozenset({"color"})


def init(key, config):
    return {"net": _net()[0](key, (-1, 4, 4, 3))[1]}


def apply(params, buffers, config):
    return _net()[1](params["net"], buffers.color, train=False)


def loss(params, batch, config):
    y, updates = _net()[1](params["net"], batch["x"], train=True)
    return jnp.mean(jnp.square(y - batch["y"])), {"updates": {"net": updates}}


def make_dataset(data_dir, config):
    return None


def batch(dataset, step, config, rng):
    x = (3.0 + rng.normal(size=(8, 4, 4, 3))).astype(np.float32)
    return {"x": x, "y": np.zeros((8, 4, 4, 3), np.float32)}
