import json

import numpy as np
import pytest

from jaxdenoise import checkpoint


def test_roundtrip_nested_structure_with_empty_layers(tmp_path):
    params = {"net": [{"w": np.ones((2, 3), np.float32), "b": np.zeros(3, np.float32)}, {},
                      {"w": np.arange(6.0).reshape(3, 2)}], "norm": {"mean": np.float32(1.5)}, "empty": []}
    checkpoint.save(tmp_path / "ck", params, extra={"step": 7})
    back, meta = checkpoint.load(tmp_path / "ck")
    assert isinstance(back["net"], list) and back["net"][1] == {} and back["empty"] == []
    np.testing.assert_array_equal(back["net"][2]["w"], params["net"][2]["w"])  # exact
    assert float(back["norm"]["mean"]) == 1.5 and meta["step"] == 7


def test_reserved_keys_and_missing_files(tmp_path):
    with pytest.raises(ValueError, match="may not contain '/'"):
        checkpoint.save(tmp_path / "x", {"a/b": np.zeros(1)})
    with pytest.raises(FileNotFoundError, match="no parameter file"):
        checkpoint.load(tmp_path / "nothing")


def test_save_is_atomic_and_never_pickles(tmp_path):
    checkpoint.save(tmp_path / "ck", {"w": np.ones(2)})
    before = (tmp_path / "ck" / "params.npz").read_bytes()
    with pytest.raises(ValueError):
        checkpoint.save(tmp_path / "ck", {"w": np.array([object()], dtype=object)})  # refuses objects
    assert (tmp_path / "ck" / "params.npz").read_bytes() == before
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == ["config.json", "params.npz"]
    json.loads((tmp_path / "ck" / "config.json").read_text())


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    """A writer killed inside `atomic_path` leaves its temporary; the next run removes it, but never
    a live process's (tolerance: exact file sets)."""
    import os
    import subprocess
    import sys

    from jaxdenoise import fsutil

    code = ("import os, sys; from jaxdenoise.fsutil import atomic_path\n"
            "with atomic_path(sys.argv[1]) as t:\n    open(t, 'w').write('partial'); os._exit(9)")
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "a.json")])
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".a.tmp-") and not (tmp_path / "a.json").exists()
    live = tmp_path / f".b.tmp-{fsutil._HOST}-{os.getpid()}.json"  # this (live) process's
    live.write_text("in progress")
    removed = fsutil.remove_stale_temporaries(tmp_path)
    assert [p.name for p in removed] == left and sorted(p.name for p in tmp_path.iterdir()) == [live.name]


def test_embedded_metadata_keeps_params_and_step_together(tmp_path):
    """A training checkpoint (`embed_meta`) whose config.json is one write behind its params (a kill
    between the two renames) still loads the step saved with the params; a plain save reads
    config.json, and the embedded copy never appears among the params."""
    from jaxdenoise import checkpoint

    d = tmp_path / "ckpt"
    checkpoint.save(d, {"w": np.ones(3, np.float32)}, extra={"step": 5}, embed_meta=True)
    stale = json.loads((d / checkpoint.CONFIG_FILE).read_text())
    checkpoint.save(d, {"w": np.full(3, 2.0, np.float32)}, extra={"step": 6}, embed_meta=True)
    (d / checkpoint.CONFIG_FILE).write_text(json.dumps(stale))  # params renamed, config.json not yet
    params, meta = checkpoint.load(d)
    assert meta["step"] == 6 and set(params) == {"w"}
    np.testing.assert_array_equal(params["w"], np.full(3, 2.0, np.float32))  # exact
    plain = tmp_path / "weights"
    checkpoint.save(plain, {"w": np.ones(3, np.float32)}, extra={"step": 1})
    (plain / checkpoint.CONFIG_FILE).write_text(json.dumps({"config": {}, "step": 9}))
    assert checkpoint.load(plain)[1]["step"] == 9
