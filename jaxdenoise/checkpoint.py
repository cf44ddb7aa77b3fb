"""Parameters on disk: a flat ``.npz`` of the params pytree plus ``config.json`` (never pickle).

Keys in the ``.npz`` are the '/'-joined dict path of each leaf; params are nested dicts (and
lists/tuples, stored with integer keys marked ``#i``) of arrays, as every method's ``init`` returns.
An empty dict or list (a parameter-free layer) is kept as a zero-size marker entry ``#{}`` / ``#[]``,
so the structure round-trips exactly.
Both files are written atomically (`fsutil.atomic_path`).

Reading never trusts the files: `load` refuses a parameter file that is not a valid ``.npz`` or
that holds a pickled object, and a ``config.json`` that is not JSON; `restore_like` refuses missing,
unexpected, misshapen and (for weights) non-finite entries against the structure the method's
``init`` gives. Every refusal is a `WeightsError` naming the folder and what is wrong.
"""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .fsutil import atomic_path, json_text, write_json
from .errors import JaxdenoiseError

PARAMS_FILE = "params.npz"
CONFIG_FILE = "config.json"


class WeightsError(JaxdenoiseError):
    """A weights folder or checkpoint that cannot be used (the message names the folder and why)."""


def flatten(tree: Any, prefix: str = "") -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    if isinstance(tree, (dict, list, tuple)) and len(tree) == 0:
        out[prefix + ("#{}" if isinstance(tree, dict) else "#[]")] = np.zeros(0, np.float32)
    elif isinstance(tree, dict):
        for k, v in tree.items():
            if "/" in str(k) or str(k).startswith("#"):
                raise ValueError(f"param key {k!r} may not contain '/' or start with '#'")
            out.update(flatten(v, f"{prefix}{k}/"))
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            out.update(flatten(v, f"{prefix}#{i}/"))
    elif tree is None:
        pass
    else:
        arr = np.asarray(tree)
        if arr.dtype.kind not in "biuf":  # np.savez would pickle object arrays: never
            raise ValueError(f"param '{prefix.rstrip('/')}' has dtype {arr.dtype}; expected a numeric array")
        out[prefix.rstrip("/")] = arr
    return out


def unflatten(flat: dict[str, np.ndarray]) -> Any:
    root: dict = {}
    for key, value in flat.items():
        node = root
        parts = key.split("/")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return _lists(root)


def _lists(node: Any) -> Any:
    if not isinstance(node, dict):
        return node
    if set(node) == {"#{}"}:
        return {}
    if set(node) == {"#[]"}:
        return []
    node = {k: _lists(v) for k, v in node.items()}
    if node and all(k.startswith("#") for k in node):
        return [node[f"#{i}"] for i in range(len(node))]
    return node


def config_to_dict(config: Any) -> dict:
    if dataclasses.is_dataclass(config):
        return {f.name: _plain(getattr(config, f.name)) for f in dataclasses.fields(config)}
    return dict(config)


def _plain(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    return v


def config_from_dict(cls: type, data: dict) -> Any:
    """Build ``cls`` (a frozen dataclass) from ``data``; lists become tuples; unknown keys fail."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise JaxdenoiseError(f"config for {cls.__module__}.{cls.__name__} has unknown key(s) {unknown}")
    return cls(**{k: (tuple(_tuples(v)) if isinstance(v, list) else v) for k, v in data.items()})


def _tuples(v: list) -> list:
    return [tuple(_tuples(x)) if isinstance(x, list) else x for x in v]


# The entry of ``params.npz`` that holds a copy of ``config.json`` (UTF-8 bytes) when `save` is called
# with ``embed_meta``: a training checkpoint's params and its step then change in one rename.
META_ENTRY = "#meta.json"


def save(directory: str | os.PathLike, params: Any, config: Any = None, extra: dict | None = None, *,
         embed_meta: bool = False) -> Path:
    """Write ``params.npz`` and ``config.json`` into ``directory`` atomically; returns the directory.

    Each file is renamed into place on its own, so a process killed between the two renames leaves
    new params beside the old ``config.json``. ``embed_meta`` also stores the metadata inside
    ``params.npz`` (`META_ENTRY`), and `load` then reads it from there: a resumable checkpoint,
    whose step must match its params, uses it (a run killed there resumed one step off)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    flat = flatten(params)
    meta = {"config": config_to_dict(config) if config is not None else {}}
    if extra:
        meta.update(extra)
    if embed_meta:
        flat[META_ENTRY] = np.frombuffer(json_text(meta).encode("utf-8"), np.uint8)
    with atomic_path(directory / PARAMS_FILE) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **flat)
    write_json(directory / CONFIG_FILE, meta)
    return directory


