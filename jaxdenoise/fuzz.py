"""Seeded mutation fuzzing of the project's readers (reliability issue): used by
``tests/test_fuzz.py`` (a quick run in the default suite, thousands of cases under ``slow``) and by
``experiments/reliability_report.py``. Not part of the public API.

Mutations of a valid file's bytes (``KINDS``): byte flips in the EXR header and in the pixel data,
truncations, a duplicated chunk, two chunks swapped, an oversized data window (10^6 x 10^6), a
wrong channel pixel type. Every case is run by a worker process (`run_cases`), so a crash inside
OpenImageIO / OpenEXR or a hang is recorded as such (and the worker restarted) instead of ending the
run. Outcomes: ``ok`` (read fine), ``named`` (the project's own error type, naming the file),
``other`` (anything else: another exception type, or a message without the file name),
``crash``, ``hang``.
"""
from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

KINDS = ("header_flip", "pixel_flip", "truncate", "duplicate_chunk", "swap_chunks", "oversized", "channel_type")
READERS = ("read_buffers", "read_image", "read_sequence", "cli_denoise", "cli_bench", "weights")


def header_end(data: bytes) -> int:
    """Offset of the byte after an EXR header's terminating null (magic, version, attributes)."""
    pos = 8
    while pos < len(data) and data[pos] != 0:
        name_end = data.index(b"\0", pos)
        type_end = data.index(b"\0", name_end + 1)
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        pos = type_end + 5 + size
    return pos + 1


def _attribute(data: bytes, name: bytes) -> tuple[int, int] | None:
    """(offset, size) of a header attribute's value."""
    pos = 8
    while pos < len(data) and data[pos] != 0:
        name_end = data.index(b"\0", pos)
        type_end = data.index(b"\0", name_end + 1)
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        if data[pos:name_end] == name:
            return type_end + 5, size
        pos = type_end + 5 + size
    return None


def mutate(data: bytes, kind: str, rng: np.random.Generator) -> bytes:
    """One mutation of ``kind`` (module docstring) of a valid EXR's bytes."""
    b = bytearray(data)
    try:
        h = header_end(data)
    except (ValueError, struct.error):
        h = min(len(data), 256)
    if kind == "header_flip":
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(8, max(9, h)))
            b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == "pixel_flip":
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(h, len(b)))
            b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == "truncate":
        b = b[: int(rng.integers(1, len(b)))]
    elif kind == "duplicate_chunk":
        i, n = int(rng.integers(0, len(b))), int(rng.integers(1, 257))
        j = int(rng.integers(0, len(b)))
        b = b[:j] + b[i:i + n] + b[j:]
    elif kind == "swap_chunks":
        n = int(rng.integers(1, 257))
        i, j = sorted(int(x) for x in rng.integers(0, max(1, len(b) - n), size=2))
        if j >= i + n:
            b[i:i + n], b[j:j + n] = b[j:j + n], b[i:i + n]
    elif kind == "oversized":
        at = _attribute(data, b"dataWindow")
        if at is not None:
            off, _ = at
            struct.pack_into("<iiii", b, off, 0, 0, 999_999, 999_999)
    elif kind == "channel_type":
        at = _attribute(data, b"channels")
        if at is not None:
            off, size = at
            pos, picks = off, []
            while pos < off + size - 1:
                end = data.index(b"\0", pos)
                picks.append(end + 1)  # the channel's int32 pixel type follows its name
                pos = end + 1 + 16
            k = picks[int(rng.integers(0, len(picks)))]
            struct.pack_into("<i", b, k, int(rng.choice([0, 7, -1, 2**30])))
    else:
        raise ValueError(f"mutate: unknown kind {kind!r}")
    return bytes(b)


# -- running a case (inside the worker) ------------------------------------------------------------

def _classify(exc: BaseException, path: str) -> tuple[str, str]:
    from .checkpoint import WeightsError
    from .io import ExrError

    msg = f"{type(exc).__name__}: {exc}"
    own = isinstance(exc, (ExrError, WeightsError))
    return ("named" if own and path in str(exc) else "other"), msg


