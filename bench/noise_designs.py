"""Image noise on the random designs: what the +- assumes against what the images carry.

    .venv/bin/python bench/noise_designs.py WORK [--designs 1-40] [--no-write]

WORK is the folder of a ``bench/accuracy_designs.py --work WORK`` run (each design's
render ``design_NNN/`` and its calibrated session ``design_NNN.h5``). Per design, from
the simulator's true corner pixels (issue 17's groundwork):

- the test set's detection noise: RMS per coordinate of detected minus true corner pixels
  over every test image and half;
- what ``predict-error`` assumes by default: the raytrace calibration's residual sigma
  (one figure for every point), and its ratio to the test set's noise;
- the detector's formal covariance per image and half (``features/precision.py``,
  stored with each detection): the ratio true / formal sigma (median, 10th and 90th
  percentile over the image halves of both sets) and the correlation of the two over the
  image halves (logarithms), i.e. how far a formal covariance scaled by one factor
  would follow the noise from image to image.

Writes the "noise-designs" section of docs/accuracy.md unless ``--no-write``.
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report, script_parser  # noqa: E402
from _samples import detection_errors  # noqa: E402
from accuracy_designs import _seeds  # noqa: E402

SECTION = "noise-designs"
MIN_CORNERS = 10  # an image half with fewer detected corners gives no noise figure


def design_noise(session: Path, folder: Path) -> dict | None:
    """The figures of one design (module docstring); None without a usable raytrace."""
    from endomeasure.conventions import Half
    from endomeasure.errors import EndomeasureError
    from endomeasure.io.records import load_calibrated_model
    from endomeasure.io.session import open_session

    with open_session(session) as reader:
        try:
            residual = load_calibrated_model(reader, "raytrace", session).sigma_px
        except EndomeasureError:
            return None
        covariance = {(d.image, Half.parse(d.half).label): d.covariance
                      for d in reader.detections() if d.ok}  # fmt: skip
    test_errors, true, formal = [], [], []
    for h in detection_errors(folder, session, sets=("calib", "test")):
        C = covariance.get((h.image, h.half))
        if h.ids.size == 0 or C is None:
            continue
        e = h.detected - h.true_pixels[h.ids]
        ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(C.reshape(len(C), -1)), axis=1)
        if ok.sum() < MIN_CORNERS:
            continue
        if h.set_name == "test":
            test_errors.append(e[ok])
        true.append(float(np.sqrt(np.mean(e[ok] ** 2))))
        formal.append(float(np.sqrt(np.mean((C[ok, 0, 0] + C[ok, 1, 1]) / 2))))
    if not test_errors:
        return None
    true_a, formal_a = np.array(true), np.array(formal)
    ratio = true_a / formal_a
    test_sigma = float(np.sqrt(np.mean(np.concatenate(test_errors) ** 2)))
    return {
        "test_sigma": test_sigma,
        "residual_sigma": float(residual),
        "halves": int(ratio.size),
        "ratio": [float(q) for q in np.percentile(ratio, [10, 50, 90])],
        "correlation": float(np.corrcoef(np.log(true_a), np.log(formal_a))[0, 1]),
    }


def section(rows: dict[int, dict], designs: str) -> str:
    assumed = [r["residual_sigma"] / r["test_sigma"] for r in rows.values()]
    medians = [r["ratio"][1] for r in rows.values()]
    spreads = [r["ratio"][2] / r["ratio"][0] for r in rows.values()]
    corr = [r["correlation"] for r in rows.values()]
    lines = [
        f"Designs {designs} with a usable raytrace calibration ({len(rows)}), made by "
        "`python bench/noise_designs.py WORK` on an `accuracy_designs.py` work folder.",
        "",
        "| figure | median over the designs | range |",
        "|---|---:|---|",
        f"| `predict-error`'s default sigma (calibration residuals) / test set's noise | "
        f"{statistics.median(assumed):.2f} | {min(assumed):.2f}-{max(assumed):.2f} |",
        f"| true / formal sigma, median over a design's image halves | "
        f"{statistics.median(medians):.2f} | {min(medians):.2f}-{max(medians):.2f} |",
        f"| the same, 90th / 10th percentile within a design | {statistics.median(spreads):.2f} "
        f"| {min(spreads):.2f}-{max(spreads):.2f} |",
        f"| correlation of true and formal sigma over a design's image halves (log) | "
        f"{statistics.median(corr):.2f} | {min(corr):.2f}-{max(corr):.2f} |",
        "",
        "Per design: test set's noise (px per coordinate), the default sigma (px), true / "
        "formal sigma per image half (10th / 50th / 90th percentile), their correlation, "
        "image halves.",
        "",
        "| seed | test noise | default sigma | true / formal | correlation | halves |",
        "|---|---:|---:|---|---:|---:|",
    ]
    for seed, r in sorted(rows.items()):
        lo, mid, hi = r["ratio"]
        lines.append(
            f"| {seed} | {r['test_sigma']:.4f} | {r['residual_sigma']:.4f} | "
            f"{lo:.2f} / {mid:.2f} / {hi:.2f} | {r['correlation']:+.2f} | {r['halves']} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("work", type=Path, help="an accuracy_designs.py work folder")
    parser.add_argument("--designs", default="1-40", help="seeds, e.g. 1-40 or 1,5")
    args = parser.parse_args(argv)
    report = Report("bench/noise_designs.py", args, ACCURACY)
    rows = {}
    for seed in _seeds(args.designs):
        stem = args.work / f"design_{seed:03d}"
        if not stem.with_suffix(".h5").exists():
            continue
        r = design_noise(stem.with_suffix(".h5"), stem)
        if r is not None:
            rows[seed] = r
            print(seed, r, flush=True)
    return report.finish({SECTION: section(rows, args.designs)})


if __name__ == "__main__":
    raise SystemExit(main())