def load(directory: str | os.PathLike) -> tuple[Any, dict]:
    """Read ``params.npz`` and ``config.json``; returns (params pytree of numpy arrays, metadata)."""
    directory = Path(directory)
    pfile = directory / PARAMS_FILE
    if not pfile.is_file():
        raise FileNotFoundError(f"{pfile}: no parameter file (expected {PARAMS_FILE} beside {CONFIG_FILE})")
    try:
        with np.load(pfile, allow_pickle=False) as data:
            flat = {}
            for k in data.files:
                try:
                    flat[k] = data[k]
                except ValueError as e:  # an object array: loading it would unpickle
                    raise WeightsError(f"{pfile}: entry '{k}' is a pickled object ({e}); weights are numeric "
                                       f"arrays only, refused") from None
    except WeightsError:
        raise
    except Exception as e:  # noqa: BLE001 - zipfile / numpy raise many types for a damaged file
        raise WeightsError(f"{pfile}: not a readable .npz parameter file ({type(e).__name__}: {e})") from None
    bad = sorted(k for k, v in flat.items() if v.dtype.kind not in "biuf")
    if bad:
        raise WeightsError(f"{pfile}: entries {bad} are not numeric arrays (dtype "
                           f"{flat[bad[0]].dtype}); refused")
    embedded = flat.pop(META_ENTRY, None)
    params = unflatten(flat)
    cfile = directory / CONFIG_FILE
    try:
        if embedded is not None:  # the copy saved with the params (`save`'s embed_meta) is authoritative
            meta = json.loads(bytes(np.asarray(embedded, np.uint8)).decode("utf-8"))
        else:
            meta = json.loads(cfile.read_text()) if cfile.is_file() else {}
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise WeightsError(f"{pfile if embedded is not None else cfile}: not valid JSON ({e})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("config", {}), dict):
        raise WeightsError(f"{cfile}: expected an object with a 'config' object")
    return params, meta


def restore_like(template: Any, loaded: Any, *, where: str = "checkpoint", finite: bool = False) -> Any:
    """Rebuild ``loaded`` (as returned by `load`) in the exact pytree structure of ``template``
    (tuples, empty containers and ``None`` included), checking every entry's presence and shape, and
    with ``finite`` that it holds no NaN/Inf; the dtypes become the template's."""
    import jax.numpy as jnp

    flat = flatten(loaded)
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
            raise WeightsError(f"{where}: entry '{key}' is missing")
        value = flat[key]
        shape = tuple(node.shape) if hasattr(node, "shape") else np.shape(node)  # an array or jax.eval_shape's struct
        if tuple(np.shape(value)) != shape:
            raise WeightsError(f"{where}: entry '{key}' has shape {np.shape(value)}; expected {shape}")
        if finite:
            n_bad = int(np.size(value) - np.isfinite(value).sum())
            if n_bad:
                raise WeightsError(f"{where}: entry '{key}' has {n_bad} NaN/Inf value(s)")
        used.add(key)
        return jnp.asarray(value, dtype=node.dtype if hasattr(node, "dtype") else jnp.asarray(node).dtype)

    out = rec(template, "")
    extra = sorted(set(flat) - used)
    if extra:
        raise WeightsError(f"{where}: unexpected entries {extra[:5]}{'...' if len(extra) > 5 else ''}")
    return out
