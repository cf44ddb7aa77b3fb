"""Reliability report: the mutation fuzzer over every reader, and the tampered-weights cases.

    python experiments/reliability_report.py --seeds 1,2,3 --per-kind 12 --out docs/results

Sources (written here, 16x16): a noisy frame with every layer of the EXR contract, a reference, a
gradient frame (R G B + dx + dy), a sequence frame (`frame_0000/`), and the shipped `lbf`
``params.npz``. Every mutation kind of `jaxdenoise.fuzz` is applied ``--per-kind`` times per
source and seed, and each mutated file goes through `read_buffers`, `read_image`, `read_sequence`,
`jaxdenoise denoise`, `jaxdenoise bench` (EXRs) or the weights loader (`params.npz`), each case in
a worker process with a time limit. Then the tampered-weights cases of the reliability issue are
run through `jaxdenoise.load`. Writes ``reliability.json`` and ``reliability.md``: cases per reader
and mutation kind, outcomes (ok / named error / other / crash / hang), and the distinct messages
per mutation kind (file paths stripped).
"""
from __future__ import annotations

import argparse
import collections
import json
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402

from jaxdenoise import fuzz  # noqa: E402
from jaxdenoise.fsutil import write_json, write_text  # noqa: E402
from common import num  # noqa: E402

OUTCOMES = ("ok", "named", "other", "crash", "hang")


def sources(src: Path) -> dict[str, Path]:
    from conftest import synthetic_frame

    from jaxdenoise.io import write_buffers, write_image

    src.mkdir(parents=True, exist_ok=True)
    write_buffers(src / "noisy.exr", synthetic_frame(16, 16, seed=1))
    write_image(src / "reference.exr", synthetic_frame(16, 16, seed=2).color)
    write_buffers(src / "gradient.exr", synthetic_frame(16, 16, seed=3, fields=("color", "dx", "dy")))
    seq = src / "seq" / "frame_0000"
    seq.mkdir(parents=True, exist_ok=True)
    write_buffers(seq / "spp0001_00.exr", synthetic_frame(16, 16, seed=4, spp=1,
                                                          fields=("color", "albedo", "normal", "depth")))
    return {"noisy": src / "noisy.exr", "reference": src / "reference.exr", "gradient": src / "gradient.exr",
            "sequence": seq / "spp0001_00.exr", "weights": ROOT / "jaxdenoise" / "weights" / "lbf" / "params.npz"}


def normalize(message: str) -> str:
    m = re.sub(r"(FOLDER|/\S+?)/?[\w.]*\.(exr|npz|json)", "FILE", message)
    m = re.sub(r"\b\d+(\.\d+)?\b", "N", m)
    return m[:160]


def tampered(work: Path) -> list[dict]:
    """The tampered-weights cases: each must be refused with a WeightsError saying which."""
    import jaxdenoise as jd
    from jaxdenoise.checkpoint import WeightsError

    shipped = ROOT / "jaxdenoise" / "weights" / "lbf"

    def arrays(d):
        with np.load(d / "params.npz") as z:
            return {k: z[k] for k in z.files}

    def case(name, edit):
        d = work / name.replace(" ", "_")
        shutil.copytree(shipped, d)
        edit(d)
        try:
            jd.load("lbf", d)
            return {"case": name, "refused": False, "message": "loaded"}
        except WeightsError as e:
            return {"case": name, "refused": str(d) in str(e), "message": normalize(str(e).replace(str(d), "FOLDER"))}
        except Exception as e:  # noqa: BLE001
            return {"case": name, "refused": False,
                    "message": f"{type(e).__name__}: {normalize(str(e).replace(str(d), 'FOLDER'))}"}

    def savez(d, flat):
        np.savez(d / "params.npz", **flat)

    def drop(d):
        f = arrays(d)
        f.pop("net/0/w")
        savez(d, f)

    def shape(d):
        f = arrays(d)
        f["net/0/w"] = np.zeros((3, 3), np.float32)
        savez(d, f)

    def nan(d):
        f = arrays(d)
        f["net/0/b"][0] = np.nan
        savez(d, f)

    def pickled(d):
        f = arrays(d)
        f["net/0/w"] = np.array([{"x": 1}], dtype=object)
        savez(d, f)

    def other_method(d):
        meta = json.loads((d / "config.json").read_text())
        meta["method"] = "poisson-l2"
        (d / "config.json").write_text(json.dumps(meta))

    def other_config(d):
        meta = json.loads((d / "config.json").read_text())
        meta["config"] = {"alpha": 0.2, "norm": "l2"}
        meta.pop("method", None)
        (d / "config.json").write_text(json.dumps(meta))

    return [case("missing array", drop), case("wrong shape", shape), case("NaN weights", nan),
            case("pickled object", pickled), case("weights of another method", other_method),
            case("config of another method", other_config)]


