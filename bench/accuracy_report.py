"""Measure and predict-error accuracy on a rendered set -> docs/accuracy.md.

    python bench/accuracy_report.py [DATA] [--test-seeds 1,2,3] [--work DIR] [--reuse]
        [--quick] [--no-write]

DATA is a folder written by `endomeasure simulate` (default: sample_sessions/). The
script runs the commands a user would: `endomeasure detect` for each board spec of the
calib and test sets (the spec from the ground truth), `endomeasure calibrate --model
all`, `endomeasure measure --board-test --model all`, then `predict-error --board-test`
at the measured detection noise for several correlations. Besides the commands it uses
the simulator's truth (true corner pixels) for two figures a user could not have: the
detection noise and its correlations, and the board test on the *true* pixels (the model
error alone, without image noise). Tables go to the "measure" section of
docs/accuracy.md (between its markers). Targets: issue 7's four per board and zone (every
cell), issue 8's std band (every zone) and 2-sigma share (``*_TARGET`` below).
``--quick``: 2 noise draws of the perfect-model reference, no extra test seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report, Target, machine, script_parser  # noqa: E402
from _samples import (  # noqa: E402
    detect_samples,
    detection_errors,
    endomeasure,
    truth_board_sets,
    truth_board_test,
)
from endomeasure.simulate.manifest import load_manifest, load_truth  # noqa: E402

EM = [sys.executable, "-m", "endomeasure"]
SECTION = "measure"
QUICK_REPS = 2
RHOS = (0.0, 0.3, 0.6, 0.9)
STD_BAND = 0.25  # issue 8: actual std within +-25 % of the predicted one, per zone and kind
MIN_IN_BAND = 0.9  # issue 8: >= 90 % of the errors inside the predicted 2-sigma band
KINDS = ("x-segment", "y-segment", "point-plane", "area")
PRIMARY = "per board and zone sigma, u and v, and correlations"
RHO_POINTS_FLOOR = -0.3
"""Lowest rho_points passed on: an equicorrelation of n points needs rho >= -1/(n-1), and
the board test's measurements have up to four points."""
"""The prediction the issue 8 table shows: sigma equal to the measured detection noise of
the corners it predicts (each board in each zone, u and v separately)."""
SEGMENT_TARGET = 0.5  # issue 7: raytrace segment mean error within 0.5 % of the square
AREA_TARGET = 1.0  # issue 7: raytrace area mean error within 1 %
PLANE_TARGET = 0.3  # issue 7: point-to-plane |mean| within 0.3 of its per-zone std
ISSUE7_TARGET = Target(
    "raytrace board/zone cells missing an issue 7 target", "==", 0, "", "issue 7"
)
STD_BAND_TARGET = Target(
    f"zones whose actual std is outside +-{100 * STD_BAND:g} % of the predicted", "==", 0, "",
    "issue 8",
)  # fmt: skip
IN_BAND_TARGET = Target(
    "errors inside the predicted 2-sigma band", ">=", 100 * MIN_IN_BAND, " %", "issue 8"
)


def run(*args) -> dict | None:
    out = endomeasure(*args)
    return json.loads(out.stdout) if "--json" in args else None


def build_session(data: Path, session: Path) -> dict:
    """Detect the calib and test sets of a simulated set into ``session`` and calibrate
    both models (the commands a user runs); returns the calibration report."""
    session.unlink(missing_ok=True)
    detect_samples(data, session, workers=2)
    return run("calibrate", session, "--model", "all", "--json")


def with_more_test_frames(data: Path, work: Path, seeds: list[int]) -> Path:
    """``data`` plus the test set rendered again with other seeds (the same stage positions,
    fresh lateral offsets, tilts and noise: more frames per position, as a lab would take
    to shrink the sampling error of its zone statistics), as one simulated set in
    ``work/data``: the manifest lists every frame, the extra ones renamed ``test_sN_KKK``.
    """
    import shutil

    out = work / "data"
    shutil.rmtree(out, ignore_errors=True)
    (out / "test").mkdir(parents=True)
    manifest = load_manifest(data)
    (out / "calib").symlink_to(data / "calib")
    items = []
    for seed in [0, *seeds]:
        if seed == 0:
            src, prefix, sim = data, "test", manifest
        else:
            src, prefix = work / f"render_s{seed}", f"test_s{seed}"
            if not (src / "simulation.json").exists():
                run("simulate", src, "--set", "test", "--seed", seed, "--json")
            sim = load_manifest(src)
        for item in sim["sets"]["test"]["images"]:
            stem = Path(item["image"]).stem.replace("test", prefix, 1)
            for key, ext in (("image", ".png"), ("truth", ".json")):
                (out / "test" / f"{stem}{ext}").symlink_to((src / item[key]).resolve())
            items.append({**item, "image": f"test/{stem}.png", "truth": f"test/{stem}.json"})
    manifest["sets"]["test"] = {**manifest["sets"]["test"], "images": items}
    (out / "simulation.json").write_text(json.dumps(manifest))
    return out


