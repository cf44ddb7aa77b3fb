"""What a one-off ``jaxdenoise denoise`` of one frame costs with a network, as a user runs it: the
whole process's wall time, with the compile cache off, then twice with a fresh cache folder (the
second run loads the compiled programs). Issue 36, part 5.

    python experiments/first_call.py --frame FRAME.exr --out docs/results/first_call

``FRAME.exr`` needs every buffer of the methods (the demo's render does:
``~/.cache/jaxdenoise/demo/default_128px_ref1024/spp0004_00.exr`` after ``jaxdenoise demo``).
Each process is ``python -m jaxdenoise.cli denoise FRAME -o OUT --method M`` with
``JAXDENOISE_CACHE_DIR`` set; nothing else should run.

Writes ``first_call.json`` and ``first_call.md`` (`page`).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import all_measured, write_study  # noqa: E402

CASES = ("cache off", "first run, empty cache", "second run, cache filled")


def wall(frame: str, method: str, cache: str, out: Path) -> float:
    env = {**os.environ, "JAXDENOISE_CACHE_DIR": cache, "JAX_PLATFORMS": "cpu"}
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "jaxdenoise.cli", "denoise", frame, "-o", str(out), "--method", method],
                   env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frame", required=True)
    ap.add_argument("--methods", default="demc,rae,gradnet")
    ap.add_argument("--repeats", type=int, default=3, help="repeats of each case (a fresh cache folder each)")
    ap.add_argument("--out", default="docs/results/first_call")
    args = ap.parse_args()
    t0 = time.time()
    res = {"frame": Path(args.frame).name, "repeats": args.repeats, "load_at_start": os.getloadavg()[0],
           "cpus": os.cpu_count(), "methods": {}}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.exr"
        for m in args.methods.split(","):
            runs = {c: [] for c in CASES}
            for k in range(args.repeats):
                runs["cache off"].append(wall(args.frame, m, "off", out))
                cache = str(Path(tmp) / f"cache_{m}_{k}")
                runs["first run, empty cache"].append(wall(args.frame, m, cache, out))
                runs["second run, cache filled"].append(wall(args.frame, m, cache, out))
            res["methods"][m] = {c: {"median_s": statistics.median(v), "runs_s": v} for c, v in runs.items()}
            print(m, {c: round(r["median_s"], 2) for c, r in res["methods"][m].items()}, flush=True)
    res["load_at_end"] = os.getloadavg()[0]
    res["seconds"] = time.time() - t0
    shown = [Path(a).name if a == args.frame else a for a in sys.argv]  # no machine path in a report
    res["command"] = "python " + " ".join(shown)
    write_study(Path(args.out), "first_call.json", "first_call.md", res, page)


def page(res: dict) -> str:
    all_measured(res, "first_call.json")
    lines = ["# A one-off `jaxdenoise denoise` with a network: the whole process", "",
             f"Wall seconds of `python -m jaxdenoise.cli denoise {res['frame']} -o OUT --method M`, median of "
             f"{res['repeats']} (a fresh cache folder each time).", "",
             "| method | " + " | ".join(CASES) + " |", "|---|" + "---:|" * len(CASES)]
    for m, r in res["methods"].items():
        lines.append(f"| {m} | " + " | ".join(f"{r[c]['median_s']:.1f}" for c in CASES) + " |")
    lines += ["", "## Run", "", f"`{res['command']}` ({res['seconds']:.0f} s, {res['cpus']} cores; load average "
              f"{res['load_at_start']:.2f} at start, {res['load_at_end']:.2f} at the end)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
