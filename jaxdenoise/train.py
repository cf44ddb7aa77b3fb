"""The generic training loop behind ``jaxdenoise train METHOD`` (docs/architecture.md "Methods", "Command line").

```python
from jaxdenoise import methods, train
method = methods.get("lbf")                                  # resolved once, passed down
run = train.TrainConfig.for_method(method, steps=400, val_data="data/val", validate_every=50)
summary = train.train(method, "data/train", "runs/lbf", run)  # data: a folder, an export or load_data(...)
print(summary["line"])
```

``train(method, data, out_dir, run=None) -> dict`` takes the resolved `jaxdenoise.methods.Method`
(never a name: nothing below looks the method up again), the training data (a folder or export, or
a `TrainingData` from `load_data` that several runs share), the output folder and one
`TrainConfig`: everything a run needs besides the method and the data, one field per option of
``jaxdenoise train`` (``--steps`` -> ``steps``, ``--quiet`` -> ``progress=False``, ...).
`TrainConfig.for_method` starts from the method's ``TRAIN`` defaults. The body reads as setup
(`initial_state`, `make_stepper`), loop (one `Stepper` call per batch, `validation_round` and
`save_checkpoint` on their schedules) and finish (`save_weights`, the summary).

What a trainable method module provides (besides ``Config``, ``init``, ``apply``, ``loss``):

- ``make_dataset(data_dir, config) -> dataset``: reads and preprocesses the training data once
  (anything that does not depend on the parameters, e.g. LBF's secondary features);
- ``batch(dataset, step, config, rng) -> batch``: the mini-batch of one step; ``rng`` is a
  ``numpy.random.Generator`` seeded from ``(seed, step)``, so a resumed run draws the same
  batches as an uninterrupted one (being a function of the step alone, the next batches are drawn
  on worker threads, `batch_workers`, while the device runs the current step; it must not mutate
  ``dataset``);
- optionally ``init_from_data(key, config, dataset) -> params`` (e.g. input normalization
  statistics from the training set; default ``init(key, config)``);
- optionally ``TRAIN``: a dict of `TrainConfig` defaults for the method (e.g. its optimizer);
- optionally ``FROZEN``: top-level keys of the params dict that are stored with the weights but
  not trained (e.g. normalization statistics); their updates are discarded.

Outputs under ``out_dir``:

- ``checkpoint/``: ``params.npz`` + ``config.json`` (params, optimizer state, step, loss history),
  written atomically every ``checkpoint_every`` steps and at the end; ``resume=True`` continues
  from it (the method config must match);
- ``weights/``: the trained params with the method config, loadable like shipped weights
  (`jaxdenoise.checkpoint.load`);
- ``train_config.json``: the resolved configuration (method config, training config, data, seed);
- ``summary.json``: the returned summary (its ``line`` is the one-line summary the CLI prints);
- ``best/`` (only with validation data): the params with the lowest validation error so far, same
  format as ``weights/``, with the step and the scores in its ``config.json``, and the run's whole
  validation curve so far in ``selection.json`` (`selection_curve`; ``weights/`` gets it too): the
  curve a shipped weight file's README points to.

Validation (``val_data`` and ``validate_every > 0``): every ``validate_every`` steps and at the end,
the current params denoise one render per shot and sampling rate of ``val_data`` (the first noise
instance; ``val_spps`` limits the rates) through the method's full inference path (`inference.inference_fn`,
so post-processing such as LBF's spike removal is included), and the score is the mean RelMSE
(`metrics.relmse`) over those frames, or with ``select="geomean"`` their geometric mean (`SELECT`:
validation frames at several rates, where the mean follows the noisiest rate; both are recorded
either way), or with ``select="geomean_halo"`` the geometric mean among the validations with no more
halo pixels (`metrics.halo_pixels`, recorded in every validation) than the run's first (`selectable`:
a fine-tune never ships more light drawn where the reference has none than it started with). A
method whose module defines ``validation_loss(params, buffers, config)`` (an unsupervised loss of one
whole frame that reads no reference: GradNet's) also gets its mean over the frames recorded as
``loss``, and ``select="loss"`` picks ``best/`` by it: what a user without
references can do (the reference-based scores are still recorded beside it, never used to choose). Mini-batch losses are too noisy to pick weights by, and a run
can get worse on some scenes while its training loss falls; ``best/`` is what to ship. The scores
are kept in the checkpoint's history, so a resumed run continues the same record. A run started
from given weights (``init_from``) scores them first (step 0), so ``best/`` is never worse on the
validation frames than what the run started from.

Optimization (`TrainConfig`): Adam (moment decays ``adam_b1`` / ``adam_b2``) with a step-size
schedule in steps (``schedule``: constant, the geometric ramp-up then 1/sqrt(t) of Chaitanya 2017,
step decay, exponential; `jaxdenoise.solvers.optim.schedule`) or RPROP; optional clipping of the
gradient's global norm (``clip_norm``). ``loss`` may return ``(scalar, aux)``; ``aux["updates"]``
replaces params leaves after each step (running statistics, `jaxdenoise.nn.state`). Data parallel: every batch is
split over all local devices (`shard_batch`; params replicated, gradients reduced by XLA), so the
same command uses every GPU (or ``--xla_force_host_platform_device_count`` CPU devices) JAX sees.
Parameter groups: a method may declare ``param_groups(config) -> {group: (top-level params
keys)}`` (and ``group_train(config) -> {group: TrainConfig overrides}``); the trainer then updates
the groups in alternation, step t updating group t mod n with its own optimizer state and the
group's loss ``loss(params, batch, config, group=name)`` (GradNet's autoencoder and G-branch,
Guo 2019 Sec. 4.3). This module imports without OpenImageIO, Mitsuba and jaxopt (EXRs are read only by ``make_dataset``
and validation).

Weight averaging (``ema`` in (0, 1)): the trainer also keeps ``e <- ema * e + (1 - ema) * params``
after every finite step (starting from the initial params), and validation, ``best/`` and
``weights/`` use the average instead of the last iterate (each validation record also carries the
last iterate's score as ``raw``); the checkpoint stores both, so a resumed run continues the same
average (a checkpoint written without it starts the average from its params). Averaging the
iterates of a noisy optimizer (Polyak-Ruppert; an EMA as in Karras et al.'s and most image
restoration training) removes the step-to-step wander of small batches without lowering the rate.

Non-finite losses or gradients skip the update (counted in the summary); ``max_bad_steps`` of them
in a row stop the run with an error, since the parameters would not move any more.
"""
from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import checkpoint, compile_cache
from .fsutil import write_json
from .methods import Method, MethodError
from .nn.state import merge_updates
from .errors import JaxdenoiseError

