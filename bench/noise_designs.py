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
  with the same ratio and correlation to the true noise;
- the same for the test images as ``predict-error --board-test`` measures it by default
  (:func:`~endomeasure.measure.board_runs.test_image_noise`, per coordinate);
- the board test's zones with n >= 30 whose actual std is within +-25 % of the predicted
  one, predicted three ways: with the calibration's residual sigma for every point (the
  earlier default), with the default (each test image's own measured noise and the
  correlation of a corner's two views, and the calibration's model misfit), and with each
  test image's *true* noise and correlation and the model misfit (from the simulator's
  corner pixels: what no noise model independent from corner to corner can beat);
- the correlation of neighbouring corners' true disparity errors (u_L - u_R) along the
  board's rows and along its columns (over every test image's pairs), which a model of
  independent corners leaves out and which the adjacent-corner segments of a board test
  feel.

Each design's figures go to ``WORK/noise_designs.jsonl`` as it finishes (a rerun
reuses them; ``--fresh`` recomputes). Writes the "noise-designs" section of
docs/accuracy.md unless ``--no-write``.
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report, parse_seeds  # noqa: E402
from _samples import detection_errors  # noqa: E402
from accuracy_designs import (  # noqa: E402
    MIN_ZONE_N,
    STD_RATIO_LIMIT,
    _finished,
    store_design,
    stored_designs,
    work_parser,
)

SECTION = "noise-designs"
MIN_CORNERS = 10  # an image half with fewer detected corners gives no noise figure


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
    from endomeasure.measure.board_runs import MIN_IMAGE_RUNS
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
            s = scatter_floor(a["obs_board_points"][sel][ok], zeros, zeros, r[ok], MIN_IMAGE_RUNS)
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


def _zones_within(bt, cm, noise, misfit=None) -> tuple[int, int]:
    """(zones with n >= 30 whose actual std is within +-25 % of the predicted, zones), with
    the calibration covariance and the model misfit ``misfit``."""
    from endomeasure import defaults
    from endomeasure.measure.board_runs import prediction_zones
    from endomeasure.pipeline.predict import board_predictions

    pred = board_predictions(bt, cm.model, noise, param_cov=cm.param_cov, misfit=misfit)
    zones = [z for z in prediction_zones(bt, pred, defaults.ZONE_MM) if z["n"] >= MIN_ZONE_N]
    close = sum(abs(z["actual_std"] / z["predicted_std"] - 1.0) <= STD_RATIO_LIMIT for z in zones)
    return close, len(zones)


def _true_errors(bt, halves: dict) -> tuple[np.ndarray, np.ndarray, list]:
    """Per test image of the board test: true noise (I, 4) px, true correlation of a
    corner's two views (I, 2), and the disparity errors by corner id."""
    std, rho, disparity = np.zeros((len(bt.images), 4)), np.zeros((len(bt.images), 2)), []
    for k, name in enumerate(bt.images):
        ids = bt.image_pixels(k)[0]
        e = []
        for half in ("left", "right"):
            h = halves[(name, half)]
            at = {int(i): n for n, i in enumerate(h.ids)}
            e.append(np.array([h.detected[at[i]] - h.true_pixels[i] for i in ids]))
        left, right = e
        ok = np.all(np.isfinite(left), axis=1) & np.all(np.isfinite(right), axis=1)
        left, right = left[ok], right[ok]
        std[k] = np.sqrt(np.concatenate([np.mean(left**2, 0), np.mean(right**2, 0)]))
        rho[k] = np.mean(left * right, 0) / np.sqrt(np.mean(left**2, 0) * np.mean(right**2, 0))
        disparity.append(dict(zip(ids[ok].tolist(), left[:, 0] - right[:, 0], strict=True)))
    return std, rho, disparity


def _neighbour_correlation(disparity: list, cols: list[int]) -> tuple[float, float]:
    """Correlation of neighbouring corners' disparity errors along the board's rows and
    along its columns, over the pairs of every test image."""
    out = []
    for along_row in (True, False):
        pairs = []
        for d, c in zip(disparity, cols, strict=True):
            step = 1 if along_row else c
            pairs += [(d[i], d[i + step]) for i in d
                      if i + step in d and not (along_row and i % c == c - 1)]  # fmt: skip
        a = np.array(pairs).reshape(-1, 2)
        ok = a.shape[0] >= MIN_CORNERS
        out.append(
            float(np.mean(a[:, 0] * a[:, 1]) / np.sqrt(np.mean(a**2, 0).prod())) if ok else np.nan
        )
    return out[0], out[1]


