"""A registered-for-one-test method that can use albedo but runs without it (to test the records,
tables and warnings of a method run without an optional buffer)."""
import dataclasses


@dataclasses.dataclass(frozen=True)
class Config:
    pass


def needs(config):
    return frozenset({"color", "albedo"})


def required(config):
    return frozenset({"color"})


def init(key, config):
    return {}


def apply(params, buffers, config):
    return buffers.color if buffers.albedo is None else 0.5 * (buffers.color + buffers.albedo)
