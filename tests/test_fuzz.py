"""Seeded mutation fuzzing of every reader (jaxdenoise.fuzz): each outcome is a success or the
project's own error naming the file; never another exception, a traceback on the CLI, a crash of
the process or a hang. A quick run in the default suite; thousands of cases under `slow`."""
from __future__ import annotations

import collections
from pathlib import Path

import pytest

from jaxdenoise import fuzz

from conftest import synthetic_frame

ROOT = Path(__file__).resolve().parents[1]


def _sources(tmp_path):
    from jaxdenoise.io import write_buffers, write_image

    src = tmp_path / "src"
    src.mkdir()
    write_buffers(src / "noisy.exr", synthetic_frame(16, 16, seed=1))  # every layer of the contract
    write_image(src / "reference.exr", synthetic_frame(16, 16, seed=2).color)
    write_buffers(src / "gradient.exr", synthetic_frame(16, 16, seed=3, fields=("color", "dx", "dy")))
    seq = src / "seq" / "frame_0000"
    seq.mkdir(parents=True)
    write_buffers(seq / "spp0001_00.exr", synthetic_frame(16, 16, seed=4, spp=1,
                                                          fields=("color", "albedo", "normal", "depth")))
    return {"noisy": src / "noisy.exr", "reference": src / "reference.exr", "gradient": src / "gradient.exr",
            "sequence": seq / "spp0001_00.exr", "weights": ROOT / "jaxdenoise" / "weights" / "lbf" / "params.npz"}


def _check(results):
    counts = collections.Counter(r["outcome"] for r in results)
    bad = [r for r in results if r["outcome"] not in ("ok", "named")]
    assert not bad, "\n".join(f"{r['reader']} {r['source']} {r['kind']}: {r['outcome']}: {r['message'][:200]}"
                              for r in bad[:10])
    assert counts["named"] > 0  # the mutations do reach the checks


def test_mutated_files_give_named_errors_only(tmp_path):
    cases = fuzz.make_cases(_sources(tmp_path), tmp_path / "cases", n_per_kind=1, seed=20261127)
    _check(fuzz.run_cases(cases, timeout=120))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_thousands_of_mutations(tmp_path, seed):
    cases = fuzz.make_cases(_sources(tmp_path), tmp_path / "cases", n_per_kind=12, seed=seed)
    assert len(cases) >= 1000
    _check(fuzz.run_cases(cases, timeout=120))


def test_mutations_are_what_they_say(tmp_path):
    import numpy as np

    from jaxdenoise.io import write_buffers

    data = write_buffers(tmp_path / "f.exr", synthetic_frame(8, 8)).read_bytes()
    rng = np.random.default_rng(0)
    h = fuzz.header_end(data)
    assert data[:4] == b"\x76\x2f\x31\x01" and 8 < h < len(data)  # EXR magic; header inside the file
    flipped = fuzz.mutate(data, "pixel_flip", rng)
    assert flipped[:h] == data[:h] and flipped != data  # pixel flips leave the header alone
    assert len(fuzz.mutate(data, "truncate", rng)) < len(data)
    big = fuzz.mutate(data, "oversized", rng)
    assert b"\x3f\x42\x0f\x00" in big  # 999999 as int32 in the data window