def truth_of(data: Path, image: str) -> dict:
    return load_truth(data, image)


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a, b)[0, 1]) if a.size > 2 else float("nan")


def noise_figures(el: np.ndarray, er: np.ndarray, pairs: np.ndarray) -> dict:
    """sigma and correlations of matched left/right errors (n, 2) and neighbour pairs."""
    both = np.concatenate([el, er])
    sd = np.sqrt(np.mean((both - both.mean(axis=0)) ** 2, axis=0))
    return {
        "n": int(el.shape[0]),
        "sigma": float(np.sqrt(np.mean(sd**2))),
        "sigma_uv": [float(v) for v in sd],
        "mean_uv": [float(v) for v in both.mean(axis=0)],
        "rho_images": [_corr(el[:, k], er[:, k]) for k in range(2)],
        "rho_points": [_corr(pairs[:, 0, k], pairs[:, 1, k]) for k in range(2)]
        if len(pairs)
        else [float("nan")] * 2,
    }


def _zone_of(distance_mm: float, zone_mm: float) -> float:
    """The start of the board-test zone that holds an image's stage distance (the key
    its measurements' zones carry)."""
    from endomeasure.measure.board_test import zone_bounds, zone_index

    return zone_bounds(zone_index(distance_mm, zone_mm), zone_mm)[0]


def neighbour_pairs(ids: np.ndarray, cols: int, errors: dict) -> list[tuple]:
    """(error, error) of every corner and its right and lower neighbour, per half;
    ``errors`` maps half -> (len(ids), 2) in the order of ``ids``."""
    at = {int(i): k for k, i in enumerate(ids)}
    pairs = []
    for i, k in at.items():
        for j in ((i + 1) if (i % cols) + 1 < cols else -1, i + cols):
            if j in at:
                for half in ("left", "right"):
                    pairs.append((errors[half][k], errors[half][at[j]]))
    return pairs


def detection_noise(session: Path, data: Path, zone_mm: float | None = None) -> dict:
    """Detected minus true corner pixels of the test set: sigma and correlations
    (between a corner's left and right errors, and between neighbouring corners of one
    half), overall and, with ``zone_mm``, per distance zone of the image (``zones``) and per
    board and zone (``board_zones``, keys ``(board spec, zone start)``): the detection
    noise depends on the squares' size in pixels, so the two boards differ at one
    distance."""
    halves = detection_errors(data, session, sets=("test",))
    by_image: dict[str, dict] = {}
    for h in halves:
        if h.found:
            by_image.setdefault(h.image, {})[h.half] = h
    groups: dict[float | None, list] = {}
    for image, hs in by_image.items():
        if len(hs) < 2:
            continue
        left, right = hs["left"], hs["right"]
        ids = np.intersect1d(left.ids, right.ids)
        e = {}
        for h in (left, right):
            row = {int(i): k for k, i in enumerate(h.ids)}
            e[h.half] = h.errors[[row[int(i)] for i in ids]]
        pairs = neighbour_pairs(ids, left.cols, e)
        # the random part: minus the image's mean error in each half (a systematic shift
        # of the whole board in one half, which moves its depth, not its shape)
        r = {half: e[half] - e[half].mean(axis=0) for half in e}
        rpairs = neighbour_pairs(ids, left.cols, r)
        offset = e["left"].mean(axis=0) - e["right"].mean(axis=0)
        truth = load_truth(data, image)
        zone = _zone_of(truth["distance_mm"], zone_mm) if zone_mm else None
        keys = [None] + ([zone, (truth["board_spec"], zone)] if zone_mm else [])
        for key in keys:
            groups.setdefault(key, []).append(
                (e["left"], e["right"], pairs, r["left"], r["right"], rpairs, offset)
            )
    out = {}
    for key, items in groups.items():
        el = np.concatenate([i[0] for i in items])
        er = np.concatenate([i[1] for i in items])
        pairs = np.array([p for i in items for p in i[2]]).reshape(-1, 2, 2)
        out[key] = noise_figures(el, er, pairs)
        rl = np.concatenate([i[3] for i in items])
        rr = np.concatenate([i[4] for i in items])
        rpairs = np.array([p for i in items for p in i[5]]).reshape(-1, 2, 2)
        out[key]["random"] = noise_figures(rl, rr, rpairs)
        offsets = np.array([i[6] for i in items])
        out[key]["disparity_offset_u"] = float(np.mean(offsets[:, 0]))
        out[key]["disparity_random_std_u"] = float(np.std(rl[:, 0] - rr[:, 0]))
    result = out.pop(None)
    result["zones"] = dict(sorted((k, v) for k, v in out.items() if not isinstance(k, tuple)))
    result["board_zones"] = dict(sorted((k, v) for k, v in out.items() if isinstance(k, tuple)))
    return result


