"""The generic training loop behind ``jaxdenoise train METHOD`` (DESIGN.md "Methods", "Command line").

``train(method_name, data_dir, out_dir, *, resume=False, steps=None, seed=0, progress=True) -> dict``

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
  format as ``weights/``, with the step and the scores in its ``config.json``.

Validation (``val_data`` and ``validate_every > 0``): every ``validate_every`` steps and at the end,
the current params denoise one render per shot and sampling rate of ``val_data`` (the first noise
instance; ``val_spps`` limits the rates) through the method's full inference path (`api.inference_fn`,
so post-processing such as LBF's spike removal is included), and the score is the mean RelMSE
(`metrics.relmse`) over those frames. Mini-batch losses are too noisy to pick weights by, and a run
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

from . import checkpoint
from .fsutil import write_json
from .methods import MethodError, get
from .nn.state import merge_updates

__all__ = ["TrainConfig", "TrainError", "train", "restore_like", "make_optimizer", "model_fields", "summary_line",
           "load_validation", "validate", "shard_batch"]

CHECKPOINT_DIR = "checkpoint"
WEIGHTS_DIR = "weights"
BEST_DIR = "best"


# Batches drawn ahead on worker threads (the batch of step t depends on (seed, t) only).
PREFETCH = 2


def batch_workers() -> int:
    """Threads that draw batches: one where XLA computes on the same CPU cores; beside an
    accelerator, half the host's cores (at most 8), since crops and augmentations are array copies
    that release the GIL and the device can outrun one thread."""
    if jax.default_backend() == "cpu":
        return 1
    return max(1, min(8, (os.cpu_count() or 2) // 2))


class TrainError(RuntimeError):
    """Training cannot start or continue (bad data, config mismatch on resume, diverged)."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimization settings (method defaults come from the module's ``TRAIN`` dict)."""

    steps: int = 1000
    optimizer: str = "adam"  # "adam" or "rprop" (jaxdenoise.solvers.optim)
    learning_rate: float = 1e-3  # Adam step size; for RPROP the initial step size
    adam_b1: float = 0.9  # Adam's moment decays (Chaitanya 2017: 0.9 / 0.99; Guo 2019: 0.5 / 0.999)
    adam_b2: float = 0.999
    schedule: str = "constant"  # Adam's step size over steps: solvers.optim.schedule (SCHEDULES)
    schedule_every: int = 1  # the schedule's step count (ramp length, decay interval)
    schedule_factor: float = 1.0  # the schedule's factor (ramp factor, decay factor)
    clip_norm: float | None = None  # clip the gradient's global L2 norm to this (None: off)
    checkpoint_every: int = 25
    max_bad_steps: int = 20
    time_limit: float | None = None  # seconds; stop (with a checkpoint) when exceeded
    validate_every: int = 0  # steps between validations (0: only at the end, when val_data is given)
    ema: float = 0.0  # decay of an exponential moving average of the params (0: off; module docstring)


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


