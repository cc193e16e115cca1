"""Throughput of ``endomeasure sweep``: the serial loop against 2 local Dask workers.

Usage::

    .venv/bin/python bench/bench_sweep.py [--designs 200] [--draws 5] [--quick] [--no-write]

The sweep: the default preset's wedge angle (a grid) and lens focal length (random),
``--designs`` designs of ``--draws`` tolerance draws each (wedges, apex offset), 2 images
per board of the calibration protocol, seeded with the nominal design, a 1 mm x-segment
at 30 mm on a 6 x 4 grid. Runs it serially (``--workers 0``) and on a LocalCluster of 2
worker processes (cluster start-up included), checks that both give the same results, and
rewrites the ``sweep`` section of docs/benchmarks.md with the throughput (designs/s).
Target (issue 21): at least 1.8x with 2 workers. ``--quick``: 4 designs of 1 draw.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import endomeasure  # noqa: F401  (pins BLAS threads before numpy loads)
from _common import BENCHMARKS, Report, Target, machine, script_parser

SPEEDUP = Target("sweep throughput, 2 local workers over the serial loop", ">=", 1.8, "x",
                 "issue 21")  # fmt: skip


def spec(designs: int, draws: int) -> dict:
    wedges = max(1, min(designs, 4))
    return {
        "preset": "default",
        "seed": 2024,
        "designs": {
            "wedge_deg": {"set": {"prism.left_face.a_deg": -1, "prism.right_face.a_deg": 1},
                          "grid": {"linspace": [32.0, 37.0, wedges]}},
            "lens.fx": {"random": [290.0, 310.0]},
        },
        "random_designs": -(-designs // wedges),
        "tolerances": {"draws": draws, "sigmas": {"prism.left_face.a_deg": 0.05,
                                                  "prism.right_face.a_deg": 0.05,
                                                  "prism.apex_mm.0": 0.01}},
        "protocol": {"images_per_board": 2, "noise_px": 0.05, "start": "design"},
        "merit": {"depths_mm": [30.0], "grid": [6, 4]},
    }  # fmt: skip


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--designs", type=int, default=200)
    parser.add_argument("--draws", type=int, default=5)
    args = parser.parse_args(argv)
    if args.quick:
        args.designs, args.draws = 4, 1
    report = Report("bench/bench_sweep.py", args, BENCHMARKS)
    from endomeasure.pipeline.sweep import run_sweep

    doc = spec(args.designs, args.draws)
    with tempfile.TemporaryDirectory() as tmp:
        spec_path = Path(tmp) / "spec.json"
        spec_path.write_text(json.dumps(doc))
        times, runs = {}, {}
        for label, workers in (("serial", 0), ("2 workers", 2)):
            t0 = time.perf_counter()
            runs[label] = run_sweep(spec_path, Path(tmp) / f"{workers}.h5", workers=workers)
            times[label] = time.perf_counter() - t0
    serial, local = runs["serial"], runs["2 workers"]
    n = serial.n_designs
    same = all(a.same_as(b) for a, b in zip(serial.results, local.results, strict=True))
    rate = {k: n / v for k, v in times.items()}
    speedup = rate["2 workers"] / rate["serial"]
    check = report.check(SPEEDUP, speedup)
    cpu = sum(r.seconds for r in serial.results) / n
    body = f"""## Design sweep (`endomeasure sweep`)

`bench/bench_sweep.py --designs {args.designs} --draws {args.draws}`: {n} designs x
{args.draws} tolerance draws (each draw a simulated calibration of 6 images and a
1 mm x-segment error map at 30 mm), {machine()}, {os.cpu_count()} cores (shared with
other work while this ran).

| run | wall time | throughput |
|---|---:|---:|
| serial loop (`--workers 0`) | {times["serial"]:.1f} s | {rate["serial"]:.3f} designs/s |
| LocalCluster, 2 processes | {times["2 workers"]:.1f} s | {rate["2 workers"]:.3f} designs/s |

Speed-up {speedup:.2f}x (target >= 1.8x: {check}); one design takes {cpu:.1f} s serially;
the cluster's start-up (about 2-4 s) is in its time. Both runs gave identical results:
{same}.
"""
    return report.finish({"sweep": body})


if __name__ == "__main__":
    raise SystemExit(main())