def board_figures(session: Path, folder: Path) -> dict | None:
    """The test images' measured noise against the truth, and the board test's zones
    predicted three ways (module docstring)."""
    import shutil
    import tempfile

    from endomeasure import defaults
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.io.session import open_session
    from endomeasure.measure.board_runs import test_image_noise
    from endomeasure.measure.predict import ImageNoise, ImageNoiseByImage
    from endomeasure.pipeline import calibrated_model
    from endomeasure.pipeline.predict import _board_grids, _board_test_of

    with tempfile.TemporaryDirectory() as tmp:  # a new board test is not stored
        copy = Path(tmp) / session.name
        shutil.copy(session, copy)
        with open_session(copy) as reader:
            cm = calibrated_model(reader, "raytrace", copy)
            bt, _ = _board_test_of(copy, reader, "raytrace", cm, defaults.ZONE_MM)
    halves = {(h.image, h.half): h for h in detection_errors(folder, session, sets=("test",))}
    measured = test_image_noise(bt, cm.model, _board_grids(bt))
    std, rho, disparity = _true_errors(bt, halves)
    cols = [parse_board_spec(b).cols for b in bt.board]
    return {
        "test_scatter": _spread(std.ravel(), measured.std.ravel()),
        "zones": {
            "residual": _zones_within(bt, cm, ImageNoise(cm.sigma_px)),
            "default": _zones_within(
                bt, cm, ImageNoiseByImage(measured.std, "", measured.rho), cm.misfit
            ),
            "truth": _zones_within(
                bt, cm, ImageNoiseByImage(std, "", np.clip(rho, -1, 1)), cm.misfit
            ),
        },
        "neighbour": _neighbour_correlation(disparity, cols),
    }


def section(rows: dict[int, dict], designs: str) -> str:
    assumed = [r["residual_sigma"] / r["test_sigma"] for r in rows.values()]
    figures = {}
    for kind in ("formal", "scatter", "test_scatter"):
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
        f"| the calibration's residual sigma / test set's noise | {cells(assumed)} |",
    ]
    kinds = (
        ("formal", "the detector's formal sigma (calib and test images)"),
        ("scatter", "the scatter of its neighbouring corners (calib images)"),
        ("test_scatter", "`predict-error`'s default: the same on each test image, per coordinate"),
    )
    for kind, what in kinds:
        medians, spreads, corr = figures[kind]
        lines += [
            f"| true noise / {what}, median over a design's image halves | {cells(medians)} |",
            f"| the same, 90th / 10th percentile within a design | {cells(spreads)} |",
            f"| correlation of the two over a design's image halves (log) | {cells(corr)} |",
        ]
    along = [[r["neighbour"][i] for r in rows.values()] for i in (0, 1)]
    lines += [
        f"| true disparity errors of neighbouring corners, correlation along the board's rows "
        f"| {cells(along[0])} |",
        f"| the same along its columns | {cells(along[1])} |",
    ]
    totals = {k: [sum(r["zones"][k][i] for r in rows.values()) for i in (0, 1)]
              for k in ("residual", "default", "truth")}  # fmt: skip
    ways = (
        ("residual", "the calibration's residual sigma, every point alike"),
        ("default", "`predict-error`'s default: each test image's measured noise, model misfit"),
        (
            "truth",
            "each test image's true noise and correlation, model misfit (the best a "
            "noise figure can do; the zone statistics' own spread: section below)",
        ),
    )
    lines += [
        "",
        "Board-test zones with n >= 30 whose actual std is within +-25 % of the predicted one "
        "(all designs):",
        "",
        "| image noise of the prediction | zones within +-25 % |",
        "|---|---:|",
    ]
    for k, what in ways:
        close, total = totals[k]
        if total:
            lines.append(f"| {what} | {close} of {total} ({100 * close / total:.1f} %) |")
    lines += [
        "",
        "Per design: test set's noise (px per coordinate), the residual sigma (px); true noise "
        "of an image half over the formal sigma, over the calibration images' neighbour "
        "scatter and over the default's measured noise of the test images (10th / 50th / 90th "
        "percentile over the image halves; correlation); zones within +-25 % with the residual "
        "sigma, the default and the true noise; neighbour correlation of the true disparity "
        "errors along rows / columns.",
        "",
        "| seed | test noise | residual sigma | true / formal | true / calib scatter | true / "
        "test scatter | zones: residual / default / true | neighbours |",
        "|---|---:|---:|---|---|---|---|---|",
    ]  # fmt: skip

    def spread(f):
        return " / ".join(f"{q:.2f}" for q in f["ratio"]) + f" ({f['correlation']:+.2f})"

    for seed, r in sorted(rows.items()):
        z = r["zones"]
        lines.append(
            f"| {seed} | {r['test_sigma']:.4f} | {r['residual_sigma']:.4f} | "
            f"{spread(r['formal'])} | {spread(r['scatter'])} | {spread(r['test_scatter'])} | "
            + " / ".join(f"{z[k][0]}" for k in ("residual", "default", "truth"))
            + f" of {z['default'][1]} | {r['neighbour'][0]:+.2f} / {r['neighbour'][1]:+.2f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    args = work_parser(__doc__).parse_args(argv)
    report = Report("bench/noise_designs.py", args, ACCURACY)
    store = args.work / "noise_designs.jsonl"  # one line per design, kept between runs
    done = stored_designs(store, args.fresh)
    rows = {}
    finished = _finished(args.work)
    for seed in parse_seeds(args.designs):
        stem = args.work / f"design_{seed:03d}"
        if seed in done:
            rows[seed] = done[seed]
            continue
        if seed not in finished:  # accuracy_designs.py is not done with it yet
            continue
        r = design_noise(stem.with_suffix(".h5"), stem)
        if r is not None:
            r.update(board_figures(stem.with_suffix(".h5"), stem), seed=seed)
            rows[seed] = r
            store_design(store, r)
            print(seed, r["zones"], r["neighbour"], flush=True)
    return report.finish({SECTION: section(rows, args.designs)})


if __name__ == "__main__":
    raise SystemExit(main())