def _optimizer_key(tc: TrainConfig) -> tuple:
    """The fields of ``tc`` that change the compiled step (a cache key)."""
    return (tc.optimizer, tc.learning_rate, tc.adam_b1, tc.adam_b2, tc.schedule, tc.schedule_every,
            tc.schedule_factor, tc.clip_norm)


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
    True}``: loss weights, schedules), in which weights given to ``init_from`` may differ."""
    training = {f.name for f in dataclasses.fields(config) if f.metadata.get("training")}
    return {k: v for k, v in cfg_dict.items() if not k.startswith("train_") and k not in training}


@functools.lru_cache(maxsize=8)
def _ema_fn(decay: float):
    """``(e, p) -> decay * e + (1 - decay) * p`` leaf by leaf, jitted (the trainer's weight average)."""
    return jax.jit(lambda e, p: jax.tree_util.tree_map(lambda a, b: decay * a + (1.0 - decay) * b, e, p))


@functools.lru_cache(maxsize=16)
def _step_fn(method_name: str, config: Any, opt_key: tuple, group: str | None = None,
             keys: tuple[str, ...] | None = None):
    """The jitted training step, cached so repeated runs with the same settings compile once.

    ``loss`` may return a scalar or ``(scalar, aux)``; an ``aux`` dict with ``"updates"`` (a nested dict
    of params leaves, e.g. BatchNorm running statistics from the forward pass, `jaxdenoise.nn.state`)
    replaces those leaves after the optimizer step. The gradient is clipped to
    ``clip_norm`` (global L2 norm) when set. With ``group`` (a parameter group, `param_groups`), the
    step differentiates ``loss(..., group=group)`` with respect to the top-level params ``keys`` of
    that group only and updates them with the group's optimizer state."""
    module = get(method_name, config).module
    fields = ("optimizer", "learning_rate", "adam_b1", "adam_b2", "schedule", "schedule_every",
              "schedule_factor", "clip_norm")
    tc = TrainConfig(**dict(zip(fields, opt_key)))
    _, opt_update = make_optimizer(tc)
    frozen = tuple(getattr(module, "FROZEN", ()))

    def loss_fn(sub, p, b):
        full = {**p, **sub} if group is not None else sub
        out = module.loss(full, b, config) if group is None else module.loss(full, b, config, group=group)
        return (out[0], out[1]) if isinstance(out, tuple) else (out, None)

    @jax.jit
    def step_fn(p, s, b):
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
                raise MethodError(f"method '{method_name}': loss aux updates do not fit the params: {e}") from None
        # A non-finite step keeps the previous params and optimizer state (module docstring).
        keep = lambda a, b_: jnp.where(finite, a, b_)
        return jax.tree_util.tree_map(keep, new_p, p), jax.tree_util.tree_map(keep, new_s, s), value, finite

    return step_fn


def _param_groups(module: Any, config: Any, params: Any, tc: TrainConfig) -> dict | None:
    """``{group: (top-level params keys, TrainConfig)}`` when the method declares
    ``param_groups(config)`` (and optionally ``group_train(config)``: per-group TrainConfig overrides,
    e.g. its own optimizer and step size); None otherwise. Every group names existing, non-FROZEN
    keys, and no key is in two groups."""
    fn = getattr(module, "param_groups", None)
    if fn is None:
        return None
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
    out = {}
    for g, keys in declared.items():
        try:
            gtc = dataclasses.replace(tc, **overrides.get(g, {}))
        except TypeError as e:
            raise TrainError(f"group_train['{g}']: {e}") from None
        out[g] = (keys, gtc)
    return out


def shard_batch(batch: Any, devices: list | None = None) -> Any:
    """Data parallelism (DESIGN.md "Methods": the trainer runs over all local devices): every batch
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
    from .api import prepare

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
    from .api import prepare
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
    per sampling rate, and mean SSIM beside it (None when every frame is under SSIM's window); a
    sequence entry runs through the sequence driver (state carried, neighbours read) and counts each
    of its frames. A non-finite output scores RelMSE ``inf`` (never the best)."""
    from . import metrics
    from .api import inference_fn
    from .sequence import run

    fn = inference_fn(method)
    errs: dict[Any, list[float]] = {}
    ssims: list[float] = []

    def score(out, ref, spp):
        e = float(metrics.relmse(out, ref))
        errs.setdefault(spp, []).append(e if math.isfinite(e) else math.inf)
        if min(np.shape(ref)[-3:-1]) >= metrics.SSIM_WIN:  # smaller frames have no SSIM
            ssims.append(float(metrics.ssim(jnp.nan_to_num(jnp.asarray(out, jnp.float32)), ref)))

    for f in frames:
        if "frames" in f:
            for out, ref in zip(run(method, params, f["frames"]), f["references"]):
                score(out, ref, f["spp"])
        else:
            score(fn(params, f["buffers"]), f["reference"], f["spp"])
    every = [e for es in errs.values() for e in es]
    return {"relmse": float(np.mean(every)), "ssim": float(np.mean(ssims)) if ssims else None,
            "per_spp": {str(k): float(np.mean(v))
                    for k, v in sorted(errs.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))}}


def summary_line(summary: dict) -> str:
    line = (f"trained {summary['method']}: {summary['steps_done']} steps "
            f"(+{summary['steps_this_run']} this run) in {summary['seconds']:.1f} s, "
            f"final loss {summary['final_loss']:.5g}, weights in {summary['weights']}")
    if summary.get("best") is not None:
        line += (f"; best validation RelMSE {summary['best']['relmse']:.5g} at step {summary['best']['step']}"
                 f" in {summary['best_weights']}")
    return line


def _saved_config(module: Any, meta: dict) -> Any:
    """A checkpoint's config with the fields it predates filled by their defaults (a config field
    added later, with a default that keeps the old behaviour, must not orphan older runs and
    weights); as saved when it does not build (an unknown key: then it differs, as it should)."""
    saved = meta.get("config")
    try:
        return checkpoint.config_to_dict(checkpoint.config_from_dict(module.Config, saved))
    except (TypeError, ValueError):
        return saved


