"""Training and validation data that travel to a GPU machine: one compact ``.npz`` each, sized so
that both, with the repository, fit what a device run carries (64 MiB in all).

    python experiments/export_training.py demc --train data/library_train data/train_rooms \
        --val data/library_val --spps 1,2,4,8,16,32,64 --crop 96 --out runs/export_demc

The training folders (the scene library's and procedural ones alike) are linked into one folder,
decoded once into the method's cache (its ``make_dataset``: the fields it reads and its per-frame
statistics, computed on every whole render, `jaxdenoise.pipeline`) and exported as random
``--crop`` crops over every rate of ``--spps`` (sequence crops of ``--frames`` frames for a
recurrent method), as many as fit in what is left of the budget once the repository and the
validation export are counted; the validation folder goes whole (one noise instance per frame).
Writes ``train.npz``, ``val.npz`` and ``exports.json`` (counts per rate, bytes, the budget) into
``--out``. On the device: ``--data OUT/train.npz --val-data OUT/val.npz`` with ``carry`` = OUT.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from jaxdenoise.errors import JaxdenoiseError  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402

CARRY_MIB = 64.0  # what a device run carries: the working tree plus the carried paths


def repository_mib(root: Path = ROOT) -> float:
    """MiB of the files git tracks (what travels with every device run)."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True).stdout.split(b"\0")
    return sum((root / f.decode()).stat().st_size for f in files if f and (root / f.decode()).is_file()) / 2**20


def link_folders(folders: list[Path], into: Path) -> int:
    """Link every shot folder (``scene_XXXX`` or a sequence) of ``folders`` into ``into`` as
    ``<folder name>_<shot name>``; returns how many."""
    into.mkdir(parents=True, exist_ok=True)
    n = 0
    for folder in folders:
        if not folder.is_dir():
            raise JaxdenoiseError(f"export_training: {folder}: not a folder")
        for shot in sorted(p for p in folder.iterdir() if p.is_dir()):
            dst = into / f"{folder.name}_{shot.name}"
            if not dst.exists():
                os.symlink(shot.resolve(), dst)
            n += 1
    if n == 0:
        raise JaxdenoiseError(f"export_training: no shot folder in {[str(f) for f in folders]}")
    return n


def fill(export, mib: float) -> dict:
    """``export(max_mib)`` sized so that the compressed file, not the raw arrays `Cache.export`
    bounds, takes up to ``mib``: once with ``mib`` as the raw bound, then, when the file came out
    smaller and more items were available, again with the bound scaled by the compression seen (the
    file is written atomically each time; the last one stays if the second overshoots)."""
    first = export(mib)
    ratio = first["bytes"] / max(1, first["count"] * first["per_item_bytes"])
    if first["count"] >= first["requested"] or first["bytes"] > 0.9 * mib * 2**20:
        return first
    second = export(0.97 * mib / ratio)
    if second["bytes"] > mib * 2**20:  # compressed worse than the first draw: back to the safe bound
        return export(mib)
    return second


def per_rate(path: Path) -> dict[str, int]:
    """How many items of an export are at each sampling rate."""
    with np.load(path) as z:
        spp = z["spp"].reshape(len(z["spp"]), -1)[:, 0] if "spp" in z.files else np.zeros(0)
    rates, counts = np.unique(spp.astype(int), return_counts=True)
    return {str(r): int(c) for r, c in zip(rates, counts)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("method", help="a registered network with a pipeline dataset: demc, rae or gradnet")
    ap.add_argument("--train", nargs="+", required=True, help="training data folders (data_gen layout)")
    ap.add_argument("--val", required=True, help="validation folder (exported whole)")
    ap.add_argument("--spps", default="1,2,4,8,16,32,64", help="rates to export (default 1,2,4,8,16,32,64)")
    ap.add_argument("--crop", type=int, default=96, help="crop size of the training items (default 96)")
    ap.add_argument("--frames", type=int, default=None, help="sequence crops of this many frames (rae: 7)")
    ap.add_argument("--budget-mib", type=float, default=CARRY_MIB, help="repository + both exports (default 64)")
    ap.add_argument("--val-mib", type=float, default=12.0, help="at most this much for the validation export")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)

    from jaxdenoise.methods import get

    m = get(a.method)
    spps = tuple(int(s) for s in a.spps.split(","))
    fields = {f.name for f in dataclasses.fields(m.config)}
    config = dataclasses.replace(m.config, train_spps=spps) if "train_spps" in fields else m.config
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    n_train = link_folders([Path(f) for f in a.train], out / "links" / "train")
    link_folders([Path(a.val)], out / "links" / "val")
    repo = repository_mib()
    val = m.module.make_dataset(out / "links" / "val", config, progress=True)
    vs = fill(lambda mib: val.export(out / "val.npz", n=len(val.frames), whole=True, spps=spps, instances=1,
                                     max_mib=mib), a.val_mib)
    left = a.budget_mib - repo - vs["bytes"] / 2**20 - 1.0  # 1 MiB for what the run writes beside
    if left <= 1.0:
        raise JaxdenoiseError(f"export_training: the repository ({repo:.1f} MiB) and the validation export "
                              f"({vs['bytes'] / 2**20:.1f} MiB) leave no room in {a.budget_mib} MiB")
    train = m.module.make_dataset(out / "links" / "train", config, progress=True)
    # compressed .npz: the bound applies to the raw arrays, so the file is at most this and usually less
    ts = fill(lambda mib: train.export(out / "train.npz", n=10**6, size=a.crop, rng=np.random.default_rng(a.seed),
                                       spps=spps, frames=a.frames, max_mib=mib), left)
    summary = {"method": m.name, "train_folders": a.train, "train_shots": n_train, "val_folder": a.val,
               "spps": list(spps), "crop": a.crop, "frames": a.frames, "budget_mib": a.budget_mib,
               "repository_mib": repo, "train": {**ts, "per_rate": per_rate(out / "train.npz")},
               "val": {**vs, "per_rate": per_rate(out / "val.npz")},
               "total_mib": repo + (ts["bytes"] + vs["bytes"]) / 2**20,
               "command": "python " + " ".join([Path(sys.argv[0]).as_posix(), *(argv or sys.argv[1:])])}
    write_json(out / "exports.json", summary)
    print(f"export_training: {ts['count']} training items ({ts['bytes'] / 2**20:.1f} MiB), {vs['count']} validation "
          f"frames ({vs['bytes'] / 2**20:.1f} MiB), with the repository {summary['total_mib']:.1f} of "
          f"{a.budget_mib:g} MiB -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
