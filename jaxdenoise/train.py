"""The generic training loop behind ``jaxdenoise train METHOD`` (DESIGN.md "Methods", "Command line").

``train(method_name, data_dir, out_dir, *, resume=False, steps=None, seed=0, progress=True) -> dict``

What a trainable method module provides (besides ``Config``, ``init``, ``apply``, ``loss``):

- ``make_dataset(data_dir, config) -> dataset``: reads and preprocesses the training data once
  (anything that does not depend on the parameters, e.g. LBF's secondary features);
- ``batch(dataset, step, config, rng) -> batch``: the mini-batch of one step; ``rng`` is a
  ``numpy.random.Generator`` seeded from ``(seed, step)``, so a resumed run draws the same
  batches as an uninterrupted one;
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
- ``summary.json``: the returned summary (its ``line`` is the one-line summary the CLI prints).

Non-finite losses or gradients skip the update (counted in the summary); ``max_bad_steps`` of them
in a row stop the run with an error, since the parameters would not move any more.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import checkpoint
from .fsutil import write_json
from .methods import MethodError, get

__all__ = ["TrainConfig", "TrainError", "train", "restore_like", "make_optimizer", "summary_line"]

CHECKPOINT_DIR = "checkpoint"
WEIGHTS_DIR = "weights"


class TrainError(RuntimeError):
    """Training cannot start or continue (bad data, config mismatch on resume, diverged)."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimization settings (method defaults come from the module's ``TRAIN`` dict)."""

    steps: int = 1000
    optimizer: str = "adam"  # "adam" or "rprop" (jaxdenoise.solvers.optim)
    learning_rate: float = 1e-3  # Adam step size; for RPROP the initial step size
    checkpoint_every: int = 25
    max_bad_steps: int = 20
    time_limit: float | None = None  # seconds; stop (with a checkpoint) when exceeded


def make_optimizer(tc: TrainConfig) -> tuple[Callable, Callable]:
    """The pure ``(init, update)`` pair named by ``tc.optimizer``."""
    from .solvers import optim

    if tc.optimizer == "adam":
        return optim.adam(tc.learning_rate)
    if tc.optimizer == "rprop":
        return optim.rprop(step_init=tc.learning_rate)
    raise TrainError(f"optimizer '{tc.optimizer}' is unknown; expected 'adam' or 'rprop'")


def restore_like(template: Any, loaded: Any, *, where: str = "checkpoint") -> Any:
    """Rebuild ``loaded`` (as returned by `checkpoint.load`) in the exact pytree structure of
    ``template`` (tuples, empty containers and ``None`` included), checking every shape."""
    flat = checkpoint.flatten(loaded)
    used: set[str] = set()

    def rec(node: Any, prefix: str) -> Any:
        if isinstance(node, dict):
            return {k: rec(v, f"{prefix}{k}/") for k, v in node.items()}
        if isinstance(node, (list, tuple)):
            items = [rec(v, f"{prefix}#{i}/") for i, v in enumerate(node)]
            if isinstance(node, tuple) and hasattr(node, "_fields"):
                return type(node)(*items)
            return type(node)(items)
        if node is None:
            return None
        key = prefix.rstrip("/")
        if key not in flat:
            raise TrainError(f"{where}: entry '{key}' is missing")
        value = flat[key]
        if tuple(np.shape(value)) != tuple(np.shape(node)):
            raise TrainError(f"{where}: entry '{key}' has shape {np.shape(value)}; expected {np.shape(node)}")
        used.add(key)
        return jnp.asarray(value, dtype=jnp.asarray(node).dtype)

    out = rec(template, "")
    extra = sorted(set(flat) - used)
    if extra:
        raise TrainError(f"{where}: unexpected entries {extra[:5]}{'...' if len(extra) > 5 else ''}")
    return out


@functools.lru_cache(maxsize=16)
def _step_fn(method_name: str, config: Any, optimizer: str, learning_rate: float):
    """The jitted training step, cached so repeated runs with the same settings compile once."""
    module = get(method_name, config).module
    _, opt_update = make_optimizer(TrainConfig(optimizer=optimizer, learning_rate=learning_rate))
    frozen = tuple(getattr(module, "FROZEN", ()))

    def loss_fn(p, b):
        return module.loss(p, b, config)

    @jax.jit
    def step_fn(p, s, b):
        value, grads = jax.value_and_grad(loss_fn)(p, b)
        finite = jnp.isfinite(value)
        for g in jax.tree_util.tree_leaves(grads):
            finite = finite & jnp.all(jnp.isfinite(g))
        new_p, new_s = opt_update(grads, s, p)
        if frozen:
            new_p = {**new_p, **{k: p[k] for k in frozen}}
        # A non-finite step keeps the previous params and optimizer state (module docstring).
        keep = lambda a, b_: jnp.where(finite, a, b_)
        return jax.tree_util.tree_map(keep, new_p, p), jax.tree_util.tree_map(keep, new_s, s), value, finite

    return step_fn


def summary_line(summary: dict) -> str:
    return (f"trained {summary['method']}: {summary['steps_done']} steps "
            f"(+{summary['steps_this_run']} this run) in {summary['seconds']:.1f} s, "
            f"final loss {summary['final_loss']:.5g}, weights in {summary['weights']}")