def train(method_name: str, data_dir: str | Path, out_dir: str | Path, *, resume: bool = False,
          steps: int | None = None, seed: int = 0, progress: bool = True, config: Any = None,
          train_config: TrainConfig | None = None, dataset: Any = None, val_data: str | Path | None = None,
          val_spps: Any = None, init_from: str | Path | None = None, **train_overrides: Any) -> dict:
    """Train a registered method on ``data_dir``; writes checkpoints and weights under ``out_dir``.

    ``steps`` is the total number of steps of the run (a resumed run continues up to it);
    ``config`` replaces the method's default config; ``train_config`` / ``train_overrides``
    (fields of `TrainConfig`) adjust the optimization; ``dataset`` reuses the result of an earlier
    ``make_dataset`` (experiments that train several variants on the same data); ``val_data`` /
    ``val_spps`` turn on validation (module docstring); ``init_from`` (a weights folder of the same
    method and model config, e.g. shipped weights; training-only fields may differ, `model_fields`)
    replaces the initial params, frozen entries included, so a run can fine-tune them (ignored when
    resuming). Returns the summary.
    """
    method = get(method_name, config)
    module = method.module
    if not method.trainable:
        raise MethodError(f"method '{method_name}' cannot be trained here: its module needs loss, "
                          "make_dataset and batch (see jaxdenoise.train)")
    base = dataclasses.asdict(train_config) if train_config is not None else dict(getattr(module, "TRAIN", {}))
    base.update(train_overrides)
    if steps is not None:
        base["steps"] = int(steps)
    tc = TrainConfig(**base)
    if tc.steps < 0:
        raise TrainError(f"steps must be >= 0, got {tc.steps}")
    if tc.validate_every < 0:
        raise TrainError(f"validate_every must be >= 0, got {tc.validate_every}")
    if not 0.0 <= tc.ema < 1.0:
        raise TrainError(f"ema must be in [0, 1) (0: off), got {tc.ema}")
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg_dict = checkpoint.config_to_dict(method.config)
    resolved = {"method": method_name, "config": cfg_dict, "train": dataclasses.asdict(tc),
                "data": str(data_dir), "seed": int(seed),
                "val_data": None if val_data is None else str(val_data),
                "val_spps": None if val_spps is None else [int(x) for x in val_spps],
                "init_from": None if init_from is None else str(init_from)}
    write_json(out_dir / "train_config.json", resolved)

    t0 = time.perf_counter()
    val_frames = load_validation(method, val_data, val_spps) if val_data is not None else None
    if dataset is None:
        quiet = {} if progress or "progress" not in inspect.signature(module.make_dataset).parameters \
            else {"progress": False}  # --quiet silences the data pass too
        dataset = module.make_dataset(data_dir, method.config, **quiet)
    key = jax.random.PRNGKey(seed)
    if hasattr(module, "init_from_data"):
        params = module.init_from_data(key, method.config, dataset)
    else:
        params = module.init(key, method.config)
    if init_from is not None:
        loaded, meta = checkpoint.load(init_from)
        if meta.get("config") and model_fields(method.config, _saved_config(module, meta)) != \
                model_fields(method.config, cfg_dict):
            raise TrainError(f"{init_from}: weights were trained with config {meta['config']}; this run is "
                             f"{method_name!r} with {cfg_dict}")
        params = restore_like(params, loaded, where=str(init_from))
    groups = _param_groups(module, method.config, params, tc)
    if groups is None:
        opt_state = make_optimizer(tc)[0](params)
    else:
        opt_state = {g: make_optimizer(gtc)[0]({k: params[k] for k in keys}) for g, (keys, gtc) in groups.items()}
    start, history, bad_total, val_history = 0, [], 0, []
    ema_params = params if tc.ema else None
    ckpt_dir = out_dir / CHECKPOINT_DIR
    if resume and (ckpt_dir / checkpoint.PARAMS_FILE).is_file():
        loaded, meta = checkpoint.load(ckpt_dir)
        if meta.get("method") != method_name or _saved_config(module, meta) != cfg_dict:
            raise TrainError(f"{ckpt_dir}: checkpoint is for method {meta.get('method')!r} with config "
                             f"{meta.get('config')}; this run is {method_name!r} with {cfg_dict}. "
                             "Use a new --out or the same settings.")
        template = {"params": params, "opt_state": opt_state}
        if tc.ema and "ema" in loaded:
            template["ema"] = params
        state = restore_like(template, loaded if "ema" in template else {k: v for k, v in loaded.items() if k != "ema"},
                             where=str(ckpt_dir))
        params, opt_state = state["params"], state["opt_state"]
        if tc.ema:
            ema_params = state.get("ema", params)
        start, history, bad_total = int(meta["step"]), list(meta.get("history", [])), int(meta.get("bad_steps", 0))
        val_history = [v for v in meta.get("validation", []) if v["step"] <= start]
    best_dir = out_dir / BEST_DIR
    best = None
    if val_frames is not None and resume and (best_dir / checkpoint.CONFIG_FILE).is_file():
        best = checkpoint.load(best_dir)[1].get("validation")
    if groups is None:
        step_fn = _step_fn(method_name, method.config, _optimizer_key(tc))
    else:
        order = list(groups)
        group_fns = {g: _step_fn(method_name, method.config, _optimizer_key(gtc), g, keys)
                     for g, (keys, gtc) in groups.items()}

    ema_fn = _ema_fn(tc.ema) if tc.ema else None

    def shipped():  # what validation scores and best/ + weights/ hold
        return params if ema_params is None else ema_params

    def save(step: int) -> None:
        state = {"params": params, "opt_state": opt_state}
        if ema_params is not None:
            state["ema"] = ema_params
        checkpoint.save(ckpt_dir, state, method.config,
                        extra={"method": method_name, "step": step, "history": history,
                               "bad_steps": bad_total, "train": dataclasses.asdict(tc), "seed": int(seed),
                               "validation": val_history})

    def run_validation(step: int) -> None:
        nonlocal best
        if val_frames is None or (val_history and val_history[-1]["step"] == step):
            return
        t = time.perf_counter()
        score = {"step": step, **validate(method, shipped(), val_frames)}
        if ema_params is not None:
            raw = validate(method, params, val_frames)
            score["raw"] = {"relmse": raw["relmse"], "per_spp": raw["per_spp"]}
        score["seconds"] = time.perf_counter() - t
        val_history.append(score)
        if best is None or score["relmse"] < best["relmse"]:
            best = score
            checkpoint.save(best_dir, shipped(), method.config,
                            extra={"method": method_name, "steps": step, "data": str(data_dir), "seed": int(seed),
                                   "val_data": str(val_data), "validation": score})
        if bar is not None:
            bar.write(f"step {step}: validation RelMSE {score['relmse']:.5g} (best {best['relmse']:.5g} "
                      f"at step {best['step']}; {score['seconds']:.0f} s)")

    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=tc.steps, initial=min(start, tc.steps), desc=f"train {method_name}", unit="step")
    bad_run = 0
    step = start
    t_loop = time.perf_counter()

    def draw(s: int) -> Any:  # a pure function of (seed, step): the same batches on resume
        return module.batch(dataset, s, method.config, np.random.default_rng([int(seed), s]))

    # The next batches are drawn on worker threads while the device runs the current step.
    workers = batch_workers()
    ahead = PREFETCH * workers
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="jaxdenoise-batches")
    pending: dict[int, Any] = {}
    try:
        if init_from is not None and start == 0:
            run_validation(0)  # the starting weights' score: fine-tuning keeps them unless it beats them
        for step in range(start, tc.steps):
            for s in range(step, min(step + ahead, tc.steps)):
                if s not in pending:
                    pending[s] = pool.submit(draw, s)
            b = shard_batch(pending.pop(step).result())
            if groups is None:
                params, opt_state, value, ok = step_fn(params, opt_state, b)
            else:  # parameter groups in alternation: step t updates group t mod (number of groups)
                g = order[step % len(order)]
                params, opt_state[g], value, ok = group_fns[g](params, opt_state[g], b)
            value = float(value)
            if bool(ok):
                bad_run = 0
                history.append(value)
                if ema_fn is not None:
                    ema_params = ema_fn(ema_params, params)
            else:
                bad_run += 1
                bad_total += 1
                if bad_run >= tc.max_bad_steps:
                    raise TrainError(f"{bad_run} non-finite steps in a row at step {step}; training diverged")
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{value:.4g}")
            if tc.validate_every and (step + 1) % tc.validate_every == 0:
                run_validation(step + 1)
            if (step + 1) % tc.checkpoint_every == 0:
                save(step + 1)
            if tc.time_limit is not None and time.perf_counter() - t_loop > tc.time_limit:
                step += 1
                break
        else:
            step = max(start, tc.steps)
        run_validation(step)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        if bar is not None:
            bar.close()
    save(step)
    checkpoint.save(out_dir / WEIGHTS_DIR, shipped(), method.config,
                    extra={"method": method_name, "steps": step, "data": str(data_dir), "seed": int(seed),
                           "final_loss": _final(history)})
    summary = {"method": method_name, "steps_done": step, "steps_this_run": step - start,
               "final_loss": _final(history), "seconds": time.perf_counter() - t0,
               "bad_steps": bad_total, "out": str(out_dir), "weights": str(out_dir / WEIGHTS_DIR)}
    if val_frames is not None:
        summary.update(best=best, best_weights=str(best_dir), validation=val_history)
    summary["line"] = summary_line(summary)
    write_json(out_dir / "summary.json", summary)
    return summary


def _final(history: list[float], window: int = 10) -> float:
    """Mean loss of the last ``window`` steps (one mini-batch is noisy); NaN before any step."""
    if not history:
        return math.nan
    return float(np.mean(history[-window:]))
