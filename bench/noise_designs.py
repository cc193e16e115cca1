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
  would follow the noise from image to image;
- the noise each calibration image half shows itself: the scatter of its neighbouring
  corners' residuals (second differences along the board's rows and columns,
  :func:`~endomeasure.solvers.verdict.scatter_floor` per image half, per coordinate),
  with the same ratio and correlation to the true noise.

With ``--zone-noise SEEDS`` (slow: one ``predict-error`` per board and zone), those
designs' board tests are also predicted with each board and zone's measured test-set
noise, u and v, and its correlations (the prediction ``bench/accuracy_report.py`` makes
for the default preset), against ``predict-error``'s defaults: zones with n >= 30 whose
actual std is within +-25 % of the predicted one.

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
from accuracy_designs import MIN_ZONE_N, STD_RATIO_LIMIT, _seeds  # noqa: E402

SECTION = "noise-designs"
MIN_CORNERS = 10  # an image half with fewer detected corners gives no noise figure
MIN_RUNS = 8  # runs of three neighbouring corners for one image half's scatter


def _spread(true: np.ndarray, estimate: np.ndarray) -> dict:
    """Ratio true / estimate (10th, 50th, 90th percentile) and correlation (of logs)."""
    ok = np.isfinite(true) & np.isfinite(estimate) & (estimate > 0)
    t, e = true[ok], estimate[ok]
    return {
        "ratio": [float(q) for q in np.percentile(t / e, [10, 50, 90])],
        "correlation": float(np.corrcoef(np.log(t), np.log(e))[0, 1]),
        "halves": int(t.size),
    }