__all__ = ["TrainConfig", "TrainError", "TrainingData", "State", "Group", "Stepper", "train", "load_data",
           "initial_state", "param_groups", "optimizer_state", "step_fn", "make_stepper", "validation_round", "save_checkpoint",
           "save_weights", "selection_curve", "restore_like", "make_optimizer", "model_fields", "summary_line", "load_validation",
           "unsupervised_loss", "validate", "shard_batch", "batch_workers", "selectable", "SELECT"]

CHECKPOINT_DIR = "checkpoint"
WEIGHTS_DIR = "weights"
BEST_DIR = "best"
SELECTION_FILE = "selection.json"  # the validation curve beside best/ and weights/


# Batches drawn ahead on worker threads (the batch of step t depends on (seed, t) only).
PREFETCH = 2


def batch_workers() -> int:
    """Threads that draw batches: one where XLA computes on the same CPU cores; beside an
    accelerator, half the host's cores (at most 8), since crops and augmentations are array copies
    that release the GIL and the device can outrun one thread."""
    if jax.default_backend() == "cpu":
        return 1
    return max(1, min(8, (os.cpu_count() or 2) // 2))


class TrainError(JaxdenoiseError, RuntimeError):
    """Training cannot start or continue (bad data, config mismatch on resume, diverged)."""


# How best/ is picked (TrainConfig.select): the validation record's key it minimizes, and what it is.
# The mean is dominated by the noisiest frames (with validation frames at 1 and 64 spp, by the 1-spp
# ones); the geometric mean weighs every frame by its ratio, so a rate-general run is picked at every rate.
SELECT = {"mean": ("relmse", "mean RelMSE over the validation frames (metrics.relmse)"),
          "geomean": ("relmse_geomean", "geometric mean of RelMSE over the validation frames (metrics.relmse)"),
          "loss": ("loss", "mean unsupervised validation loss over the validation frames (the method's "
                           "validation_loss; no reference read)"),
          "geomean_halo": ("relmse_geomean", "geometric mean of RelMSE over the validation frames, among the "
                                             "validations with no more halo pixels (metrics.halo_pixels) than "
                                             "the run's first")}


def selectable(select: str, first: dict, record: dict) -> bool:
    """Whether the validation ``record`` may become ``best/`` (`SELECT`): with ``select="geomean_halo"``
    only when it has no more halo pixels than ``first``, the run's first validation (the starting weights'
    when fine-tuning; a record without the count, from an older run, does not constrain)."""
    return select != "geomean_halo" or record.get("halo", 0) <= first.get("halo", math.inf)

# The TrainConfig fields that change the compiled step (its cache key, with the method).
OPTIMIZER_FIELDS = ("optimizer", "learning_rate", "adam_b1", "adam_b2", "schedule", "schedule_every",
                    "schedule_factor", "clip_norm")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """One training run's configuration: everything it needs besides the method and the data, one
    field per option of ``jaxdenoise train`` (`TrainConfig.for_method`: the method's ``TRAIN``
    defaults under given fields). Paths are kept as strings and rate lists as tuples, so the whole
    configuration is what ``train_config.json`` and the checkpoint record."""

    # the run
    steps: int = 1000  # total steps; a resumed run continues up to it
    seed: int = 0  # initial params and every batch (drawn from (seed, step))
    resume: bool = False  # continue from out_dir/checkpoint when it exists
    init_from: str | None = None  # a weights folder to start from (fine-tuning; ignored when resuming)
    val_data: str | None = None  # folder or whole-frame export scored during training (module docstring)
    val_spps: tuple[int, ...] | None = None  # its sampling rates to score (None: all)
    validate_every: int = 0  # steps between validations (0: only at the end, when val_data is given)
    select: str = "mean"  # what picks best/: a validation record's key in SELECT (module docstring)
    checkpoint_every: int = 25
    max_bad_steps: int = 20  # non-finite steps in a row that stop the run
    time_limit: float | None = None  # seconds; stop (with a checkpoint) when exceeded
    progress: bool = True  # a progress bar (and the data pass's)
    # the optimization
    optimizer: str = "adam"  # "adam" or "rprop" (jaxdenoise.solvers.optim)
    learning_rate: float = 1e-3  # Adam step size; for RPROP the initial step size
    adam_b1: float = 0.9  # Adam's moment decays (Chaitanya 2017: 0.9 / 0.99; Guo 2019: 0.5 / 0.999)
    adam_b2: float = 0.999
    schedule: str = "constant"  # Adam's step size over steps: solvers.optim.schedule (SCHEDULES)
    schedule_every: int = 1  # the schedule's step count (ramp length, decay interval)
    schedule_factor: float = 1.0  # the schedule's factor (ramp factor, decay factor)
    clip_norm: float | None = None  # clip the gradient's global L2 norm to this (None: off)
    ema: float = 0.0  # decay of an exponential moving average of the params (0: off; module docstring)

    def __post_init__(self) -> None:
        for name in ("init_from", "val_data"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, str):
                object.__setattr__(self, name, str(value))
        if self.val_spps is not None:
            object.__setattr__(self, "val_spps", tuple(int(s) for s in self.val_spps))
        if self.steps < 0:
            raise TrainError(f"steps must be >= 0, got {self.steps}")
        if self.validate_every < 0:
            raise TrainError(f"validate_every must be >= 0, got {self.validate_every}")
        if self.select not in SELECT:
            raise TrainError(f"select must be one of {sorted(SELECT)}, got {self.select!r}")
        if not 0.0 <= self.ema < 1.0:
            raise TrainError(f"ema must be in [0, 1) (0: off), got {self.ema}")

    @classmethod
    def for_method(cls, method: Method, **fields: Any) -> "TrainConfig":
        """The method's ``TRAIN`` defaults, then ``fields``."""
        merged = {**getattr(method.module, "TRAIN", {}), **fields}
        unknown = sorted(set(merged) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise TrainError(f"unknown training setting(s) {unknown}; TrainConfig has "
                             f"{[f.name for f in dataclasses.fields(cls)]}")
        return cls(**merged)

    def optimizer_settings(self) -> tuple:
        """The fields that change the compiled step (`OPTIMIZER_FIELDS`), as a cache key."""
        return tuple(getattr(self, f) for f in OPTIMIZER_FIELDS)


def make_optimizer(tc: TrainConfig) -> tuple[Callable, Callable]:
    """The pure ``(init, update)`` pair named by ``tc.optimizer``."""
    from .solvers import optim

    try:
        if tc.optimizer == "adam":
            lr = optim.schedule(tc.schedule, tc.learning_rate, every=tc.schedule_every, factor=tc.schedule_factor)
            return optim.adam(tc.learning_rate if tc.schedule == "constant" else lr, b1=tc.adam_b1, b2=tc.adam_b2)
        if tc.optimizer == "rprop":
            if tc.schedule != "constant":
                raise TrainError(f"schedule '{tc.schedule}' needs optimizer 'adam' (RPROP adapts its own steps)")
            return optim.rprop(step_init=tc.learning_rate)
    except ValueError as e:
        raise TrainError(str(e)) from None
    raise TrainError(f"optimizer '{tc.optimizer}' is unknown; expected 'adam' or 'rprop'")


def restore_like(template: Any, loaded: Any, *, where: str = "checkpoint") -> Any:
    """`checkpoint.restore_like` with its error as a `TrainError` (a checkpoint that does not fit
    the run)."""
    try:
        return checkpoint.restore_like(template, loaded, where=where)
    except checkpoint.WeightsError as e:
        raise TrainError(str(e)) from None


def model_fields(config: Any, cfg_dict: dict) -> dict:
    """The entries of a config dict (of ``config``'s class) that define the model: without the
    training-only fields (``train_*``: crops, batch; dataclass fields with ``metadata={"training":
    True}``: loss weights, schedules) and the input transforms a fine-tune may change (``metadata=
    {"fine_tune": True}``: DEMC's exposure), in which weights given to ``init_from`` may differ."""
    training = {f.name for f in dataclasses.fields(config)
                if f.metadata.get("training") or f.metadata.get("fine_tune")}
    return {k: v for k, v in cfg_dict.items() if not k.startswith("train_") and k not in training}


# -- data ------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class TrainingData:
    """A method's training data, read once (``make_dataset``): several runs may share it."""

    source: Path  # the folder or export it was read from (recorded in every output)
    dataset: Any  # what the module's ``make_dataset`` returned


def load_data(method: Method, source: str | os.PathLike, *, progress: bool = True) -> TrainingData:
    """``method.module.make_dataset(source, method.config)`` (silenced when ``progress`` is off)."""
    make = method.module.make_dataset
    quiet = {} if progress or "progress" not in inspect.signature(make).parameters else {"progress": False}
    return TrainingData(Path(source), make(Path(source), method.config, **quiet))


class _Batches:
    """The batch of each step, ``batch(dataset, step, config, rng((seed, step)))``, drawn ahead on
    worker threads while the device runs the current step, and placed on the devices."""

    def __init__(self, method: Method, data: TrainingData, run: TrainConfig):
        self._draw = lambda s: method.module.batch(data.dataset, s, method.config,
                                                   np.random.default_rng([int(run.seed), s]))
        self._steps = run.steps
        workers = batch_workers()
        self._ahead = PREFETCH * workers
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="jaxdenoise-batches")
        self._pending: dict[int, Any] = {}

    def get(self, step: int) -> Any:
        for s in range(step, min(step + self._ahead, self._steps)):
            if s not in self._pending:
                self._pending[s] = self._pool.submit(self._draw, s)
        return shard_batch(self._pending.pop(step).result())

    def __enter__(self) -> "_Batches":
        return self

    def __exit__(self, *exc: Any) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


# -- state: initialisation, init_from, resume --------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Group:
    """What one kind of step updates: the top-level params ``keys`` (None: all) with the optimizer
    ``train``; ``name`` None for a method without parameter groups."""

    name: str | None
    keys: tuple[str, ...] | None
    train: TrainConfig


@dataclasses.dataclass
class State:
    """What a run carries from step to step, and what its checkpoint stores."""

    params: Any
    opt_state: Any  # the optimizer state; with parameter groups {group: state}
    ema: Any = None  # the weight average (None: off)
    step: int = 0
    history: list = dataclasses.field(default_factory=list)  # loss of every finite step
    bad_steps: int = 0  # non-finite steps skipped, over the whole run
    validation: list = dataclasses.field(default_factory=list)  # one record per validation
    best: dict | None = None  # the best validation record (its params are in out_dir/best)

    @property
    def shipped(self) -> Any:
        """What validation scores and ``best/`` + ``weights/`` hold: the average when kept."""
        return self.params if self.ema is None else self.ema


def param_groups(method: Method, run: TrainConfig, params: Any) -> list[Group]:
    """The groups steps alternate over: ``[Group(None, None, run)]``, or one per group the method
    declares with ``param_groups(config)`` (and ``group_train(config)``: per-group `TrainConfig`
    overrides, e.g. its own optimizer and step size). Every group names existing, non-FROZEN keys,
    and no key is in two groups."""
    module, config = method.module, method.config
    fn = getattr(module, "param_groups", None)
    if fn is None:
        return [Group(None, None, run)]
    declared = {str(g): tuple(keys) for g, keys in fn(config).items()}
    frozen = set(getattr(module, "FROZEN", ()))
    seen: dict[str, str] = {}
    for g, keys in declared.items():
        for k in keys:
            if k not in params or k in frozen:
                raise TrainError(f"parameter group '{g}' names '{k}', which is not a trainable top-level params entry "
                                 f"(entries: {sorted(params)}, frozen: {sorted(frozen)})")
            if k in seen:
                raise TrainError(f"params entry '{k}' is in two parameter groups ('{seen[k]}' and '{g}')")
            seen[k] = g
    overrides = getattr(module, "group_train", lambda c: {})(config)
    out = []
    for g, keys in declared.items():
        try:
            gtc = dataclasses.replace(run, **overrides.get(g, {}))
        except TypeError as e:
            raise TrainError(f"group_train['{g}']: {e}") from None
        out.append(Group(g, keys, gtc))
    return out


def optimizer_state(groups: list[Group], params: Any) -> Any:
    """Fresh optimizer state for ``params``: one state, or ``{group: state}`` over its keys."""
    if groups[0].name is None:
        return make_optimizer(groups[0].train)[0](params)
    return {g.name: make_optimizer(g.train)[0]({k: params[k] for k in g.keys}) for g in groups}


def _saved_config(method: Method, meta: dict) -> Any:
    """A checkpoint's config with the fields it predates filled by their defaults (a config field
    added later, with a default that keeps the old behaviour, must not orphan older runs and
    weights); as saved when it does not build (an unknown key: then it differs, as it should)."""
    saved = meta.get("config")
    try:
        return checkpoint.config_to_dict(checkpoint.config_from_dict(method.module.Config, saved))
    except (TypeError, ValueError):
        return saved


def initial_state(method: Method, data: TrainingData, run: TrainConfig, out_dir: Path) -> tuple[State, list[Group]]:
    """The state a run starts from, and its parameter groups: the method's initial params
    (``init_from_data`` or ``init`` from ``run.seed``), replaced by ``run.init_from``'s weights when
    given (same model config; training-only fields may differ, `model_fields`), fresh optimizer
    states, and with ``run.resume`` everything the checkpoint in ``out_dir`` holds (params,
    optimizer states, weight average, step, histories, the best validation record)."""
    module, cfg_dict = method.module, checkpoint.config_to_dict(method.config)
    key = jax.random.PRNGKey(run.seed)
    if hasattr(module, "init_from_data"):
        params = module.init_from_data(key, method.config, data.dataset)
    else:
        params = module.init(key, method.config)
    if run.init_from is not None:
        loaded, meta = checkpoint.load(run.init_from)
        if meta.get("config") and model_fields(method.config, _saved_config(method, meta)) != \
                model_fields(method.config, cfg_dict):
            raise TrainError(f"{run.init_from}: weights were trained with config {meta['config']}; this run is "
                             f"{method.name!r} with {cfg_dict}")
        params = restore_like(params, loaded, where=run.init_from)
    groups = param_groups(method, run, params)
    state = State(params=params, opt_state=optimizer_state(groups, params), ema=params if run.ema else None)
    ckpt_dir = out_dir / CHECKPOINT_DIR
    if run.resume and (ckpt_dir / checkpoint.PARAMS_FILE).is_file():
        loaded, meta = checkpoint.load(ckpt_dir)
        if meta.get("method") != method.name or _saved_config(method, meta) != cfg_dict:
            raise TrainError(f"{ckpt_dir}: checkpoint is for method {meta.get('method')!r} with config "
                             f"{meta.get('config')}; this run is {method.name!r} with {cfg_dict}. "
                             "Use a new --out or the same settings.")
        template = {"params": params, "opt_state": state.opt_state}
        if run.ema and "ema" in loaded:
            template["ema"] = params
        restored = restore_like(template, loaded if "ema" in template else
                                {k: v for k, v in loaded.items() if k != "ema"}, where=str(ckpt_dir))
        state.params, state.opt_state = restored["params"], restored["opt_state"]
        if run.ema:
            state.ema = restored.get("ema", state.params)
        state.step, state.history = int(meta["step"]), list(meta.get("history", []))
        state.bad_steps = int(meta.get("bad_steps", 0))
        state.validation = [v for v in meta.get("validation", []) if v["step"] <= state.step]
    best_dir = out_dir / BEST_DIR
    if run.val_data is not None and run.resume and (best_dir / checkpoint.CONFIG_FILE).is_file():
        state.best = checkpoint.load(best_dir)[1].get("validation")
    return state, groups


# -- one step ---------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=8)
def _ema_fn(decay: float):
    """``(e, p) -> decay * e + (1 - decay) * p`` leaf by leaf, jitted (the trainer's weight average)."""
    return jax.jit(lambda e, p: jax.tree_util.tree_map(lambda a, b: decay * a + (1.0 - decay) * b, e, p))


def step_fn(method: Method, tc: TrainConfig, group: str | None = None, keys: tuple[str, ...] | None = None):
    """The jitted training step ``(params, opt_state, batch) -> (params, opt_state, loss, finite)``,
    cached on the resolved method and ``tc``'s optimizer settings, so repeated runs with the same
    settings compile once.

    ``loss`` may return a scalar or ``(scalar, aux)``; an ``aux`` dict with ``"updates"`` (a nested dict
    of params leaves, e.g. BatchNorm running statistics from the forward pass, `jaxdenoise.nn.state`)
    replaces those leaves after the optimizer step. The gradient is clipped to
    ``clip_norm`` (global L2 norm) when set. With ``group`` (a parameter group, `param_groups`), the
    step differentiates ``loss(..., group=group)`` with respect to the top-level params ``keys`` of
    that group only and updates them with the group's optimizer state (``opt_state`` is then that
    group's). A non-finite loss or gradient keeps the params and optimizer state as they were."""
    return _compiled_step(method, tc.optimizer_settings(), group, keys)


@functools.lru_cache(maxsize=16)
def _compiled_step(method: Method, settings: tuple, group: str | None, keys: tuple[str, ...] | None):
    module, config = method.module, method.config
    tc = TrainConfig(**dict(zip(OPTIMIZER_FIELDS, settings)))
    _, opt_update = make_optimizer(tc)
    frozen = tuple(getattr(module, "FROZEN", ()))

    def loss_fn(sub, p, b):
        full = {**p, **sub} if group is not None else sub
        out = module.loss(full, b, config) if group is None else module.loss(full, b, config, group=group)
        return (out[0], out[1]) if isinstance(out, tuple) else (out, None)

    @jax.jit
    def step(p, s, b):
        trained = {k: p[k] for k in keys} if group is not None else p
        (value, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(trained, p, b)
        if tc.clip_norm is not None:
            from .solvers.optim import clip_by_global_norm

            grads, _ = clip_by_global_norm(grads, tc.clip_norm)
        finite = jnp.isfinite(value)
        for g in jax.tree_util.tree_leaves(grads):
            finite = finite & jnp.all(jnp.isfinite(g))
        new_p, new_s = opt_update(grads, s, trained)
        if group is not None:
            new_p = {**p, **new_p}
        if frozen:
            new_p = {**new_p, **{k: p[k] for k in frozen}}
        updates = aux.get("updates") if isinstance(aux, dict) else None
        if updates:
            try:
                new_p = merge_updates(new_p, updates)
            except ValueError as e:
                raise MethodError(f"method '{method.name}': loss aux updates do not fit the params: {e}") from None
        # A non-finite step keeps the previous params and optimizer state (module docstring).
        keep = lambda a, b_: jnp.where(finite, a, b_)
        return jax.tree_util.tree_map(keep, new_p, p), jax.tree_util.tree_map(keep, new_s, s), value, finite

    return step


Stepper = Callable[[State, Any], tuple[float, bool]]


def make_stepper(method: Method, run: TrainConfig, groups: list[Group]) -> Stepper:
    """``advance(state, batch) -> (loss, finite)``: one step at ``state.step`` (with parameter groups,
    group ``state.step mod n``), in place: params and optimizer state, the loss history and the
    weight average after a finite step, the count of skipped ones, and the step counter."""
    fns = [step_fn(method, g.train, g.name, g.keys) for g in groups]
    average = _ema_fn(run.ema) if run.ema else None

    def advance(state: State, batch: Any) -> tuple[float, bool]:
        i = state.step % len(groups)
        if groups[i].name is None:
            state.params, state.opt_state, value, ok = fns[i](state.params, state.opt_state, batch)
        else:
            name = groups[i].name
            state.params, state.opt_state[name], value, ok = fns[i](state.params, state.opt_state[name], batch)
        value, ok = float(value), bool(ok)
        if ok:
            state.history.append(value)
            if average is not None:
                state.ema = average(state.ema, state.params)
        else:
            state.bad_steps += 1
        state.step += 1
        return value, ok

    return advance


# -- validation and checkpoints -----------------------------------------------------------------------

def validation_round(method: Method, frames: list[dict], state: State) -> dict:
    """The validation record of ``state`` at its step: `validate` of what it ships (the weight
    average when kept, with the last iterate's score as ``raw``) and the seconds it took."""
    t = time.perf_counter()
    record = {"step": state.step, **validate(method, state.shipped, frames)}
    if state.ema is not None:
        raw = validate(method, state.params, frames)
        record["raw"] = {k: raw[k] for k in ("relmse", "relmse_geomean", "per_spp", "loss") if k in raw}
    record["seconds"] = time.perf_counter() - t
    return record


def save_checkpoint(out_dir: Path, method: Method, run: TrainConfig, state: State) -> None:
    """``out_dir/checkpoint``: everything `initial_state` resumes from (atomic)."""
    stored = {"params": state.params, "opt_state": state.opt_state}
    if state.ema is not None:
        stored["ema"] = state.ema
    checkpoint.save(out_dir / CHECKPOINT_DIR, stored, method.config,
                    extra={"method": method.name, "step": state.step, "history": state.history,
                           "bad_steps": state.bad_steps, "train": dataclasses.asdict(run), "seed": int(run.seed),
                           "validation": state.validation}, embed_meta=True)


def save_weights(folder: Path, method: Method, run: TrainConfig, data: TrainingData, state: State,
                 **extra: Any) -> None:
    """What ``state`` ships, loadable like shipped weights, with where it came from and how many
    non-finite steps the run skipped (``bad_steps``)."""
    checkpoint.save(folder, state.shipped, method.config,
                    extra={"method": method.name, "steps": state.step, "data": str(data.source),
                           "seed": int(run.seed), "bad_steps": state.bad_steps, **extra})
    if state.validation:
        write_json(folder / SELECTION_FILE, selection_curve(method, run, state))


def selection_curve(method: Method, run: TrainConfig, state: State) -> dict:
    """``selection.json`` beside saved weights: every validation record of the run so far and the
    step ``best/`` holds, the curve a weights README points to when the weights ship."""
    return {"method": method.name, "val_data": None if run.val_data is None else str(run.val_data),
            "val_spps": run.val_spps, "metric": SELECT[run.select][1], "select": SELECT[run.select][0],
            "selected_step": None if state.best is None else state.best["step"],
            "bad_steps": state.bad_steps, "validation": state.validation}


# -- devices and validation frames ------------------------------------------------------------------

def shard_batch(batch: Any, devices: list | None = None) -> Any:
    """Data parallelism (docs/architecture.md "Methods": the trainer runs over all local devices): every batch
    leaf whose leading axis divides evenly is split along it over ``devices`` (default: all local
    ones), the rest is replicated; params and optimizer state stay replicated, and XLA reduces the
    gradients across devices inside the jitted step. With one device this is a plain transfer.
    Multi-host: start each process with ``jax.distributed.initialize()`` first (coordinator address,
    process count and id from the environment or arguments); ``jax.devices()`` then spans every
    host and the same code runs unchanged (not testable on this machine)."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = list(devices or jax.local_devices())
    if len(devices) == 1:
        return jax.device_put(batch, devices[0])
    mesh = Mesh(np.array(devices), ("data",))
    split, whole = NamedSharding(mesh, PartitionSpec("data")), NamedSharding(mesh, PartitionSpec())

    def put(x):
        x = np.asarray(x)
        return jax.device_put(x, split if x.ndim and x.shape[0] % len(devices) == 0 else whole)

    return jax.tree_util.tree_map(put, batch)


def load_validation(method: Any, data_dir: str | Path, spps: Any = None) -> list[dict]:
    """The validation frames of ``data_dir``: for every shot (`data.discover`) and sampling rate
    (all rates, or those in ``spps``), its first render in name order, read with the buffers
    ``method`` uses: ``{"file", "spp", "buffers", "reference"}``. A sequence (``frame_XXXX/`` shots)
    gives one entry per sampling rate holding the whole video, ``{"file", "spp", "frames",
    "references"}`` (its first render name at that rate in every frame), so that `validate` steps
    recurrent and windowed methods through it."""
    from .inference import prepare

    wanted = None if spps is None else {int(s) for s in spps}
    if Path(data_dir).suffix == ".npz":
        return _validation_from_export(method, Path(data_dir), wanted)
    from .data import discover, renders_by_spp, sequences
    from .io import read_buffers, read_image

    def load(path, ref):
        buffers, _ = read_buffers(path)
        if buffers.shape != ref.shape[:2]:
            raise TrainError(f"{path}: size {buffers.shape} differs from its reference {ref.shape[:2]}")
        try:
            return prepare(method, buffers)
        except ValueError as e:
            raise TrainError(f"{path}: cannot validate {method.name} on it: {e}") from None

    seqs, singles = sequences(discover(data_dir))
    frames = []
    for shot in singles:
        ref = None
        for spp, renders in sorted(renders_by_spp(shot, wanted).items()):
            if ref is None:
                ref = np.asarray(read_image(shot.reference), np.float32)[..., :3]
            frames.append({"file": str(renders[0].path), "spp": spp, "buffers": load(renders[0].path, ref),
                           "reference": ref})
    for seq in seqs:
        by_spp = [renders_by_spp(s, wanted) for s in seq.shots]
        refs = [np.asarray(read_image(s.reference), np.float32)[..., :3] for s in seq.shots]
        for spp in sorted(set.intersection(*(set(b) for b in by_spp))):
            paths = [b[spp][0].path for b in by_spp]
            frames.append({"file": str(seq.folder), "spp": spp, "references": refs,
                           "frames": [load(p, r) for p, r in zip(paths, refs)]})
    if not frames:
        raise TrainError(f"{data_dir}: no validation render" + (f" at spp {sorted(wanted)}" if wanted else ""))
    return frames


def _validation_from_export(method: Any, path: Path, wanted: set | None) -> list[dict]:
    """Validation frames from an export of whole frames (`pipeline.Cache.export(whole=True)`): the
    machine that trains may have no OpenImageIO (a GPU machine)."""
    from .inference import prepare
    from .buffers import Buffers
    from .pipeline import load_export

    if not path.is_file():
        raise TrainError(f"{path}: no such validation export")
    ex = load_export(path)
    if not ex.summary.get("whole"):
        raise TrainError(f"{path}: holds random crops; validation needs whole frames (export with whole=True)")

    def load(i):
        where = f"{path}#{i}"
        fields = {f: v[i] for f, v in ex.items.items() if f not in ("reference", "spp")}
        try:
            return prepare(method, Buffers(**fields, spp=int(ex.items["spp"][i])), where=where)
        except ValueError as e:
            raise TrainError(f"{where}: cannot validate {method.name} on it: {e}") from None

    frames = []
    in_video = set()
    for v in ex.videos:  # whole videos: the first noise instance of every frame, in time order
        first = v[min(v)][0]
        spp = int(ex.items["spp"][first])
        in_video.update(i for ids in v.values() for i in ids)
        if wanted is None or spp in wanted:
            ids = [v[t][0] for t in sorted(v)]
            frames.append({"file": f"{path}#video{int(ex.index['video'][first])}", "spp": spp,
                           "frames": [load(i) for i in ids], "references": [ex.items["reference"][i] for i in ids]})
    for i in range(ex.count):
        spp = int(ex.items["spp"][i])
        if i in in_video or (wanted is not None and spp not in wanted):
            continue
        frames.append({"file": f"{path}#{i}", "spp": spp, "buffers": load(i), "reference": ex.items["reference"][i]})
    if not frames:
        raise TrainError(f"{path}: no validation frame" + (f" at spp {sorted(wanted)}" if wanted else ""))
    return frames


def validate(method: Any, params: Any, frames: list[dict]) -> dict:
    """Mean RelMSE of ``method`` with ``params`` over ``frames`` (`load_validation`), overall and
    per sampling rate, their geometric mean (``relmse_geomean``), mean SSIM beside it (None when every frame is
    under SSIM's window) and the halo pixels (`metrics.halo_pixels`, every pixel counted) summed over the
    frames, overall (``halo``) and per rate; a
    sequence entry runs through the sequence driver (state carried, neighbours read) and counts each
    of its frames. A non-finite output scores RelMSE ``inf`` (never the best)."""
    from . import metrics
    from .inference import inference_fn
    from .sequence import run

    fn = inference_fn(method)
    errs: dict[Any, list[float]] = {}
    halos: dict[Any, int] = {}
    ssims: list[float] = []
    losses: list[float] = []
    vloss = unsupervised_loss(method)

    def score(out, ref, spp):
        e = float(metrics.relmse(out, ref))
        errs.setdefault(spp, []).append(e if math.isfinite(e) else math.inf)
        halos[spp] = halos.get(spp, 0) + metrics.halo_pixels(out, ref)
        if min(np.shape(ref)[-3:-1]) >= metrics.SSIM_WIN:  # smaller frames have no SSIM
            ssims.append(float(metrics.ssim(jnp.nan_to_num(jnp.asarray(out, jnp.float32)), ref)))

    for f in frames:
        if "frames" in f:
            for out, ref in zip(run(method, params, f["frames"]), f["references"]):
                score(out, ref, f["spp"])
        else:
            score(fn(params, f["buffers"]), f["reference"], f["spp"])
            if vloss is not None:
                v = float(vloss(params, f["buffers"]))
                losses.append(v if math.isfinite(v) else math.inf)
    every = [e for es in errs.values() for e in es]
    geomean = float(np.exp(np.mean(np.log(np.maximum(every, 1e-30))))) if all(map(math.isfinite, every)) else math.inf
    record = {"relmse": float(np.mean(every)), "relmse_geomean": geomean,
              "ssim": float(np.mean(ssims)) if ssims else None,
              "per_spp": {str(k): float(np.mean(v))
                          for k, v in sorted(errs.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))},
              "halo": int(sum(halos.values())),
              "halo_per_spp": {str(k): v
                               for k, v in sorted(halos.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))}}
    if losses:
        record["loss"] = float(np.mean(losses))
    return record


def unsupervised_loss(method: Any) -> Callable | None:
    """The method's ``validation_loss`` (module docstring) jitted as ``f(params, buffers)``, or None;
    one compiled function per (loss, config), so every validation round of a run reuses it."""
    vloss = getattr(method.module, "validation_loss", None)
    return None if vloss is None else _jitted_loss(vloss, method.config)


@functools.lru_cache(maxsize=8)
def _jitted_loss(vloss: Callable, config: Any) -> Callable:
    return jax.jit(functools.partial(vloss, config=config))


def summary_line(summary: dict) -> str:
    line = (f"trained {summary['method']}: {summary['steps_done']} steps "
            f"(+{summary['steps_this_run']} this run) in {summary['seconds']:.1f} s, "
            f"final loss {summary['final_loss']:.5g}, weights in {summary['weights']}")
    if summary.get("best") is not None:
        line += (f"; best validation RelMSE {summary['best']['relmse']:.5g} at step {summary['best']['step']}"
                 f" in {summary['best_weights']}")
    return line


def _final(history: list[float], window: int = 10) -> float:
    """Mean loss of the last ``window`` steps (one mini-batch is noisy); NaN before any step."""
    if not history:
        return math.nan
    return float(np.mean(history[-window:]))


# -- the loop -------------------------------------------------------------------------------------------

def train(method: Method, data: str | os.PathLike | TrainingData, out_dir: str | os.PathLike,
          run: TrainConfig | None = None) -> dict:
    """Train the resolved ``method`` on ``data`` (a folder or export, or `load_data`'s result) with
    ``run`` (default: `TrainConfig.for_method(method)`); writes checkpoints and weights under
    ``out_dir`` (module docstring) and returns the summary."""
    if not method.trainable:
        raise MethodError(f"method '{method.name}' cannot be trained here: its module needs loss, "
                          "make_dataset and batch (see jaxdenoise.train)")
    run = TrainConfig.for_method(method) if run is None else run
    if run.select == "loss" and unsupervised_loss(method) is None:
        raise TrainError(f"select='loss' needs an unsupervised validation loss; method '{method.name}' has none "
                         "(its module defines no validation_loss): select by 'mean' or 'geomean'")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    compile_cache.enable()  # a resumed run compiles its steps from the persistent cache
    source = data.source if isinstance(data, TrainingData) else Path(data)
    write_json(out_dir / "train_config.json",
               {"method": method.name, "config": checkpoint.config_to_dict(method.config),
                "train": dataclasses.asdict(run), "data": str(source), "seed": int(run.seed),
                "val_data": run.val_data, "val_spps": None if run.val_spps is None else list(run.val_spps),
                "init_from": run.init_from})

    # setup
    t0 = time.perf_counter()
    frames = load_validation(method, run.val_data, run.val_spps) if run.val_data is not None else None
    if not isinstance(data, TrainingData):
        data = load_data(method, source, progress=run.progress)
    state, groups = initial_state(method, data, run, out_dir)
    start = state.step
    advance = make_stepper(method, run, groups)
    bar = None
    if run.progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=run.steps, initial=min(start, run.steps), desc=f"train {method.name}", unit="step")

    def validate_now() -> None:
        if frames is None or (state.validation and state.validation[-1]["step"] == state.step):
            return
        record = validation_round(method, frames, state)
        state.validation.append(record)
        key = SELECT[run.select][0]
        better = state.best is None or record[key] < state.best.get(key, math.inf)  # (older records lack a key)
        if better and selectable(run.select, state.validation[0], record):
            state.best = record
            save_weights(out_dir / BEST_DIR, method, run, data, state, val_data=run.val_data, validation=record)
        else:  # the curve beside best/ runs on past the step it holds
            write_json(out_dir / BEST_DIR / SELECTION_FILE, selection_curve(method, run, state))
        if bar is not None:
            bar.write(f"step {state.step}: validation RelMSE {record['relmse']:.5g}, geometric mean "
                      f"{record['relmse_geomean']:.5g} (best by {key} {state.best.get(key, math.inf):.5g} "
                      f"at step {state.best['step']}; {record['seconds']:.0f} s)")

    # loop
    t_loop, bad_run = time.perf_counter(), 0
    try:
        with _Batches(method, data, run) as batches:
            if run.init_from is not None and start == 0:
                validate_now()  # the starting weights' score: fine-tuning keeps them unless it beats them
            while state.step < run.steps:
                value, ok = advance(state, batches.get(state.step))
                bad_run = 0 if ok else bad_run + 1
                if bad_run >= run.max_bad_steps:
                    raise TrainError(f"{bad_run} non-finite steps in a row at step {state.step - 1}; "
                                     "training diverged")
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{value:.4g}")
                if run.validate_every and state.step % run.validate_every == 0:
                    validate_now()
                if state.step % run.checkpoint_every == 0:
                    save_checkpoint(out_dir, method, run, state)
                if run.time_limit is not None and time.perf_counter() - t_loop > run.time_limit:
                    break
            validate_now()
    finally:
        if bar is not None:
            bar.close()

    # finish
    save_checkpoint(out_dir, method, run, state)
    save_weights(out_dir / WEIGHTS_DIR, method, run, data, state, final_loss=_final(state.history))
    summary = {"method": method.name, "steps_done": state.step, "steps_this_run": state.step - start,
               "final_loss": _final(state.history), "seconds": time.perf_counter() - t0,
               "bad_steps": state.bad_steps, "out": str(out_dir), "weights": str(out_dir / WEIGHTS_DIR)}
    if frames is not None:
        summary.update(best=state.best, best_weights=str(out_dir / BEST_DIR), validation=state.validation)
    summary["line"] = summary_line(summary)
    write_json(out_dir / "summary.json", summary)
    return summary