def perfect_reference(data: Path, groups: dict, zone_mm: float, reps: int) -> dict:
    """What a perfect model and a perfect noise prediction give on this test set.

    The simulator's *truth* optics measure the test set's *true* corner pixels plus
    Gaussian noise drawn with each (board, zone) group's measured sigma_u, sigma_v, ``reps``
    times; the UT predicts with exactly that noise (image noise only: the optics are
    exact). Whatever such a run misses of the issue 7 and 8 targets is the sampling error
    of the zone statistics and the estimator's own noise-induced bias, which no model and
    no prediction can remove. Returns, per (board, zone), the issue 7 figures of every
    run, and per run the zones, those within +-25 % and those with >= 90 % in the band.
    """
    from endomeasure.measure.board_runs import prediction_zones, run_board_test
    from endomeasure.measure.predict import ImageNoise
    from endomeasure.models import model_from_dict
    from endomeasure.pipeline.predict import board_predictions  # parses the board grids

    truth_model = model_from_dict(load_manifest(data)["truth_model"])
    # by the manifest's names: unique, while a frame of an extra test seed carries the
    # name of its own render in its truth (board_sets keys the images by name)
    names = [Path(i["image"]).stem for i in load_manifest(data)["sets"]["test"]["images"]]
    truths = [(name, load_truth(data, name)) for name in names]
    rng = np.random.default_rng(8)
    preds, figures, counts = {}, {}, []
    for _ in range(reps):
        images = []
        for name, t in truths:
            s = np.asarray(
                groups[(t["board_spec"], _zone_of(t["distance_mm"], zone_mm))]["sigma_uv"]
            )
            noisy = []
            for half in ("left", "right"):
                q = np.asarray(t["corners"]["pixels"][half], dtype=float)
                noisy.append(q + rng.normal(0.0, 1.0, q.shape) * s)
            images.append((name, t, *noisy))
        bt = run_board_test("truth", truth_model, truth_board_sets(images), zone_mm)
        rows = []
        for key, nz in groups.items():
            if key not in preds:  # the prediction at the ideal board: the same every run
                preds[key] = board_predictions(bt, truth_model, ImageNoise(tuple(nz["sigma_uv"])))
            p = preds[key]
            zones = prediction_zones(bt, p, zone_mm)
            rows += [
                z for z in zones if z["board"] == key[0] and abs(z["zone_start"] - key[1]) < 1e-9
            ]
        _, ok_std, ok_band = zone_verdicts(rows)
        counts.append((len(rows), ok_std, ok_band))
        for z in rows:
            f = figures.setdefault((z["board"], z["kind"], z["zone_start"]), [])
            f.append((z["actual_mean"], z["actual_std"], z["true"]))
    return {"reps": reps, "counts": counts, "issue7": _issue7_runs(figures, reps)}


def _issue7_runs(figures: dict, reps: int) -> dict:
    """Per (board, zone): the issue 7 figures of each run that has all four kinds."""
    met = {}
    for board, kind, z0 in figures:
        if kind != "x-segment":
            continue
        series = {k: figures.get((board, k, z0), []) for k in KINDS}
        runs = [
            issue7_figures({k: v[r] for k, v in series.items() if len(v) == reps})
            for r in range(reps)
        ]
        met[(board, z0)] = [r for r in runs if r is not None]
    return met


def issue7_figures(cells: dict) -> tuple[float, float, float, float, bool] | None:
    """x-, y-segment and area mean error in % of the true value, point-plane mean / std,
    and whether all four targets are met; ``cells`` maps kind -> (mean, std, true)."""
    if any(k not in cells for k in KINDS):
        return None
    x, y, area = (100 * cells[k][0] / cells[k][2] for k in ("x-segment", "y-segment", "area"))
    mean, std, _ = cells["point-plane"]
    pp = mean / std if std else float("nan")
    met = (
        abs(x) <= SEGMENT_TARGET
        and abs(y) <= SEGMENT_TARGET
        and abs(area) <= AREA_TARGET
        and abs(pp) <= PLANE_TARGET
    )
    return x, y, area, pp, met


def fmt(v, digits=4, sign=True):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v:+.{digits}f}" if sign else f"{v:.{digits}f}"


def board_name(board: str) -> str:
    return board.removeprefix("chessboard:")


def zone_key(r: dict) -> tuple:
    return (r["board"], r["kind"], r["zone_start"])


def predict(session: Path, sigma: float, zone_mm: float, *extra, plot: Path | None = None):
    return run(
        "predict-error", session, "--board-test", "--model", "raytrace", "--sigma", sigma,
        "--zone-mm", zone_mm, *extra, "--json", *(["--plot", plot] if plot else []),
    )  # fmt: skip