def _scatter(record, truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per calibration image half: true noise and the scatter of its residuals (px per
    coordinate), from the stored calibration ``record``."""
    from endomeasure.solvers.verdict import scatter_floor

    a = record.arrays
    names = [str(n) for n in a["image_names"]]
    true, scatter = [], []
    for i, name in enumerate(names):
        for half, label in ((0, "left"), (1, "right")):
            sel = (a["obs_image"] == i) & (a["obs_half"] == half)
            h = truth.get((name, label))
            if h is None or sel.sum() < MIN_CORNERS:
                continue
            e = a["obs_pixels"][sel] - h.true_pixels[a["obs_ids"][sel]]
            r = a["residuals"][sel]
            ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(r), axis=1)
            zeros = np.zeros(int(ok.sum()), dtype=np.int64)
            s = scatter_floor(a["obs_board_points"][sel][ok], zeros, zeros, r[ok], MIN_RUNS)
            true.append(float(np.sqrt(np.mean(e[ok] ** 2))))
            scatter.append(s / np.sqrt(2.0))
    return np.array(true), np.array(scatter)


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
        record = reader.model("raytrace")
    test_errors, true, formal = [], [], []
    halves = detection_errors(folder, session, sets=("calib", "test"))
    for h in halves:
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
    test_sigma = float(np.sqrt(np.mean(np.concatenate(test_errors) ** 2)))
    truth = {(h.image, h.half): h for h in halves if h.set_name == "calib"}
    return {
        "test_sigma": test_sigma,
        "residual_sigma": float(residual),
        "formal": _spread(np.array(true), np.array(formal)),
        "scatter": _spread(*_scatter(record, truth)),
    }


def zone_noise_prediction(session: Path, folder: Path) -> tuple[int, int]:
    """(zones with n >= 30 within +-25 %, zones) with each board and zone's measured
    test-set noise (``bench/accuracy_report.py``'s primary prediction)."""
    import shutil
    import tempfile

    from accuracy_report import detection_noise, group_sigma_prediction
    from endomeasure import defaults

    with tempfile.TemporaryDirectory() as tmp:  # predict-error stores its prediction
        copy = Path(tmp) / session.name
        shutil.copy(session, copy)
        noise = detection_noise(copy, folder, defaults.ZONE_MM)
        pred = group_sigma_prediction(copy, noise["board_zones"], defaults.ZONE_MM,
                                      per_axis=True, rho=True)  # fmt: skip
    zones = [z for z in pred["zones"] if z["n"] >= MIN_ZONE_N]
    close = sum(abs(z["actual_std"] / z["predicted_std"] - 1.0) <= STD_RATIO_LIMIT for z in zones)
    return close, len(zones)


def _default_zones(work: Path, seed: int) -> tuple[int, int]:
    """The same count with ``predict-error``'s defaults, from the sweep's stored record."""
    import json

    for line in (work / "designs.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r["seed"] == seed and "board" in r:
            zones = r["board"].get("prediction", [])
            return sum(abs(z["std_ratio"] - 1.0) <= STD_RATIO_LIMIT for z in zones), len(zones)
    return 0, 0


def section(rows: dict[int, dict], designs: str, zone_noise: dict[int, tuple]) -> str:
    assumed = [r["residual_sigma"] / r["test_sigma"] for r in rows.values()]
    figures = {}
    for kind in ("formal", "scatter"):
        figures[kind] = (
            [r[kind]["ratio"][1] for r in rows.values()],
            [r[kind]["ratio"][2] / r[kind]["ratio"][0] for r in rows.values()],
            [r[kind]["correlation"] for r in rows.values()],
        )

    def cells(values):
        return f"{statistics.median(values):.2f} | {min(values):.2f}-{max(values):.2f}"

    lines = [
        f"Designs {designs} with a usable raytrace calibration ({len(rows)}), made by "
        "`python bench/noise_designs.py WORK` on an `accuracy_designs.py` work folder.",
        "",
        "| figure | median over the designs | range |",
        "|---|---:|---|",
        f"| `predict-error`'s default sigma (calibration residuals) / test set's noise | "
        f"{statistics.median(assumed):.2f} | {min(assumed):.2f}-{max(assumed):.2f} |",
    ]
    kinds = (
        ("formal", "the detector's formal sigma (calib and test images)"),
        ("scatter", "the scatter of its neighbouring corners (calib images)"),
    )
    for kind, what in kinds:
        medians, spreads, corr = figures[kind]
        lines += [
            f"| true noise of an image half / {what}, median over a design's image halves | "
            f"{cells(medians)} |",
            f"| the same, 90th / 10th percentile within a design | {cells(spreads)} |",
            f"| correlation of the two over a design's image halves (log) | {cells(corr)} |",
        ]
    lines += [
        "",
        "Per design: test set's noise (px per coordinate), the default sigma (px); true noise "
        "of an image half over the formal sigma and over the neighbour scatter (10th / 50th "
        "/ 90th percentile over the image halves) and their correlations.",
        "",
        "| seed | test noise | default sigma | true / formal | correlation | true / scatter "
        "| correlation |",
        "|---|---:|---:|---|---:|---|---:|",
    ]
    for seed, r in sorted(rows.items()):
        f, s = r["formal"], r["scatter"]
        lines.append(
            f"| {seed} | {r['test_sigma']:.4f} | {r['residual_sigma']:.4f} | "
            + " / ".join(f"{q:.2f}" for q in f["ratio"])
            + f" | {f['correlation']:+.2f} | "
            + " / ".join(f"{q:.2f}" for q in s["ratio"])
            + f" | {s['correlation']:+.2f} |"
        )
    if zone_noise:
        lines += [
            "",
            "Board-test zones (n >= 30) whose actual std is within +-25 % of the predicted "
            "one (`--zone-noise`):",
            "",
            "| seed | predict-error's defaults | each board and zone's measured noise |",
            "|---|---:|---:|",
            *(f"| {seed} | {d[0]} of {d[1]} | {m[0]} of {m[1]} |"
              for seed, (d, m) in sorted(zone_noise.items())),
        ]  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("work", type=Path, help="an accuracy_designs.py work folder")
    parser.add_argument("--designs", default="1-40", help="seeds, e.g. 1-40 or 1,5")
    parser.add_argument("--zone-noise", default="", help="seeds to predict with the measured "
                        "noise of each board and zone, e.g. 2,5")  # fmt: skip
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
    zone_noise = {}
    for seed in _seeds(args.zone_noise) if args.zone_noise else []:
        stem = args.work / f"design_{seed:03d}"
        if seed in rows:
            measured = zone_noise_prediction(stem.with_suffix(".h5"), stem)
            zone_noise[seed] = (_default_zones(args.work, seed), measured)
            print(seed, zone_noise[seed], flush=True)
    return report.finish({SECTION: section(rows, args.designs, zone_noise)})


if __name__ == "__main__":
    raise SystemExit(main())
