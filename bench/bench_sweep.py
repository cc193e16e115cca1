"""Throughput of ``endomeasure sweep``: the serial loop against 2 local Dask workers.

Usage::

    .venv/bin/python bench/bench_sweep.py [--designs 200] [--draws 5] [--serial-designs N]
                                          [--quick] [--no-write]

The sweep: the default preset's wedge angle (a grid) and lens focal length (random),
``--designs`` designs of ``--draws`` tolerance draws each (wedges, apex offset), 2 images
per board of the calibration protocol, seeded with the nominal design, a 1 mm x-segment
at 30 mm on a 6 x 4 grid. All designs run on a LocalCluster of 2 worker processes
(``run_sweep(workers=2)``, its whole wall time: spec check, cluster start-up, writing and
reading back the results). The serial loop (what ``--workers 0`` runs: evaluate a design,
append it to the results file) runs ``--serial-designs`` of them, spread evenly over the
design indices (each design's work is a function of its index only, so its rate is the
serial rate of the whole sweep; default: all designs up to 40), and must give the same
results as the cluster for those designs. Rewrites the ``sweep`` section of
docs/benchmarks.md with both throughputs (designs/s), each run's machine load (the
1-minute load average, sampled during the run) and the workers' own timings (per-design
wall and CPU time, from the results). Target (issue 21): at least 1.8x with 2 workers.
``--quick``: 4 designs of 1 draw.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import endomeasure  # noqa: F401  (pins BLAS threads before numpy loads)
from _common import BENCHMARKS, Report, Target, machine, script_parser

SPEEDUP = Target("sweep throughput, 2 local workers over the serial loop", ">=", 1.8, "x",
                 "issue 21")  # fmt: skip
WORKERS = 2
SERIAL_DESIGNS = 40
"""Default cap of the serial loop's designs (about 2 min of 2 draws each on this machine)."""
LOAD_EVERY_S = 5.0


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