def train(method_name: str, data_dir: str | Path, out_dir: str | Path, *, resume: bool = False,
          steps: int | None = None, seed: int = 0, progress: bool = True, config: Any = None,
          train_config: TrainConfig | None = None, dataset: Any = None, **train_overrides: Any) -> dict:
    """Train a registered method on ``data_dir``; writes checkpoints and weights under ``out_dir``.

    ``steps`` is the total number of steps of the run (a resumed run continues up to it);
    ``config`` replaces the method's default config; ``train_config`` / ``train_overrides``
    (fields of `TrainConfig`) adjust the optimization; ``dataset`` reuses the result of an earlier
    ``make_dataset`` (experiments that train several variants on the same data). Returns the summary.
    """
    method = get(method_name, config)
    module = method.module
    if not method.trainable or not hasattr(module, "make_dataset") or not hasattr(module, "batch"):
        raise MethodError(f"method '{method_name}' cannot be trained here: its module needs loss, "
                          "make_dataset and batch (see jaxdenoise.train)")
    base = dataclasses.asdict(train_config) if train_config is not None else dict(getattr(module, "TRAIN", {}))
    base.update(train_overrides)
    if steps is not None:
        base["steps"] = int(steps)
    tc = TrainConfig(**base)
    if tc.steps < 0:
        raise TrainError(f"steps must be >= 0, got {tc.steps}")
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg_dict = checkpoint.config_to_dict(method.config)
    resolved = {"method": method_name, "config": cfg_dict, "train": dataclasses.asdict(tc),
                "data": str(data_dir), "seed": int(seed)}
    write_json(out_dir / "train_config.json", resolved)

    t0 = time.perf_counter()
    if dataset is None:
        dataset = module.make_dataset(data_dir, method.config)
    key = jax.random.PRNGKey(seed)
    if hasattr(module, "init_from_data"):
        params = module.init_from_data(key, method.config, dataset)
    else:
        params = module.init(key, method.config)
    opt_init, opt_update = make_optimizer(tc)
    opt_state = opt_init(params)
    start, history, bad_total = 0, [], 0
    ckpt_dir = out_dir / CHECKPOINT_DIR
    if resume and (ckpt_dir / checkpoint.PARAMS_FILE).is_file():
        loaded, meta = checkpoint.load(ckpt_dir)
        if meta.get("method") != method_name or meta.get("config") != cfg_dict:
            raise TrainError(f"{ckpt_dir}: checkpoint is for method {meta.get('method')!r} with config "
                             f"{meta.get('config')}; this run is {method_name!r} with {cfg_dict}. "
                             "Use a new --out or the same settings.")
        state = restore_like({"params": params, "opt_state": opt_state}, loaded, where=str(ckpt_dir))
        params, opt_state = state["params"], state["opt_state"]
        start, history, bad_total = int(meta["step"]), list(meta.get("history", [])), int(meta.get("bad_steps", 0))
    step_fn = _step_fn(method_name, method.config, tc.optimizer, tc.learning_rate)

    def save(step: int) -> None:
        checkpoint.save(ckpt_dir, {"params": params, "opt_state": opt_state}, method.config,
                        extra={"method": method_name, "step": step, "history": history,
                               "bad_steps": bad_total, "train": dataclasses.asdict(tc), "seed": int(seed)})

    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=tc.steps, initial=min(start, tc.steps), desc=f"train {method_name}", unit="step")
    bad_run = 0
    step = start
    t_loop = time.perf_counter()
    try:
        for step in range(start, tc.steps):
            rng = np.random.default_rng([int(seed), step])
            b = module.batch(dataset, step, method.config, rng)
            params, opt_state, value, ok = step_fn(params, opt_state, b)
            value = float(value)
            if bool(ok):
                bad_run = 0
                history.append(value)
            else:
                bad_run += 1
                bad_total += 1
                if bad_run >= tc.max_bad_steps:
                    raise TrainError(f"{bad_run} non-finite steps in a row at step {step}; training diverged")
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{value:.4g}")
            if (step + 1) % tc.checkpoint_every == 0:
                save(step + 1)
            if tc.time_limit is not None and time.perf_counter() - t_loop > tc.time_limit:
                step += 1
                break
        else:
            step = max(start, tc.steps)
    finally:
        if bar is not None:
            bar.close()
    save(step)
    checkpoint.save(out_dir / WEIGHTS_DIR, params, method.config,
                    extra={"method": method_name, "steps": step, "data": str(data_dir), "seed": int(seed),
                           "final_loss": _final(history)})
    summary = {"method": method_name, "steps_done": step, "steps_this_run": step - start,
               "final_loss": _final(history), "seconds": time.perf_counter() - t0,
               "bad_steps": bad_total, "out": str(out_dir), "weights": str(out_dir / WEIGHTS_DIR)}
    summary["line"] = summary_line(summary)
    write_json(out_dir / "summary.json", summary)
    return summary


def _final(history: list[float], window: int = 10) -> float:
    """Mean loss of the last ``window`` steps (one mini-batch is noisy); NaN before any step."""
    if not history:
        return math.nan
    return float(np.mean(history[-window:]))
