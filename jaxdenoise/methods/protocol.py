"""The method surface (docs/architecture.md "Methods"), stated once as typed protocols.

A method is a module ``jaxdenoise/methods/<name>.py``. Every module satisfies `MethodModule`; the
optional hooks come in groups, each a protocol of its own, and a module has either all of a group's
members or none (`check_module` says which are incomplete):

- `MethodModule` (required): ``Config``, ``needs``, ``init``, ``apply``.
- `Causal`: a temporal method that looks only backwards (a recurrent network): ``init_state`` and
  ``step``. The sequence driver (`jaxdenoise.sequence`) carries the state frame to frame.
- `Windowed`: a temporal method whose frame ``t`` also reads frames ``t - back .. t + ahead`` (LBF's
  7-frame filter): ``window``, ``prepare_frame``, ``apply_window``. The driver runs
  ``prepare_frame`` once per frame and emits frame ``t`` once frame ``t + ahead`` has arrived.
- `Trainable`: ``loss``, ``make_dataset``, ``batch`` (`jaxdenoise.train`).
- `Grouped`: ``param_groups`` (a trainable method whose parameter groups the trainer updates in
  alternation, each with its own optimizer; ``loss`` then takes ``group=``; ``group_train`` gives
  per-group TrainConfig overrides).

Plain attributes, all optional: ``required(config)`` (the subset of ``needs`` a frame must have;
default all of it), ``JITTABLE`` (False for foreign code such as OIDN), ``requirements()`` (why the
method cannot run here, or None), ``WEIGHTS`` (shipped weights folder name, or a function of the
config), ``TRAIN`` (the trainer's defaults), ``FROZEN`` (params stored with the weights but not
trained), ``init_from_data``, ``frame_stats(config)`` (the per-frame statistics the network's
inputs are normalized by: ``{name: function of a whole frame's buffers -> a small vector per
frame}``; a trainable method passes them to `jaxdenoise.pipeline.open_training_data`, which
evaluates them on every whole training render and carries them with each crop as
``"stat.<name>"``, and its input builder uses a carried value in place of the statistic of the
array it is given, so that a crop's inputs are the whole frame's inputs cropped),
``validation_loss(params, buffers, config)`` (an unsupervised loss of one whole frame that reads no
reference; the trainer records it on the validation frames and can select weights by it,
``select="loss"``).

A method with none of the temporal hooks (or a `Windowed` one whose ``window`` is ``(0, 0)`` for
its config) is run frame by frame on sequences.
"""
from __future__ import annotations

from types import ModuleType
from typing import Any, Protocol, runtime_checkable

__all__ = ["MethodModule", "Causal", "Windowed", "Trainable", "Grouped", "check_module", "HOOK_GROUPS"]


@runtime_checkable
class MethodModule(Protocol):
    """What every method module provides."""

    Config: type  # frozen dataclass of hyperparameters, defaults from the paper (cited)

    def needs(self, config: Any) -> frozenset[str]:
        """The `Buffers` fields it reads (``color`` included) and the per-frame metadata it uses
        (``spp``), so a renderer produces nothing else and a frame without them fails clearly."""

    def init(self, key: Any, config: Any) -> Any:
        """Parameters: a plain pytree (``{}`` for methods without any)."""

    def apply(self, params: Any, buffers: Any, config: Any) -> Any:
        """Denoised ``(H, W, 3)`` image; pure and jittable unless ``JITTABLE = False``. A leading axis
        is always a batch of independent frames (``(B, H, W, 3)`` in, ``(B, H, W, 3)`` out), never
        a video."""


@runtime_checkable
class Causal(Protocol):
    """A temporal method that reads only the past (recurrent)."""

    def init_state(self, buffers: Any, config: Any) -> Any:
        """The state before the first frame, shaped for ``buffers`` (one frame)."""

    def step(self, params: Any, state: Any, buffers: Any, config: Any) -> tuple[Any, Any]:
        """``(new state, denoised frame)`` for one frame; pure and jittable."""


@runtime_checkable
class Windowed(Protocol):
    """A temporal method whose output at frame t reads frames t - back .. t + ahead."""

    def window(self, config: Any) -> tuple[int, int]:
        """``(back, ahead)``: how many frames before and after t the output of t reads. ``(0, 0)``
        means per frame. At the ends of a sequence the window is clipped (fewer frames)."""

    def prepare_frame(self, params: Any, buffers: Any, config: Any) -> Any:
        """Per-frame work shared by every window that contains the frame (a pytree); jittable."""

    def apply_window(self, params: Any, prepared: tuple, center: int, config: Any) -> Any:
        """The denoised frame ``prepared[center]`` from the prepared frames of its (clipped) window,
        in time order; jittable with ``center`` static."""


@runtime_checkable
class Trainable(Protocol):
    """A method `jaxdenoise.train` can train."""

    def loss(self, params: Any, batch: Any, config: Any) -> Any:
        """A scalar, or ``(scalar, aux)`` where training carries state."""

    def make_dataset(self, data_dir: Any, config: Any) -> Any:
        """Read and preprocess the training data once."""

    def batch(self, dataset: Any, step: int, config: Any, rng: Any) -> Any:
        """The mini-batch of ``step`` (``rng`` is seeded from (seed, step): resumes draw the same)."""


@runtime_checkable
class Grouped(Protocol):
    """A trainable method with parameter groups updated in alternation (`jaxdenoise.train`)."""

    def param_groups(self, config: Any) -> dict:
        """``{group name: top-level params keys}``; step t updates group t mod n, with
        ``loss(params, batch, config, group=name)`` and its own optimizer state."""


HOOK_GROUPS: dict[str, type] = {"causal": Causal, "windowed": Windowed, "trainable": Trainable, "grouped": Grouped}


def _members(proto: type) -> list[str]:
    return [n for n in proto.__dict__ if not n.startswith("_") and callable(proto.__dict__[n])]


def check_module(module: ModuleType) -> list[str]:
    """Problems with ``module`` as a method (empty when it satisfies the surface): missing required
    members, and optional hook groups that are only partly there."""
    problems = []
    for name in ["Config"] + _members(MethodModule):
        if not hasattr(module, name):
            problems.append(f"{module.__name__}: missing required '{name}'")
    for group, proto in HOOK_GROUPS.items():
        have = [n for n in _members(proto) if callable(getattr(module, n, None))]
        if have and len(have) != len(_members(proto)):
            missing = sorted(set(_members(proto)) - set(have))
            problems.append(f"{module.__name__}: {group} hooks incomplete: has {have}, lacks {missing}")
    return problems
