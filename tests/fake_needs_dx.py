"""A registered-for-one-test method that needs a gradient buffer (to test bench's skip records)."""
import dataclasses


@dataclasses.dataclass(frozen=True)
class Config:
    pass


def needs(config):
    return frozenset({"color", "dx"})


def init(key, config):
    return {}


def apply(params, buffers, config):
    return buffers.color + 0 * buffers.dx
