"""One error-against-time plot for the gradient-domain methods and the primal-domain ones (issue 15,
item 6, last bullet): the gradient-domain bench (``poisson-l2``, ``poisson-l1``, ``gradnet`` on G-PT
frames, whose render time includes the gradient render) and the primal-domain bench (``input`` =
plain path tracing, ``oidn``, on plain renders of the same scenes with the same references) merged
into one `jaxdenoise.bench.plot`: x = render + denoise seconds (medians), y = mean RelMSE. Writes
``error_vs_time.png`` and ``rows.json``; the table on docs/results/gradnet.md is written from
``rows.json`` by ``python scripts/results.py``.

    jaxdenoise bench data/gradnet_test --methods input,poisson-l2,poisson-l1,gradnet --out runs/bench_gradnet
    jaxdenoise bench data/gradnet_test_plain --methods input,oidn --out runs/bench_gradnet_plain
    python experiments/gradnet_equal_time.py --gradient runs/bench_gradnet --plain runs/bench_gradnet_plain \
        --out docs/results/gradnet_equal_time
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdenoise import bench  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gradient", required=True, help="bench folder of the G-PT frames")
    ap.add_argument("--plain", required=True, help="bench folder of the plain renders")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    rows = []
    for folder, rename in ((args.gradient, {"input": "G-PT base image"}), (args.plain, {"oidn": "oidn (plain PT)"})):
        recs = json.loads((Path(folder) / "results.json").read_text())["records"]
        for r in bench.summarize(recs):
            if r["render_seconds"] is None or r["seconds"] is None:
                raise SystemExit(f"{folder}: rows without render or denoise time; rerun the bench with timings")
            rows.append(dict(r, method=rename.get(r["method"], r["method"])))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bench.plot(rows, out / "error_vs_time.png")
    write_json(out / "rows.json", {"gradient": args.gradient, "plain": args.plain, "rows": rows})
    print(f"gradnet_equal_time: {len(rows)} rows -> {out / 'rows.json'}; then: python scripts/results.py")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