def zone_verdicts(zones: list[dict]) -> tuple[int, int, int]:
    """(zones, zones with actual/predicted std within +-25 %, zones with >= 90 % in band)."""
    ok_std = sum(abs(z["std_ratio"] - 1.0) <= STD_BAND for z in zones if z["std_ratio"])
    ok_band = sum(z["within_band"] >= MIN_IN_BAND for z in zones)
    return len(zones), ok_std, ok_band


def group_sigma_prediction(
    session: Path,
    groups: dict,
    zone_mm: float,
    *,
    rho: bool = False,
    random: bool = False,
    per_axis: bool = False,
) -> dict:
    """predict-error with each noise group's own measured sigma: one run per group, each
    contributing the rows of its zone (and board, for ``(board, zone)`` keys).

    ``rho`` adds the group's measured correlations (of u; negative taken as 0, or with
    ``per_axis`` kept down to :data:`RHO_POINTS_FLOOR`),
    ``random`` uses the random part of the detection error (each image's common shift
    per half removed), ``per_axis`` passes sigma_u and sigma_v (``--sigma U,V``).
    """
    zones, band_num, band_den = [], 0.0, 0
    for key, nz in groups.items():
        board, z0 = key if isinstance(key, tuple) else (None, key)
        if random:
            nz = nz["random"]
        extra = []
        if rho:
            # negative correlations only where the fewest-point kind allows them (a square's
            # four corners: rho_points >= -1/3); clamped at 0 without per_axis (as before)
            low = RHO_POINTS_FLOOR if per_axis else 0.0
            extra = ["--rho-images", f"{max(nz['rho_images'][0], -1.0 if per_axis else 0.0):.3f}",
                     "--rho-points", f"{max(nz['rho_points'][0], low):.3f}"]  # fmt: skip
        sigma = ",".join(f"{v:.5f}" for v in nz["sigma_uv"]) if per_axis else nz["sigma"]
        p = predict(session, sigma, zone_mm, *extra)
        rows = [
            z for z in p["zones"]
            if abs(z["zone_start"] - z0) < 1e-9 and board in (None, z["board"])
        ]  # fmt: skip
        zones += rows
        band_num += sum(z["within_band"] * z["n"] for z in rows)
        band_den += sum(z["n"] for z in rows)
    zones.sort(key=lambda z: (z["board"], KINDS.index(z["kind"]), z["zone_start"]))
    return {"zones": zones, "within_band": band_num / max(band_den, 1)}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = script_parser(__doc__, work=True)
    ap.add_argument("data", nargs="?", default=str(ROOT / "sample_sessions"))
    ap.add_argument(
        "--reuse", action="store_true", help="keep the session of an earlier run in --work"
    )
    ap.add_argument("--zone-mm", type=float, default=5.0)
    ap.add_argument(
        "--test-seeds",
        default="",
        help="comma-separated extra seeds of the test set (more frames per position)",
    )
    ap.add_argument(
        "--reps", type=int, default=20, help="noise draws of the perfect-model reference"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.reps, args.test_seeds = QUICK_REPS, ""
    return args


@dataclass(frozen=True)
class Setup:
    """Where one run reads and writes, and the session it built (or reused)."""

    data: Path
    """The simulated set (with ``--test-seeds``: the combined one in ``work/data``)."""
    work: Path
    session: Path
    seeds: list[int]
    command: str
    """The arguments of this run as the docs quote them."""
    calibration: dict
    """The report of ``endomeasure calibrate --json``."""


def prepare(args: argparse.Namespace) -> Setup:
    """The data (with the extra test frames), the work folder and the calibrated session."""
    data = Path(args.data).resolve()
    work = Path(args.work or tempfile.mkdtemp(prefix="endomeasure-acc-"))
    work.mkdir(parents=True, exist_ok=True)
    seeds = [int(v) for v in args.test_seeds.split(",") if v.strip()]
    command = data.name if data.parent == ROOT else str(data)
    command += f" --test-seeds {','.join(map(str, seeds))}" if seeds else ""
    if seeds:
        data = with_more_test_frames(data, work, seeds)
    session = work / "accuracy.h5"
    cal_file = work / "calibration.json"
    if args.reuse and session.exists() and cal_file.exists():
        cal = json.loads(cal_file.read_text())
    else:
        cal = build_session(data, session)
        cal_file.write_text(json.dumps(cal))
    return Setup(data, work, session, seeds, command, cal)


def noise_predictions(session: Path, noise: dict, zone_mm: float, fig5: Path) -> dict:
    """``predict-error --board-test`` of raytrace under each noise assumption, by label."""
    sigma = noise["sigma"]
    rho_i = max(noise["rho_images"][0], 0.0)
    rho_p = max(noise["rho_points"][0], 0.0)
    preds = {"iid": predict(session, sigma, zone_mm, plot=fig5)}
    preds["iid, image noise only"] = predict(session, sigma, zone_mm, "--no-calibration")
    for r in RHOS[1:]:
        preds[f"rho_images {r:g}"] = predict(session, sigma, zone_mm, "--rho-images", r)
    for r in RHOS[1:]:
        preds[f"rho_points {r:g}"] = predict(session, sigma, zone_mm, "--rho-points", r)
    measured_rho = f"measured rho_images {rho_i:.2f}, rho_points {rho_p:.2f}"
    preds[measured_rho] = predict(
        session, sigma, zone_mm, "--rho-images", f"{rho_i:.3f}", "--rho-points", f"{rho_p:.3f}"
    )
    zones_, boards_ = noise["zones"], noise["board_zones"]
    preds["per-zone sigma"] = group_sigma_prediction(session, zones_, zone_mm)
    preds["per-zone sigma and correlations"] = group_sigma_prediction(
        session, zones_, zone_mm, rho=True
    )
    preds["per-zone random sigma"] = group_sigma_prediction(session, zones_, zone_mm, random=True)
    preds["per-zone random sigma and correlations"] = group_sigma_prediction(
        session, zones_, zone_mm, rho=True, random=True
    )
    preds["per board and zone sigma"] = group_sigma_prediction(session, boards_, zone_mm)
    preds["per board and zone sigma, u and v"] = group_sigma_prediction(
        session, boards_, zone_mm, per_axis=True
    )
    preds[PRIMARY] = group_sigma_prediction(session, boards_, zone_mm, per_axis=True, rho=True)
    return preds


@dataclass(frozen=True)
class Studies:
    """Everything the section reports."""

    summary: list[dict]
    """The board test's zone summary of both models (``measure --board-test --json``)."""
    noise: dict
    """:func:`detection_noise` of the test set, with its zones and board zones."""
    truth: dict
    """:func:`truth_board_test`, by model."""
    reference: dict
    """:func:`perfect_reference`."""
    predictions: dict
    """:func:`noise_predictions`."""

    def by_model(self) -> dict[str, dict[tuple, dict]]:
        """The summary rows of raytrace and pinhole by (board, kind, zone start)."""
        return {
            m: {zone_key(r): r for r in self.summary if r["model"] == m}
            for m in ("raytrace", "pinhole")
        }


def run_studies(setup: Setup, zone_mm: float, reps: int) -> Studies:
    """The board test, the detection noise, the board test on the true pixels, the
    perfect-model reference and the predictions."""
    session, work, data = setup.session, setup.work, setup.data
    bt = run(
        "measure", session, "--board-test", "--model", "all", "--zone-mm", zone_mm,
        "--json", "--plot", work / "fig4.png",
    )  # fmt: skip
    noise = detection_noise(session, data, zone_mm)
    truth = truth_board_test(session, data, zone_mm)
    ref = perfect_reference(data, noise["board_zones"], zone_mm, reps=reps)
    preds = noise_predictions(session, noise, zone_mm, work / "fig5.png")
    return Studies(bt["summary"], noise, truth, ref, preds)


def header_lines(setup: Setup, zone_mm: float, seconds: float) -> list[str]:
    """The title, how to reproduce the section, the data and the calibration."""
    sim = load_manifest(setup.data)
    n_test = len(sim["sets"]["test"]["images"])
    seeds = setup.seeds
    return [
        "## Measurement (board test) and error prediction",
        "",
        f"Reproduce: `python bench/accuracy_report.py {setup.command}`"
        " (builds a session with `endomeasure detect` / `calibrate`, then runs `endomeasure "
        "measure --board-test --model all` and `endomeasure predict-error --board-test` at the "
        f"measured detection noise; {seconds:.0f} s here, {machine()}). Data: "
        f"preset `{sim['preset']['name']}`, seed {sim['seed']} (calibration set"
        + (f"; test set seeds 0, {', '.join(map(str, seeds))}: " if seeds else " and test set: ")
        + f"{n_test} test images, board perpendicular to the axis, 1 mm steps). Zones of "
        f"{zone_mm:g} mm along z; error = measured - true; relative = mean / true value.",
        "",
        "Calibration: "
        + ", ".join(
            f"{k} RMS {m['rms_px']:.3f} px ({m['n_corners']} corners, {m['n_outliers']} outliers)"
            for k, m in setup.calibration["models"].items()
        )
        + ".",
        "",
    ]


def noise_lines(noise: dict, zone_mm: float) -> list[str]:
    """The detection noise of the test set, overall and per distance zone."""
    lines = [
        f"Detection noise of the test set against the simulator's true corners ({noise['n']} "
        f"corners in both halves): sigma {noise['sigma']:.4f} px per coordinate (u "
        f"{noise['sigma_uv'][0]:.4f}, v {noise['sigma_uv'][1]:.4f}; mean error u "
        f"{noise['mean_uv'][0]:+.4f}, v {noise['mean_uv'][1]:+.4f}); correlation of a corner's "
        f"left and right errors rho_images u {noise['rho_images'][0]:+.2f}, v "
        f"{noise['rho_images'][1]:+.2f}; between neighbouring corners of one half rho_points u "
        f"{noise['rho_points'][0]:+.2f}, v {noise['rho_points'][1]:+.2f}. Per distance zone of "
        "the board:",
        "",
        "| zone mm | corners | sigma px | sigma u | sigma v | rho_images u | rho_images v | "
        "rho_points u | rho_points v | disparity offset u | random: sigma | sigma u | sigma v | "
        "rho_images u | rho_points u | disparity std u |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for z0, nz in noise["zones"].items():
        rz = nz["random"]
        lines.append(
            f"| {z0:g}-{z0 + zone_mm:g} | {nz['n']} | {nz['sigma']:.4f} | {nz['sigma_uv'][0]:.4f} "
            f"| {nz['sigma_uv'][1]:.4f} | {nz['rho_images'][0]:+.2f} | {nz['rho_images'][1]:+.2f} "
            f"| {nz['rho_points'][0]:+.2f} | {nz['rho_points'][1]:+.2f} "
            f"| {nz['disparity_offset_u']:+.4f} | {rz['sigma']:.4f} | {rz['sigma_uv'][0]:.4f} "
            f"| {rz['sigma_uv'][1]:.4f} | {rz['rho_images'][0]:+.2f} | {rz['rho_points'][0]:+.2f} "
            f"| {nz['disparity_random_std_u']:.4f} |"
        )
    return lines + [
        "",
        "Random: the same after removing each image's mean error in each half (a shift of "
        "the whole board in one half); disparity offset: the mean of that shift, left minus "
        "right, in u (a systematic disparity error, hence a depth and scale bias); disparity "
        "std: the random part of the left-minus-right u error (iid noise of the same sigma "
        "would give sqrt(2) sigma).",
    ]


def issue7_lines(studies: Studies, zone_mm: float, report: Report) -> list[str]:
    """Issue 7's four targets in every raytrace board/zone cell, against exact optics."""
    ref = studies.reference
    lines = [
        "",
        "### Issue 7 targets: raytrace, detected corners, every zone",
        "",
        f"x- and y-segments: |mean error| <= {SEGMENT_TARGET:g} % of the square; areas: <= "
        f"{AREA_TARGET:g} %; point-to-plane: |mean| <= {PLANE_TARGET:g} x its per-zone std. "
        f"'Exact optics' is the reference described under 'A perfect model on this test set' "
        f"below ({ref['reps']} noise draws on the true pixels with the simulator's own optics): "
        "its mean x-segment error, and the share of draws in which it meets all four targets "
        "in that zone.",
        "",
        "| board | zone mm | n | x-segment % | y-segment % | area % | point-plane mean/std | met "
        "| exact optics: x-segment % | exact optics: draws meeting all four |",
        "|---|---|---:|---:|---:|---:|---:|---|---:|---:|",
    ]
    ray = studies.by_model()["raytrace"]
    zones7 = sorted({(k[0], k[2]) for k in ray})
    n_met = 0
    for board, z0 in zones7:
        r = {kind: ray.get((board, kind, z0)) for kind in KINDS}
        if any(v is None for v in r.values()):
            continue
        x, y, area, ratio, met = issue7_figures(
            {k: (v["mean_error"], v["std_error"], v["true"]) for k, v in r.items()}
        )
        n_met += met
        runs = ref["issue7"].get((board, z0), [])
        exact_x = f"{np.mean([v[0] for v in runs]):+.2f}" if runs else "-"
        exact_met = f"{100 * np.mean([v[4] for v in runs]):.0f} %" if runs else "-"
        lines.append(
            f"| {board_name(board)} | {z0:g}-{z0 + zone_mm:g} | {min(v['n'] for v in r.values())} "
            f"| {x:+.2f} | {y:+.2f} | {area:+.2f} | {ratio:+.2f} | {'yes' if met else '**no**'} "
            f"| {exact_x} | {exact_met} |"
        )
    issue7 = report.check(ISSUE7_TARGET, len(zones7) - n_met)
    return lines + ["", f"Zones meeting all four targets: {n_met} of {len(zones7)} ({issue7})."]


def model_comparison_lines(studies: Studies, zone_mm: float) -> list[str]:
    """Pinhole against raytrace per board, kind and zone, on detected and true pixels."""
    lines = [
        "",
        "### Pinhole against raytrace, zone by zone (detected corners; true pixels)",
        "",
        "Mean error in % of the true value (point-plane: in mm); std in mm (mm^2 for areas). "
        "'true px' is the same board test on the simulator's exact corner pixels: the model "
        "error alone.",
        "",
        "| board | kind | zone mm | n | raytrace mean | pinhole mean | raytrace std | pinhole std "
        "| raytrace mean, true px | pinhole mean, true px |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    tr = {}
    for name, mb in studies.truth.items():
        s_ = mb.summary
        for i in range(s_.kind.shape[0]):
            rel = 100 * s_.mean_error[i] / s_.true[i] if s_.true[i] else float(s_.mean_error[i])
            tr[(name, mb.summary_board[i], str(s_.kind[i]), float(s_.zone_start[i]))] = rel
    by_model = studies.by_model()
    keys = sorted(
        set(by_model["raytrace"]) | set(by_model["pinhole"]),
        key=lambda k: (k[0], ["x-segment", "y-segment", "point-plane", "area"].index(k[1]), k[2]),
    )
    for key in keys:
        board, kind, z0 = key
        rr, pr = by_model["raytrace"].get(key), by_model["pinhole"].get(key)
        pct = kind != "point-plane"

        def mean(r, pct=pct):
            if r is None:
                return "-"
            return fmt(r["relative_mean_percent"], 2) if pct else fmt(r["mean_error"], 4)

        def std(r):
            return "-" if r is None else fmt(r["std_error"], 4, False)

        def tmean(name, key=key, pct=pct):
            v = tr.get((name, *key))
            return "-" if v is None else fmt(float(v), 2 if pct else 4)

        n = max((r["n"] for r in (rr, pr) if r), default=0)
        lines.append(
            f"| {board_name(board)} | {kind} | {z0:g}-{z0 + zone_mm:g} | {n} | {mean(rr)} | "
            f"{mean(pr)} | {std(rr)} | {std(pr)} | {tmean('raytrace')} | {tmean('pinhole')} |"
        )
    return lines


def prediction_lines(studies: Studies, zone_mm: float, report: Report) -> list[str]:
    """Issue 8: the primary prediction against the actual errors, zone by zone."""
    preds, noise, ref = studies.predictions, studies.noise, studies.reference
    p = preds[PRIMARY]
    nz, ok_std, ok_band = zone_verdicts(p["zones"])
    counts = np.array(ref["counts"])
    std_check = report.check(STD_BAND_TARGET, nz - ok_std)
    band_check = report.check(IN_BAND_TARGET, 100 * p["within_band"])
    lines = [
        "",
        "### Predicted vs actual (raytrace, UT, the measured detection noise of each board and "
        "zone: sigma of u and v, correlations; with the calibration covariance)",
        "",
        "The detection noise depends on the squares' size in pixels (the point-symmetry "
        "window is a fraction of a square) and differs between u and v, so the sigma of a "
        "prediction is the measured noise of the corners it predicts: each board in each "
        "zone, u and v separately (`predict-error --sigma U,V`), with that group's measured "
        "correlations of u between a corner's two halves (`--rho-images`) and between "
        "neighbouring corners (`--rho-points`, an equicorrelation; kept down to "
        f"{RHO_POINTS_FLOOR:g}):",
        "",
        "| board | zone mm | corners | sigma u px | sigma v px | rho_images u | rho_points u "
        "| random: sigma u | sigma v |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for (board, z0), nz_ in noise["board_zones"].items():
        lines.append(
            f"| {board_name(board)} | {z0:g}-{z0 + zone_mm:g} | {nz_['n']} | "
            f"{nz_['sigma_uv'][0]:.4f} | {nz_['sigma_uv'][1]:.4f} | "
            f"{nz_['rho_images'][0]:+.2f} | {nz_['rho_points'][0]:+.2f} | "
            f"{nz_['random']['sigma_uv'][0]:.4f} | {nz_['random']['sigma_uv'][1]:.4f} |"
        )
    lines += [
        "",
        f"Errors inside their predicted 2-sigma band: {100 * p['within_band']:.1f} % "
        f"(target >= {IN_BAND_TARGET.limit:g} %: {band_check}) "
        f"(one sigma {noise['sigma']:.4f} px for everything: "
        f"{100 * preds['iid']['within_band']:.1f} %). "
        f"Zones with actual/predicted std within +-{100 * STD_BAND:.0f} %: **{ok_std} of {nz}** "
        f"(target: every zone; {std_check}) "
        f"(one sigma: {zone_verdicts(preds['iid']['zones'])[1]} of {nz}); with >= "
        f"{100 * MIN_IN_BAND:.0f} % of their errors in the band: {ok_band} of {nz}. "
        "Predictions are made at the pixels of the ideal board at its estimated pose.",
        "",
        f"**A perfect model on this test set.** The simulator's own optics on the true corner "
        f"pixels plus Gaussian noise of exactly the measured sigma_u, sigma_v of each board and "
        f"zone, predicted by the UT with exactly that noise, {ref['reps']} noise draws: zones "
        f"within +-{100 * STD_BAND:.0f} % median {np.median(counts[:, 1]):.0f} of "
        f"{counts[0, 0]} (range {counts[:, 1].min()}-{counts[:, 1].max()}; all of them in "
        f"{int(np.sum(counts[:, 1] == counts[:, 0]))} of {ref['reps']} draws), zones with >= "
        f"{100 * MIN_IN_BAND:.0f} % in the band median {np.median(counts[:, 2]):.0f} (range "
        f"{counts[:, 2].min()}-{counts[:, 2].max()}). The spread of a zone's sample std (its "
        "errors share corners, so they are fewer independent values than measurements) is "
        "what an exact prediction still misses by; 'every zone within +-25 %' is not reachable "
        "on this test set for that reason alone.",
        "",
        "| board | kind | zone mm | n | actual mean | predicted mean | actual std | "
        "predicted std | actual / predicted std | in 2-sigma band |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for z in p["zones"]:
        ratio = z["std_ratio"]
        flag = "" if ratio and abs(ratio - 1) <= STD_BAND else " *"
        lines.append(
            f"| {board_name(z['board'])} | {z['kind']} | "
            f"{z['zone_start']:g}-{z['zone_end']:g} | {z['n']} | {fmt(z['actual_mean'])} | "
            f"{fmt(z['predicted_mean'])} | {fmt(z['actual_std'], sign=False)} | "
            f"{fmt(z['predicted_std'], sign=False)} | {fmt(ratio, 2, False)}{flag} | "
            f"{100 * z['within_band']:.0f} % |"
        )
    return lines + ["", "(* outside +-25 %.)"]


def assumption_lines(preds: dict) -> list[str]:
    """The correlation sweep: every noise assumption's prediction against 'iid'."""
    lines = [
        "",
        "### Effect of the noise assumptions on the prediction (raytrace)",
        "",
        "Mean over zones of the predicted std relative to 'iid' (one sigma for everything, "
        "rho = 0) per kind, the median ratio actual / predicted std, zones within +-25 %, and "
        "errors in their 2-sigma band. 'per-zone sigma' uses each distance zone's own "
        "measured detection noise (first table), 'and correlations' also its measured "
        "rho_images and rho_points (of u, the coordinate along the baseline; negative values "
        "taken as 0); 'per board and zone' the noise of each board in each zone (the table "
        "above), 'u and v' its two coordinates separately, 'and correlations' with its "
        "measured correlations (the prediction shown above).",
        "",
        "| assumption | x-segment | y-segment | point-plane | area | median actual/predicted |"
        " zones within +-25 % | in 2-sigma band |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    base = {
        k: {zone_key(z): z["predicted_std"] for z in preds["iid"]["zones"] if z["kind"] == k}
        for k in KINDS
    }
    for key, q in preds.items():
        rel = []
        for k, b in base.items():
            v = [
                z["predicted_std"] / b[zone_key(z)]
                for z in q["zones"]
                if zone_key(z) in b and z["kind"] == k
            ]
            rel.append(np.mean(v) if v else float("nan"))
        med = np.median([z["std_ratio"] for z in q["zones"] if z["std_ratio"] is not None])
        nz, ok_std, _ = zone_verdicts(q["zones"])
        lines.append(
            f"| {key} | "
            + " | ".join(f"{v:.2f}" for v in rel)
            + f" | {med:.2f} | {ok_std}/{nz} | {100 * q['within_band']:.1f} % |"
        )
    return lines


def write_report_json(work: Path, studies: Studies) -> None:
    """The figures behind the section, as JSON next to the session."""
    noise = studies.noise
    (work / "report.json").write_text(
        json.dumps(
            {
                "noise": {k: v for k, v in noise.items() if k not in ("zones", "board_zones")},
                "noise_zones": {str(k): v for k, v in noise["zones"].items()},
                "noise_board_zones": {
                    f"{b} {z:g}": v for (b, z), v in noise["board_zones"].items()
                },
                "perfect_reference_counts": studies.reference["counts"],
                "predictions": studies.predictions,
                "board_test": studies.summary,
            },
            default=float,
        )
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    report = Report("bench/accuracy_report.py", args, ACCURACY)
    t0 = time.perf_counter()
    setup = prepare(args)
    zone_mm = args.zone_mm
    studies = run_studies(setup, zone_mm, args.reps)
    lines = [
        *header_lines(setup, zone_mm, time.perf_counter() - t0),
        *noise_lines(studies.noise, zone_mm),
        *issue7_lines(studies, zone_mm, report),
        *model_comparison_lines(studies, zone_mm),
        *prediction_lines(studies, zone_mm, report),
        *assumption_lines(studies.predictions),
    ]
    status = report.finish({SECTION: "\n".join(lines)})
    write_report_json(setup.work, studies)
    print(f"\nsession, fig4.png, fig5.png and report.json in {setup.work}", file=sys.stderr)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