def interrupted() -> list[dict]:
    """Run the SIGKILL-and-resume cases (tests/test_interrupts.py, default and slow) and return one
    row per case: data_gen dataset and training killed at fractions of their run time and resumed
    (bit-identical dataset; weights within 1e-6), bench killed while writing (no partial report)."""
    import subprocess

    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", "-m", "slow or not slow",
                        str(ROOT / "tests" / "test_interrupts.py")], cwd=ROOT, capture_output=True, text=True)
    rows = []
    for line in r.stdout.splitlines():
        parts = line.split(" ", 1)
        if parts[0] in ("PASSED", "FAILED", "ERROR") and len(parts) == 2:
            rows.append({"case": parts[1].split("::", 1)[-1].split(" - ")[0], "result": parts[0]})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--per-kind", type=int, default=12)
    ap.add_argument("--timeout", type=float, default=120.0)
    ap.add_argument("--out", default="docs/results")
    args = ap.parse_args()
    t0 = time.time()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = sources(tmp / "src")
        for seed in [int(s) for s in args.seeds.split(",")]:
            cases = fuzz.make_cases(src, tmp / f"cases_{seed}", n_per_kind=args.per_kind, seed=seed)
            for r in fuzz.run_cases(cases, timeout=args.timeout):
                results.append({k: r[k] for k in ("reader", "source", "kind", "outcome", "message", "seconds")}
                               | {"seed": seed})
            print(f"seed {seed}: {len(cases)} cases ({time.time() - t0:.0f} s)", flush=True)
        weights = tampered(tmp / "tampered")
    interrupts = interrupted()
    table = collections.defaultdict(collections.Counter)
    for r in results:
        table[(r["reader"], r["kind"])][r["outcome"]] += 1
    messages = collections.defaultdict(collections.Counter)
    for r in results:
        if r["outcome"] != "ok":
            messages[r["kind"]][normalize(r["message"])] += 1
    totals = collections.Counter(r["outcome"] for r in results)
    out = Path(args.out)
    report = {"command": "python " + " ".join(sys.argv), "seconds": time.time() - t0, "cases": len(results),
              "timeout_s": args.timeout, "interrupts": interrupts,
              "totals": dict(totals), "by_reader_kind": {f"{a}|{b}": dict(c) for (a, b), c in table.items()},
              "messages": {k: dict(v) for k, v in messages.items()}, "tampered_weights": weights,
              "slowest_case_s": max(r["seconds"] for r in results)}
    write_json(out / "reliability.json", report)
    write_text(out / "reliability.md", page(report))
    print(f"reliability: {len(results)} cases, totals {dict(totals)}; tampered weights refused "
          f"{sum(w['refused'] for w in weights)}/{len(weights)} -> {out / 'reliability.md'}")


def page(res: dict) -> str:
    """``reliability.md`` from ``reliability.json`` alone. Outcome counts are stored without their
    zeros (a reader x mutation cell lists the outcomes it had); every count must add up to ``cases``."""
    cells = {tuple(key.split("|")): c for key, c in res["by_reader_kind"].items()}
    for where, c in [("totals", res["totals"])] + [(f"by_reader_kind {a}|{b}", c) for (a, b), c in cells.items()]:
        if set(c) - set(OUTCOMES):
            raise ValueError(f"reliability.json {where}: unknown outcome(s) {sorted(set(c) - set(OUTCOMES))}")
    if sum(res["totals"].values()) != res["cases"] or sum(sum(c.values()) for c in cells.values()) != res["cases"]:
        raise ValueError(f"reliability.json: totals {res['totals']} and by_reader_kind do not add up to {res['cases']} cases")
    lines = ["# Reliability: fuzzed readers and tampered weights", "",
             "| reader | mutation | cases | " + " | ".join(OUTCOMES) + " |",
             "|---|---|---:|" + "---:|" * len(OUTCOMES)]
    for (reader, kind), c in sorted(cells.items()):
        lines.append(f"| {reader} | {kind} | {sum(c.values())} | " + " | ".join(str(c.get(o, 0)) for o in OUTCOMES) + " |")
    lines += ["", "Outcome totals: " + ", ".join(f"{o} {res['totals'].get(o, 0)}" for o in OUTCOMES) + ".", "",
              "- *ok*: the mutated file still reads (the mutation hit bytes the reader does not use, or "
              "values that are still valid); *named*: the project's own error (`ExrError`, `WeightsError`; "
              "for the CLI, an `error:` line without a traceback) naming the file; *other*: anything else; "
              "*crash* / *hang*: the worker died / did not answer.", "",
              f"Command: `{res['command']}` ({num(res['seconds'], '.0f')} s). {res['cases']} cases, each in a "
              f"worker process with a {num(res['timeout_s'], '.0f')} s limit (slowest case "
              f"{num(res['slowest_case_s'], '.2f')} s).", "",
              "## Distinct messages per mutation kind (file paths as FILE, numbers as N)", "",
              "The 8 most frequent of each kind (ties in message order).", ""]
    for kind in sorted({kind for _, kind in cells}):
        lines += [f"**{kind}**", ""]
        for msg, n in sorted(res["messages"].get(kind, {}).items(), key=lambda m: (-m[1], m[0]))[:8]:
            lines.append(f"- ({n}) `{msg}`")
        lines.append("")
    lines += ["## Tampered weights (`jaxdenoise.load('lbf', folder)`)", "", "| case | refused, naming the folder | message |",
              "|---|---|---|"]
    lines += [f"| {w['case']} | {'yes' if w['refused'] else '**no**'} | `{w['message']}` |" for w in res["tampered_weights"]]
    interrupts = res["interrupts"]
    survived = sum(r["result"] == "PASSED" for r in interrupts)
    lines += ["", f"## Interrupted work (SIGKILL, then resumed): {survived} of {len(interrupts)} cases survived", "",
              "`tests/test_interrupts.py` (default and `slow`; the kill moments are its own): `python -m data_gen "
              "dataset` killed part-way then rerun: bit-identical EXRs to an uninterrupted run, and every file "
              "present under its final name complete; training killed part-way and resumed: weights equal within "
              "1e-6; `bench` killed while it runs: no partial report file.", "",
              "| case | result |", "|---|---|"]
    lines += [f"| {r['case']} | {r['result']} |" for r in interrupts]
    lines += ["", "Resource limits: a header claiming 10^6 x 10^6 pixels is refused before allocation "
              "(OpenImageIO's own size limit, then ours: half the machine's memory), see the *oversized* rows; "
              "a frame whose compiled program needs more memory than is available is refused with XLA's "
              "estimate before it runs (`jaxdenoise.inference.Compiled`, tested in tests/test_api.py).", ""]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
