"""Calibration benchmark: wall time of each model's calibration against cv2.stereoCalibrate.

Usage::

    python bench/bench_calibrate.py [--session S.h5] [--images N] [--repeat R] [--seed S]
        [--quick] [--no-write]

Detections come from a session (``--session``, e.g. a sample session after
``endomeasure detect``) or, by default, from N synthetic views of the tests' perturbed
raytrace design with 0.1 px noise (``tests/solvers/calibration_data.py``). Timed, in one
run, on the same detections, median of R runs:

- peer: ``cv2.stereoCalibrate`` with ``flags=0`` from scratch (no intrinsic guess), on
  the corners seen in both halves of each image (what it accepts), right half in its
  own coordinates;
- ``calibrate('pinhole', ...)`` from scratch (per-half OpenCV, joint fit, outliers,
  covariance);
- ``calibrate('raytrace', ...)`` from scratch (the whole chain including the pinhole).

Writes the "calibrate" section of docs/benchmarks.md unless ``--no-write``. Target
(issue 6): raytrace at most 3x the peer. ``--quick``: 6 views, one run each.
"""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # for tests.solvers.calibration_data

from _common import BENCHMARKS, Report, Target, script_parser, stereo_calibrate_peer  # noqa: E402
from endomeasure.solvers.calibrate import calibrate  # noqa: E402

RATIO_TARGET = Target("raytrace calibration time / cv2.stereoCalibrate", "<=", 3.0, "x", "issue 6")
SEED = 7
QUICK_IMAGES, QUICK_REPEAT = 6, 1


def _synthetic(n_images: int, seed: int):
    from tests.solvers.calibration_data import perturbed_raytrace_truth, synthetic_views

    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(seed), n_images=n_images, noise_px=0.1)
    return data.views, data.boards, (640, 480), 320, f"{n_images} synthetic views, 0.1 px noise"


def _median_time(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main(argv=None) -> int:
    ap = script_parser(__doc__, seed=SEED)
    ap.add_argument("--session", help="take the detections of this session")
    ap.add_argument("--images", type=int, default=16, help="synthetic views (16)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per calibration (3)")
    args = ap.parse_args(argv)
    report = Report("bench/bench_calibrate.py", args, BENCHMARKS)
    if args.quick:
        args.images, args.repeat = min(args.images, QUICK_IMAGES), QUICK_REPEAT
    if args.session:
        from endomeasure.pipeline.calibrate import load_calibration_inputs

        views, boards, size, split = load_calibration_inputs(args.session)
        what = f"session {args.session} ({len(views)} views)"
    else:
        views, boards, size, split, what = _synthetic(args.images, args.seed)
    n_corners = sum(len(v.ids[0]) + len(v.ids[1]) for v in views)

    t_cv, (cv_rms, cv_corners) = _median_time(
        lambda: stereo_calibrate_peer(views, boards, size, split), args.repeat
    )
    t_ph, ph = _median_time(lambda: calibrate("pinhole", views, boards, size, split), args.repeat)
    t_rt, rt = _median_time(lambda: calibrate("raytrace", views, boards, size, split), args.repeat)
    rows = [
        ("`cv2.stereoCalibrate`, flags=0 (peer)", t_cv, cv_corners, cv_rms, "RMS per axis pair"),
        ("`calibrate` pinhole", t_ph, ph.n_inliers, ph.rms, ""),
        ("`calibrate` raytrace (whole chain)", t_rt, rt.n_inliers, rt.rms, ""),
    ]
    ratio = t_rt / t_cv
    lines = [
        "## `calibrate`",
        "",
        f"Median wall time of {args.repeat} runs each on the same detections ({what}, "
        f"{n_corners} corner observations), measured by `bench/bench_calibrate.py` in one run "
        f"(Python {platform.python_version()}, {platform.machine()}). The peer gets the "
        "corners seen in both halves of an image (all it accepts); the endomeasure "
        "calibrations use every corner of both halves.",
        "",
        "| what | median wall time | ratio to peer | corners used | RMS px |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, t, n, rms, _ in rows:
        lines.append(f"| {name} | {t:.2f} s | {t / t_cv:.2f} | {n} | {rms:.3f} |")
    check = report.check(RATIO_TARGET, ratio)
    lines += [
        "",
        f"Target ({RATIO_TARGET.source}): raytrace at most {RATIO_TARGET.limit:g}x the peer; "
        f"this run: {check} ({ratio:.2f}x). The peer's RMS is its own figure (OpenCV's "
        "reprojection RMS).",
    ]
    return report.finish({"calibrate": "\n".join(lines)})


if __name__ == "__main__":
    raise SystemExit(main())
