"""Atomic file writes: everything the project writes (EXR, checkpoints, results, manifests) goes
through `atomic_path`, so a crash or an interrupt never leaves a half-written file under the final
name and never destroys what was there before. `report_path` writes a path into a report without
this machine's absolute paths."""
from __future__ import annotations

import contextlib
import json
import os
import re
import socket
from pathlib import Path
from typing import Any, Iterator


_HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())[:40] or "host"
_TMP = re.compile(r"^\..+\.tmp-(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)(\.[^.]*)?$")


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporaries `atomic_path` left in ``folder`` (not recursive) when its writer was
    killed (SIGKILL skips the clean-up): those written on this host by a process that no longer
    exists. A temporary of a live process, or of another host sharing the folder, is kept.
    Returns what was removed."""
    removed = []
    folder = Path(folder)
    if not folder.is_dir():
        return removed
    for p in folder.iterdir():
        m = _TMP.match(p.name)
        if not m or m["host"] != _HOST or not p.is_file():
            continue
        try:
            os.kill(int(m["pid"]), 0)
            continue  # the writer is alive
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # alive, another user's
        p.unlink(missing_ok=True)
        removed.append(p)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling path; on success it is renamed over ``path`` (atomic on POSIX).

    The temporary keeps the final suffix (writers such as OpenImageIO pick the format from it).
    On any exception the temporary is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{_HOST}-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def json_text(data: Any) -> str:
    """The JSON text every file the library writes holds (sorted keys; NumPy values as lists)."""
    return json.dumps(data, indent=2, sort_keys=True, default=_json_default) + "\n"


def write_json(path: str | os.PathLike, data: Any) -> Path:
    return write_text(path, json_text(data))


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def report_path(path: str | os.PathLike, start: str | os.PathLike | None = None) -> str:
    """``path`` as a report writes it, never as this machine's absolute path: ``~/...`` when it is
    under the home directory and ``start`` is not in the same folder below it (a cache such as
    ``~/.cache/jaxdenoise`` seen from a repository elsewhere), else relative to ``start`` (as
    given when there is no ``start``)."""
    p = Path(path).expanduser().resolve()
    home = Path.home().resolve()
    s = None if start is None else Path(start).expanduser().resolve()
    if p.is_relative_to(home) and (s is None or not s.is_relative_to(home)
                                   or Path(os.path.commonpath([p, s])) == home):
        return str(Path("~") / p.relative_to(home))
    return str(path) if s is None else os.path.relpath(p, s)