class LoadSampler:
    """The 1-minute load average at the start, every few seconds, and at the end."""

    def __init__(self) -> None:
        self.samples = [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(LOAD_EVERY_S):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> LoadSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append(os.getloadavg()[0])

    def line(self, own: int) -> str:
        mean = statistics.fmean(self.samples)
        other = mean - own
        return (f"load {self.samples[0]:.2f} before, {self.samples[-1]:.2f} after, mean "
                f"{mean:.2f} during (this run's own processes about {own}: other work about "
                f"{max(other, 0.0):.1f} of {os.cpu_count()} cores)")  # fmt: skip


def progress(label: str, t0: float):
    def report(done: int, total: int) -> None:
        if done % 10 == 0 or done == total:
            print(f"{label}: {done}/{total} designs, {time.perf_counter() - t0:.0f} s, "
                  f"load {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)  # fmt: skip

    return report


def serial_loop(spec_path: Path, indices: list[int], output: Path):
    """The serial loop of ``run_sweep(workers=0)`` on ``indices``: (results, wall s)."""
    from endomeasure.io.sweep_results import SweepResultsFile
    from endomeasure.study.evaluate import evaluate_design
    from endomeasure.study.spec import read_spec

    sweep = read_spec(spec_path)
    store = SweepResultsFile(
        output, json.dumps(sweep.document), sweep.digest, sweep.n_designs, sweep.axis_names
    )
    report = progress("serial", time.perf_counter())
    t0 = time.perf_counter()
    results = []
    for k, index in enumerate(indices, 1):
        results.append(evaluate_design(sweep, index))
        store.append(results[-1])
        report(k, len(indices))
    return results, time.perf_counter() - t0


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--designs", type=int, default=200)
    parser.add_argument("--draws", type=int, default=5)
    parser.add_argument(
        "--serial-designs", type=int, default=None, help=f"serial designs (<= {SERIAL_DESIGNS})"
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.designs, args.draws = 4, 1
    report = Report("bench/bench_sweep.py", args, BENCHMARKS)
    from endomeasure.pipeline.sweep import run_sweep
    from endomeasure.study.spec import read_spec

    doc = spec(args.designs, args.draws)
    with tempfile.TemporaryDirectory() as tmp:
        spec_path = Path(tmp) / "spec.json"
        spec_path.write_text(json.dumps(doc))
        n = read_spec(spec_path).n_designs
        n_serial = min(n, args.serial_designs or SERIAL_DESIGNS)
        indices = sorted({round(k * (n - 1) / max(n_serial - 1, 1)) for k in range(n_serial)})
        with LoadSampler() as serial_load:
            serial, serial_s = serial_loop(spec_path, indices, Path(tmp) / "serial.h5")
        with LoadSampler() as local_load:
            t0, cpu0 = time.perf_counter(), time.process_time()
            local = run_sweep(spec_path, Path(tmp) / "local.h5", workers=WORKERS,
                              on_progress=progress(f"{WORKERS} workers", t0))  # fmt: skip
            local_s, client_cpu = time.perf_counter() - t0, time.process_time() - cpu0
    by_index = {r.index: r for r in local.results}
    same = len(local.results) == n and all(r.same_as(by_index[r.index]) for r in serial)
    rate_serial, rate_local = len(serial) / serial_s, n / local_s
    speedup = rate_local / rate_serial
    check = report.check(SPEEDUP, speedup)
    ser_wall = statistics.fmean(r.seconds for r in serial)
    ser_cpu = statistics.fmean(r.cpu_seconds for r in serial)
    sub_wall = statistics.fmean(by_index[r.index].seconds for r in serial)
    sub_cpu = statistics.fmean(by_index[r.index].cpu_seconds for r in serial)
    busy = sum(r.seconds for r in local.results) / (WORKERS * local_s)
    subset = "all of them" if len(serial) == n else (
        f"{len(serial)} of them, spread evenly over the indices (each design's work depends "
        f"on its index only)")  # fmt: skip
    body = f"""## Design sweep (`endomeasure sweep`)

`bench/bench_sweep.py --designs {args.designs} --draws {args.draws}`: {n} designs x
{args.draws} tolerance draws (each draw a simulated calibration of 6 images and a
1 mm x-segment error map at 30 mm), {machine()}, {os.cpu_count()} cores shared with other
agents' work. The {WORKERS}-worker run is the whole sweep through `run_sweep` (spec check,
cluster start-up, results written and read back, all in its time); the serial loop (what
`--workers 0` runs per design) ran {subset}.

| run | designs | wall time | throughput |
|---|---:|---:|---:|
| serial loop | {len(serial)} | {serial_s:.1f} s | {rate_serial:.3f} designs/s |
| LocalCluster, {WORKERS} processes | {n} | {local_s:.1f} s | {rate_local:.3f} designs/s |

Machine load (1-minute load average, sampled every {LOAD_EVERY_S:g} s):

- serial loop: {serial_load.line(1)};
- {WORKERS} workers: {local_load.line(WORKERS)}.

Speed-up {speedup:.2f}x (target >= 1.8x: {check}). Both runs gave identical results for the
designs both ran: {same}.

Where the time goes, from the results' own per-design timings (wall; CPU of the thread
that evaluated it): a design took {ser_wall:.2f} s wall / {ser_cpu:.2f} s CPU in the serial
loop, and the same designs {sub_wall:.2f} s / {sub_cpu:.2f} s on the workers; the workers
were busy {100 * busy:.0f} % of the {WORKERS}-worker wall time (the rest: start-up, the last
design's tail, scheduling); the client process (scheduler, nannies, spec check, HDF5
writes) used {client_cpu:.1f} s of CPU. A CPU/wall ratio below 1 is time a design waited
for a core.
"""
    return report.finish({"sweep": body})


if __name__ == "__main__":
    raise SystemExit(main())