def run_one(reader: str, path: str, work: str) -> tuple[str, str]:
    """Run ``reader`` on the mutated file ``path``; returns (outcome, message)."""
    import contextlib
    import io as _io

    work_dir = Path(work)
    try:
        if reader == "read_buffers":
            from .io import read_buffers

            read_buffers(path)
        elif reader == "read_image":
            from .io import read_image

            read_image(path)
        elif reader == "read_sequence":
            from .io import read_sequence

            read_sequence(str(Path(path).parent / "spp*.exr"))
        elif reader in ("cli_denoise", "cli_bench"):
            from .cli import main

            err = _io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(_io.StringIO()):
                if reader == "cli_denoise":
                    rc = main(["denoise", path, "-o", str(work_dir / "out.exr"), "--method", "gaussian"])
                else:
                    rc = main(["bench", str(Path(path).parent), "--methods", "input", "--out",
                               str(work_dir / "report"), "--quiet"])
            text = err.getvalue().strip()
            if rc == 0:
                return "ok", ""
            if "Traceback" in text:
                return "other", text[-300:]
            return ("named" if path in text else "other"), text[-300:]
        elif reader == "weights":
            from . import api

            api.resolve("lbf", str(Path(path).parent))
        else:
            raise ValueError(f"unknown reader {reader!r}")
    except Exception as e:  # noqa: BLE001 - classifying every escape is the point
        return _classify(e, path)
    return "ok", ""


def worker() -> None:
    """Read cases as JSON lines on stdin, answer one JSON line each on stdout."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    for line in sys.stdin:
        case = json.loads(line)
        outcome, msg = run_one(case["reader"], case["path"], case["work"])
        sys.stdout.write(json.dumps({"outcome": outcome, "message": msg}) + "\n")
        sys.stdout.flush()


def run_cases(cases: list[dict], *, timeout: float = 30.0) -> list[dict]:
    """Run ``cases`` (``{"reader", "path", "work", ...}``) in a worker process; a case that kills the
    worker is a ``crash``, one that exceeds ``timeout`` seconds a ``hang`` (the worker is restarted)."""
    import selectors

    results = []
    proc = None

    def start():
        return subprocess.Popen([sys.executable, "-c", "from jaxdenoise.fuzz import worker; worker()"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                text=True, bufsize=1)

    for case in cases:
        if proc is None or proc.poll() is not None:
            proc = start()
        t0 = time.perf_counter()
        proc.stdin.write(json.dumps(case) + "\n")
        proc.stdin.flush()
        sel = selectors.DefaultSelector()
        sel.register(proc.stdout, selectors.EVENT_READ)
        ready = sel.select(timeout)
        sel.close()
        line = proc.stdout.readline() if ready else ""
        if line:
            r = json.loads(line)
        elif not ready:
            proc.kill()
            proc.wait()
            proc = None
            r = {"outcome": "hang", "message": f"no answer within {timeout} s"}
        else:
            proc.wait()
            r = {"outcome": "crash", "message": f"worker died (exit {proc.returncode})"}
            proc = None
        results.append({**case, **r, "seconds": time.perf_counter() - t0})
    if proc is not None:
        proc.stdin.close()
        proc.wait()
    return results


def make_cases(sources: dict[str, Path], work: Path, *, n_per_kind: int, seed: int,
               readers=READERS) -> list[dict]:
    """Mutated copies of every source file (``{kind of file: path}``), ``n_per_kind`` per mutation
    kind, each laid out for every reader: a shot folder (the mutated file as a render beside a valid
    reference) or, for ``weights``, a weights folder whose ``params.npz`` is mutated."""
    rng = np.random.default_rng(seed)
    cases = []
    for source_kind, src in sources.items():
        data = Path(src).read_bytes()
        for kind in KINDS:
            for i in range(n_per_kind):
                mutated = mutate(data, kind, rng)
                case_dir = work / f"{source_kind}_{kind}_{i:03d}"
                case_dir.mkdir(parents=True, exist_ok=True)
                if source_kind == "weights":
                    src_dir = Path(src).parent
                    (case_dir / "config.json").write_bytes((src_dir / "config.json").read_bytes())
                    target = case_dir / "params.npz"
                    target.write_bytes(mutated)
                    cases.append({"reader": "weights", "path": str(target), "work": str(case_dir),
                                  "source": source_kind, "kind": kind})
                    continue
                shot = case_dir / "shot"
                shot.mkdir(exist_ok=True)
                (shot / "reference.exr").write_bytes(Path(sources["reference"]).read_bytes())
                target = shot / "spp0004_00.exr"
                target.write_bytes(mutated)
                for reader in readers:
                    if reader != "weights":
                        cases.append({"reader": reader, "path": str(target), "work": str(case_dir),
                                      "source": source_kind, "kind": kind})
    return cases
