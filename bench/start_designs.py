"""Sweep of the raytrace calibration start over random probe designs.

Usage::

    python bench/start_designs.py [--seeds 1-40] [--noise 0.04] [--free n_glass,k3]
        [--fixed default|k3,p1,p2] [--truth] [--from-truth] [--n-glass 1.5168]

For each design seed (``tests/solvers/design_data.py``): corners of 3 boards x 12 poses
projected with Gaussian noise by the design's truth (``--truth``: the simulator's design
space ``simulate.design`` and its own truth optics; else a random ``RaytraceModel``),
then ``calibrate('pinhole')`` and ``calibrate('raytrace', start=pinhole)`` from images
alone (``--from-truth``: seeded with the drawn design itself, which tells whether the
model family fits, e.g. with ``--n-glass 1.5168 --fixed k3,p1,p2,n_glass``: a glass
held at N-BK7). Prints one row per design:
the design, the raytrace RMS over the noise RMS (detected minus true), the pinhole's,
the wall and CPU time of both calibrations (the CPU time, less sensitive to other
work on the machine, also as a ratio to ``cv2.stereoCalibrate`` on the same detections),
and the error of a failed one. Nothing is written.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # for tests.solvers.design_data
sys.path.insert(0, str(ROOT / "bench"))  # for _common


def run_one(
    seed: int, noise: float, options=None, truth_optics: bool = False, from_truth: bool = False
) -> dict:
    from tests.solvers.design_data import design_views, draw_design, truth_design_views

    from endomeasure.errors import EndomeasureError
    from endomeasure.solvers.calibrate import calibrate

    if truth_optics:
        drawn = truth_design_views(seed, noise)
        data, size, split, n_true = drawn.sets, drawn.image_size, drawn.split, drawn.n_glass
        summary = drawn.summary
    else:
        design = draw_design(seed)
        data = design_views(design, seed, noise_px=noise)
        size, split = design.truth.config.image_size, design.truth.config.split
        summary, n_true = design.summary, design.truth.n_glass
        if from_truth:  # the design itself as the user's seed: is the model family enough?
            options = dataclasses.replace(options, seed=design.truth.to_dict())
    from _common import stereo_calibrate_peer

    row = dict(seed=seed, design=summary, noise=data.noise_rms_px, n_true=n_true)
    t0, c0 = time.perf_counter(), time.process_time()
    stereo_calibrate_peer(data.views, data.boards, size, split)
    row["peer"] = time.perf_counter() - t0
    row["peer_cpu"] = time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        pinhole = calibrate("pinhole", data.views, data.boards, size, split)
        row["pinhole"] = pinhole.rms / data.noise_rms_px
        raytrace = calibrate(
            "raytrace", data.views, data.boards, size, split, options, start=pinhole
        )
        row["ratio"] = raytrace.rms / data.noise_rms_px
        row["outliers"] = raytrace.outlier_count / raytrace.inliers.size
        row["n_fit"] = raytrace.model.n_glass
        row["start"] = raytrace.start
    except EndomeasureError as exc:
        row["error"] = str(exc)
    row["time"] = time.perf_counter() - t0
    row["cpu"] = time.process_time() - c0
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-40")
    parser.add_argument("--noise", type=float, default=0.04)
    parser.add_argument("--free", default="", help="comma list of parameters to free")
    parser.add_argument(
        "--fixed",
        default=None,
        help="comma list of the parameters held ('default': the "
        "model's DEFAULT_FIXED minus --free, without extension selection)",
    )
    parser.add_argument("--truth", action="store_true", help="simulate.design + truth optics")
    parser.add_argument("--from-truth", action="store_true", help="seed with the drawn truth")
    parser.add_argument("--n-glass", type=float, default=None, help="the glass index to set")
    args = parser.parse_args()
    from endomeasure.solvers.calibrate import CalibrationOptions

    free = frozenset(filter(None, args.free.split(",")))
    from endomeasure.models import RaytraceModel

    if args.fixed == "default":
        fixed = RaytraceModel.DEFAULT_FIXED - free
    else:
        fixed = None if args.fixed is None else frozenset(filter(None, args.fixed.split(",")))
    values = {} if args.n_glass is None else {"n_glass": args.n_glass}
    options = CalibrationOptions(free=free, fixed=fixed, values=values)
    rows = []
    from _common import parse_seeds

    for seed in parse_seeds(args.seeds):
        row = run_one(seed, args.noise, options, args.truth, args.from_truth)
        rows.append(row)
        ratio = row.get("ratio", float("nan"))
        print(
            f"{seed:3d} ratio {ratio:7.3f} pinhole {row.get('pinhole', float('nan')):8.2f} "
            f"time {row['time']:5.1f} s cpu {row['cpu']:5.1f} s "
            f"({row['cpu'] / row['peer_cpu']:4.1f}x peer) "
            f"n {row['n_true']:.3f}->{row.get('n_fit', float('nan')):.3f} "
            f"| {row['design']} | {row.get('error', '')}",
            flush=True,
        )
    ok = [r for r in rows if r.get("ratio", 99) <= 1.25]
    times = sorted(r["time"] for r in rows)
    cpus = sorted(r["cpu"] for r in rows)
    ratios = sorted(r["cpu"] / r["peer_cpu"] for r in rows)
    print(
        f"{len(ok)}/{len(rows)} within 1.25x; median time {times[len(times) // 2]:.1f} s "
        f"(cpu {cpus[len(cpus) // 2]:.1f} s), cpu {ratios[len(ratios) // 2]:.1f}x "
        "cv2.stereoCalibrate"
    )


if __name__ == "__main__":
    main()
