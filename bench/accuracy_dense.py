"""Dense surfaces on the default preset's scene images against the simulator's depth.

For each scene image of the demo session (``make demo``; ``--session``) the ``raytrace``
model's dense surface of the whole left half is compared, pixel by pixel, with the true
depth of :func:`endomeasure.simulate.truth.true_depth` (the truth optics, not the fitted
model). Counted pixels: the truth sees the target there and the true point projects into
the right half. Reports coverage, median |z error| / z, the share of errors inside the
predicted 2 sigma, the time of a whole frame, the ratio to OpenCV's StereoSGBM alone on
the same halves, and the peak memory. Writes the ``dense-surface`` section of
docs/accuracy.md unless ``--no-write``; targets: issue 20.
"""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import ACCURACY, Report, Target, script_parser  # noqa: E402

COVERAGE_TARGET = Target("pixels both halves see with a depth", ">=", 85.0, " %", "issue 20")
ERROR_TARGET = Target("median |z error| / z", "<=", 0.2, " %", "issue 20")
BAND_TARGET = Target("errors inside the predicted 2 sigma", ">=", 90.0, " %", "issue 20")
TIME_TARGET = Target("a whole 640x480 frame", "<=", 10.0, " s", "issue 20")


def _sgbm_seconds(image: np.ndarray, split: int) -> float:
    import cv2

    width = min(split, image.shape[1] - split)
    left = np.ascontiguousarray(image[:, split - width : split])
    right = np.ascontiguousarray(image[:, split : split + width])
    sgbm = cv2.StereoSGBM_create(minDisparity=-64, numDisparities=128, blockSize=9)
    start = time.perf_counter()
    sgbm.compute(left, right)
    return time.perf_counter() - start


def main() -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--session", type=Path, default=ROOT / "out" / "demo" / "demo.h5")
    args = parser.parse_args()
    from endomeasure.conventions import Half
    from endomeasure.io.records import load_calibrated_model
    from endomeasure.io.session import open_session
    from endomeasure.measure.dense import DenseSettings, DenseStatus, dense_surface
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.scenes import plan_set
    from endomeasure.simulate.truth import true_depth

    preset = load_preset("default")
    shots = {s.name: s for s in plan_set(preset, "scene", 0)}
    rows, errors, within, counted, measured, seconds, ratios = [], [], [], 0, 0, [], []
    with open_session(args.session) as reader:
        cm = load_calibrated_model(reader, "raytrace", args.session)
        images = {n: reader.image(n) for n in sorted(shots) if n in reader.image_names()}
    near, far = cm.depth_range_mm
    settings = DenseSettings(depth_range_mm=(0.8 * near, 1.25 * far))
    for name, image in images.items():
        start = time.perf_counter()
        surface = dense_surface(cm.model, image, None, settings)
        seconds.append(time.perf_counter() - start)
        ratios.append(seconds[-1] / _sgbm_seconds(image, cm.model.config.split))
        u0, v0, u1, v1 = surface.region
        truth = true_depth(preset, shots[name].target).astype(np.float64)[v0:v1, u0:u1]
        uu, vv = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
        rays = preset.truth_optics.rays(np.stack([uu, vv], -1).reshape(-1, 2), Half.LEFT)
        t = (truth.reshape(-1) - rays.origins[:, 2]) / rays.directions[:, 2]
        seen = preset.truth_optics.project(rays.origins + t[:, None] * rays.directions, Half.RIGHT)
        both = np.isfinite(truth) & (seen.status == 0).reshape(truth.shape)
        ok = both & (surface.status == DenseStatus.OK)
        err = np.abs(surface.depth[ok] - truth[ok])
        errors.append(err / truth[ok])
        within.append(err <= 2 * surface.sigma_depth[ok])
        counted += int(both.sum())
        measured += int(ok.sum())
        refused = {s.label: int(((surface.status == s) & both).sum()) for s in DenseStatus if s}
        rows.append(
            f"| {name} | {np.nanmedian(truth):.1f} | {100 * ok.sum() / both.sum():.1f} | "
            f"{100 * np.median(err / truth[ok]):.3f} | {100 * np.mean(within[-1]):.1f} | "
            f"{100 * np.median(surface.sigma_depth[ok] / truth[ok]):.3f} | {seconds[-1]:.1f} | "
            + ", ".join(f"{k} {v}" for k, v in refused.items() if v)
            + " |"
        )
    rel = np.concatenate(errors)
    inside = np.concatenate(within)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    report = Report("accuracy_dense", args, ACCURACY)
    checks = {
        "coverage": report.check(COVERAGE_TARGET, 100 * measured / counted),
        "error": report.check(ERROR_TARGET, 100 * np.median(rel)),
        "band": report.check(BAND_TARGET, 100 * np.mean(inside)),
        "time": report.check(TIME_TARGET, max(seconds)),
    }
    body = "\n".join([
        "## Dense surfaces on the scene images",
        "",
        f"`{Path(sys.executable).name} bench/accuracy_dense.py` (session {args.session.name}: "
        "the demo's raytrace calibration of the default preset, seed 0). Truth: the "
        "simulator's per-pixel depth through the truth optics; counted: left pixels whose "
        "true surface point the right half sees.",
        "",
        "| image | z mm | depth for % | median abs z error % of z | inside 2 sigma % | "
        "median predicted sigma % of z | s | counted pixels refused |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
        *rows,
        "",
        f"- {checks['coverage'].target}: {100 * measured / counted:.1f} % ({checks['coverage']})",
        f"- {checks['error'].target}: {100 * np.median(rel):.3f} % ({checks['error']})",
        f"- {checks['band'].target}: {100 * np.mean(inside):.1f} % ({checks['band']})",
        f"- {checks['time'].target}: {max(seconds):.1f} s at most "
        f"({checks['time']}); {np.median(ratios):.0f} x StereoSGBM alone on the same "
        f"halves (128 disparities, 9 px block); peak memory {peak_mb:.0f} MB (max RSS).",
        "",
        "Reading: at 16-20 mm a 0.1 % change of z moves the right pixel by about 0.01 px "
        "(the halves' parallax is a few px), so the 0.2 % target asks for a dense match to "
        "0.013 px; the errors are about twice the predicted sigma (calibration error and "
        "the window's surface curvature are not in the sigma).",
    ])  # fmt: skip
    return report.finish({"dense-surface": body})


if __name__ == "__main__":
    sys.exit(main())
