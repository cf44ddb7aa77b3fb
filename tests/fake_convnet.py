"""A registered-for-one-test convolutional method (a small U-Net from jaxdenoise.nn) trained by the
generic trainer on 4 fixed crops: it must overfit them (the trainer + layers work end to end)."""
import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxdenoise import nn


@dataclasses.dataclass(frozen=True)
class Config:
    widths: tuple = (16, 32)


def _net(config):
    stage = lambda c: nn.serial(nn.Conv(c, 3), nn.LeakyRelu(0.1), nn.Conv(c, 3), nn.LeakyRelu(0.1))
    return nn.UNet([stage(c) for c in config.widths], nn.MaxPool(2), stage(config.widths[-1]), nn.Upsample(2),
                   [nn.serial(stage(c), *([nn.Conv(3, 1)] if i == 0 else [])) for i, c in enumerate(config.widths)])


def needs(config):
    return frozenset({"color"})


def init(key, config):
    return {"net": _net(config)[0](key, (-1, 16, 16, 3))[1]}


def apply(params, buffers, config):
    x, size = nn.pad_to_multiple(buffers.color, 2 ** len(config.widths))
    return nn.crop_to(_net(config)[1](params["net"], x), size)


def loss(params, batch, config):
    return jnp.mean(jnp.square(_net(config)[1](params["net"], batch["x"]) - batch["y"]))


def make_dataset(data_dir, config):
    r = np.random.default_rng(0)
    y = r.uniform(0.2, 1.0, size=(4, 16, 16, 3)).astype(np.float32)
    return {"x": (y + 0.3 * r.normal(size=y.shape)).astype(np.float32), "y": y}


def batch(dataset, step, config, rng):
    return dataset
