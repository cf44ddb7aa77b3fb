"""A registered-for-one-test method with two parameter groups updated in alternation, each with
its own optimizer settings and its own loss (as GradNet's autoencoder and G-branch)."""
import dataclasses

import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Config:
    pass


def needs(config):
    return frozenset({"color"})


def init(key, config):
    return {"a": jnp.ones(3), "b": jnp.ones(3), "norm": jnp.zeros(3)}


FROZEN = ("norm",)


def apply(params, buffers, config):
    return buffers.color * params["a"]


def param_groups(config):
    return {"a": ("a",), "b": ("b",)}


def group_train(config):
    return {"b": {"learning_rate": 0.5}}


def loss(params, batch, config, group=None):
    # group a pulls a towards 2, group b pulls b towards -1 (each loss sees only its own target)
    if group == "a":
        return jnp.sum((params["a"] - 2.0) ** 2) + 0 * jnp.sum(params["b"])
    return jnp.sum((params["b"] + 1.0) ** 2) + 0 * jnp.sum(params["a"])


def make_dataset(data_dir, config):
    return None


def batch(dataset, step, config, rng):
    return {"x": np.zeros(1, np.float32)}
