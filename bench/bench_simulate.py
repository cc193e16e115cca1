"""Simulator benchmarks: render time, and the accuracy of the rendered truth.

``bench/bench_simulate.py [--quick] [--no-write]``
    Render time of one image at the default resolution and supersampling (one core),
    against two peers measured in the same run: tracing the preset's ray bundle (done
    once per preset) and ``cv2.findChessboardCornersSB`` on the rendered image. Writes
    the ``simulate-render`` section of docs/benchmarks.md. Target (issue 4): under 2 s
    per image. ``--quick``: one timed render instead of the median of 5.

``bench/bench_simulate.py --accuracy [--noisy DIR] [--seed N]``
    The acceptance figures of the renderer: ``cv2.findChessboardCornersSB`` (no flags)
    on each half of every calib and test image, against the true pixels, RMS per set,
    for noisy renders (``DIR``, e.g. ``sample_sessions``, or rendered now) and for
    noise-free renders of the same poses; also the project's default detector
    (``features.chessboard``) for comparison. Writes the ``simulator-accuracy`` section
    of docs/simulator.md. Targets (issue 4, restated there against a detector that
    can reach them): the point-symmetry locator and the project's detector within 0.1 px
    RMS on the noisy renders and 0.05 px noise-free; SB's rows are reported against the
    same bars but not enforced (SB alone cannot reach them, docs/simulator.md).
    ``--quick``: the test set only.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, as the target says

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    BENCHMARKS,
    ROOT,
    Report,
    Target,
    machine,
    median_time,
    script_parser,
)

RENDER_TARGET = Target("render time of one image, one core", "<", 2.0, " s", "issue 4")
NOISY_RMS_TARGET = Target("corner RMS on the noisy renders", "<=", 0.1, " px", "issue 4")
NOISE_FREE_RMS_TARGET = Target("corner RMS on the noise-free renders", "<=", 0.05, " px", "issue 4")
ENFORCED_METHODS = ("oracle", "default")
"""The detectors the renderer's truth targets are checked with (not SB, see the doc)."""
QUICK_RENDER_RUNS = 1


def bench_render(report: Report, runs: int = 5) -> str:
    import cv2

    cv2.setNumThreads(1)
    from endomeasure.simulate.optics import Region, clear_ray_cache, trace_region
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.render import render
    from endomeasure.simulate.scenes import plan_set

    preset = load_preset("default")
    shot = plan_set(preset, "calib", 0)[14]
    width, height = preset.image_size
    region = Region.full(preset.image_size)
    clear_ray_cache()
    start = time.perf_counter()
    trace_region(preset.truth_model, region, preset.supersampling, preset.chunk_rays)
    t_trace = time.perf_counter() - start
    rng = np.random.default_rng(0)
    t_render = median_time(lambda: render(preset, shot.target, rng=rng), runs=runs)
    image = render(preset, shot.target, rng=rng).image
    half = np.ascontiguousarray(image[:, : preset.split])
    t_sb = median_time(
        lambda: cv2.findChessboardCornersSB(half, (shot.target.cols, shot.target.rows)), runs=5
    )
    n = preset.supersampling
    check = report.check(RENDER_TARGET, t_render)
    return "\n".join(
        [
            "## simulate: render time of one image",
            "",
            f"{width} x {height} px, {n} x {n} = {n * n} rays per pixel, one core, {machine()}; "
            f"median of {runs} after a warm-up (`bench/bench_simulate.py`).",
            "",
            "| step | time | ratio to render |",
            "|---|---:|---:|",
            f"| render one image (rays cached) | {t_render:.2f} s | 1.00 |",
            f"| trace the ray bundle (once per preset) | {t_trace:.2f} s "
            f"| {t_trace / t_render:.2f} |",
            f"| cv2.findChessboardCornersSB on one half | {t_sb:.3f} s | {t_sb / t_render:.3f} |",
            "",
            f"Target ({RENDER_TARGET.source}): under {RENDER_TARGET.limit:g} s per image: {check}.",
        ]
    )


ORACLE_START_OFFSET_PX = 0.3
"""The point-symmetry locator starts this far (in u and v) from the true pixel."""


def _half_errors(image: np.ndarray, truth: dict, split: int, method: str):
    """Per half: detected - true pixel per corner (by truth id), or None if not found."""
    import cv2

    from endomeasure.features.boards import parse_board_spec
    from endomeasure.features.chessboard import canonical_grid, detect_chessboard
    from endomeasure.simulate.oracle import symmetric_corners

    spec = parse_board_spec(truth["board_spec"])
    out = {}
    for half, (lo, hi) in (("left", (0, split)), ("right", (split, image.shape[1]))):
        gray = np.ascontiguousarray(image[:, lo:hi])
        if method == "oracle":
            true = truth["corners"]["pixels"][half]
            if any(p is None for p in true):
                out[half] = None
                continue
            start = np.array(true) - [lo, 0] + ORACLE_START_OFFSET_PX
            pixels = symmetric_corners(gray, start, radius_px=4.0)
        elif method == "sb":
            found, corners = cv2.findChessboardCornersSB(gray, (spec.cols, spec.rows))
            if not found:
                out[half] = None
                continue
            grid, _ = canonical_grid(corners.reshape(spec.rows, spec.cols, 2))
            pixels = grid.reshape(-1, 2)
        else:
            result = detect_chessboard(gray, spec)
            if not result.ok:
                out[half] = None
                continue
            pixels = result.pixels
        pixels = pixels + [lo, 0]
        true = np.array(
            [p if p is not None else [np.nan, np.nan] for p in truth["corners"]["pixels"][half]]
        )
        err = pixels - true
        # the canonical order must be the truth order: the nearest truth corner has the same id
        nearest = np.nanargmin(np.linalg.norm(pixels[:, None] - true[None], axis=-1), axis=1)
        out[half] = (err, int((nearest != np.arange(len(nearest))).sum()))
    return out


def _accuracy_of(folder: Path, sets: list[str], method: str) -> dict[str, dict]:
    import cv2

    manifest = json.loads((folder / "simulation.json").read_text())
    split = int(manifest["split"])
    stats = {}
    for name in sets:
        errors, halves, found, id_mismatch = [], 0, 0, 0
        for entry in manifest["sets"][name]["images"]:
            truth = json.loads((folder / entry["truth"]).read_text())
            image = cv2.imread(str(folder / entry["image"]), cv2.IMREAD_GRAYSCALE)
            for half, res in _half_errors(image, truth, split, method).items():
                if not truth["board_fully_visible"][half]:
                    continue  # only halves that contain the whole board
                halves += 1
                if res is None:
                    continue
                found += 1
                errors.append(res[0])
                id_mismatch += res[1]
        e = np.concatenate(errors) if errors else np.zeros((0, 2))
        stats[name] = {
            "halves": halves,
            "found": found,
            "corners": len(e),
            "rms": float(np.sqrt(np.nanmean(np.sum(e**2, axis=1)))) if len(e) else float("nan"),
            "mean": np.nanmean(e, axis=0) if len(e) else np.array([np.nan, np.nan]),
            "p95": float(np.nanpercentile(np.linalg.norm(e, axis=1), 95))
            if len(e)
            else float("nan"),
            "id_mismatch": id_mismatch,
        }
    return stats


def _ideal_board(square_px: float, perspective: float, cols: int = 6, rows: int = 5):
    """An analytic chessboard under a homography: 8 x 8 box-filtered, Gaussian blur 0.7 px.

    Independent of the simulator: the control for what the detector does on perfect
    images. Returns the 8-bit image and the true corner pixels in id order.
    """
    from scipy.ndimage import gaussian_filter

    u0, v0 = 60.37, 70.81
    s = square_px
    H = np.array([[s, 0.03 * s, u0], [-0.02 * s, s, v0], [perspective, 0.3 * perspective, 1.0]])
    Hinv = np.linalg.inv(H)
    width, height = int(u0 + s * (cols + 4)), int(v0 + s * (rows + 4))
    ss = 8
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    acc = np.zeros((height, width))
    for dv in offsets:
        for du in offsets:
            uu, vv = np.meshgrid(np.arange(width) + du, np.arange(height) + dv)
            b = np.einsum("ij,jhw->ihw", Hinv, np.stack([uu, vv, np.ones_like(uu)]))
            bx, by = b[0] / b[2], b[1] / b[2]
            i, j = np.floor(bx), np.floor(by)
            checker = (i >= -1) & (i <= cols - 1) & (j >= -1) & (j <= rows - 1)
            card = (bx >= -2) & (bx < cols + 1) & (by >= -2) & (by < rows + 1)
            dark = checker & (np.mod(i + j, 2) == 0)
            acc += np.where(dark, 0.06, np.where(card, 0.85, 0.02))
    image = gaussian_filter(acc / ss**2, 0.7)
    jj, ii = np.divmod(np.arange(cols * rows), cols)
    P = H @ np.stack([ii, jj, np.ones_like(ii)]).astype(float)
    truth = (P[:2] / P[2]).T
    return np.clip(np.rint(image * 220 + 3), 0, 255).astype(np.uint8), truth


def sb_control() -> str:
    """SB's RMS error on ideal analytic boards by square size and perspective (markdown)."""
    import cv2

    perspectives = (0.0, 0.01, 0.02, 0.04)
    growth = []
    for perspective in perspectives:
        grid = _ideal_board(16, perspective)[1].reshape(5, 6, 2)
        width = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
        growth.append(100 * abs(np.mean(width[:, 1:] / width[:, :-1] - 1)))
    lines = [
        "| square px | " + " | ".join(f"{g:.1f} % size change per square" for g in growth) + " |",
        "|---:|" + "---:|" * len(perspectives),
    ]
    for square in (8, 10, 12, 14, 16, 20, 24, 28):
        cells = []
        for perspective in perspectives:
            image, truth = _ideal_board(square, perspective)
            found, corners = cv2.findChessboardCornersSB(image, (6, 5))
            if not found:
                cells.append("not found")
                continue
            c = corners.reshape(-1, 2)
            nearest = np.argmin(np.linalg.norm(c[:, None] - truth[None], axis=-1), axis=1)
            err = c - truth[nearest]
            cells.append(f"{np.sqrt(np.mean(np.sum(err**2, axis=1))):.3f}")
        lines.append(f"| {square} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def bench_accuracy(report: Report, noisy_dir: str | None, seed: int, sets: list[str]) -> str:
    from endomeasure.pipeline.simulate import simulate

    with tempfile.TemporaryDirectory() as tmp:
        if noisy_dir is None:
            noisy = Path(tmp) / "noisy"
            simulate(noisy, "default", sets, seed=seed)
        else:
            noisy = Path(noisy_dir)
            seed = int(json.loads((noisy / "simulation.json").read_text())["seed"])
        clean = Path(tmp) / "clean"
        simulate(clean, "default", sets, seed=seed, noise_free=True)
        rows = []
        for method, label in (
            ("oracle", "renderer check: point-symmetry locator (simulate/oracle.py)"),
            ("sb", "cv2.findChessboardCornersSB"),
            ("default", "features default (SB + point symmetry)"),
        ):
            for kind, folder, target in (
                ("noisy", noisy, NOISY_RMS_TARGET),
                ("noise-free", clean, NOISE_FREE_RMS_TARGET),
            ):
                bar = target.limit
                for name, s in _accuracy_of(folder, sets, method).items():
                    if method in ENFORCED_METHODS:
                        verdict = str(report.check(
                            Target(f"{target.what}, {label}, {name}", target.op, target.limit,
                                   target.unit, target.source), s["rms"],
                        ))  # fmt: skip
                    else:
                        verdict = "met" if target.met_by(s["rms"]) else "**missed**"
                    rows.append(
                        f"| {label} | {name} | {kind} | {s['found']}/{s['halves']} "
                        f"| {s['corners']} | {s['rms']:.3f} "
                        f"| {s['mean'][0]:+.3f}, {s['mean'][1]:+.3f} | {s['p95']:.3f} "
                        f"| {s['id_mismatch']} | {bar} {verdict} |"
                    )
    return "\n".join(
        [
            f"Seed {seed}, default preset; `.venv/bin/python bench/bench_simulate.py --accuracy"
            + (f" --noisy {noisy_dir}" if noisy_dir else "")
            + "`. Halves counted: those whose "
            "truth says the whole board is visible; errors are detected minus true pixel by "
            "corner id (the detector's canonical order), px.",
            "",
            "| detector | set | render | halves found | corners | RMS px | mean du, dv px "
            "| 95 % px | id mismatches | bar |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|---|",
            *rows,
            "",
            "Control, same run: `cv2.findChessboardCornersSB` on ideal analytic chessboards "
            "(6x5 inner corners, 8 x 8 box-filtered pixels, Gaussian blur 0.7 px, 8 bits, no "
            "noise) under a homography whose perspective term (the third-row coefficient, "
            "1/px) makes the squares grow across the board; RMS error against the exact "
            "corners, px:",
            "",
            sb_control(),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, seed=0)
    parser.add_argument("--accuracy", action="store_true", help="measure the truth accuracy")
    parser.add_argument("--noisy", help="folder of a noisy simulate run (default: render now)")
    args = parser.parse_args(argv)
    if args.accuracy:
        report = Report("bench/bench_simulate.py", args, ROOT / "docs" / "simulator.md")
        sets = ["test"] if args.quick else ["calib", "test"]
        body = bench_accuracy(report, args.noisy, args.seed, sets)
        return report.finish({"simulator-accuracy": body})
    report = Report("bench/bench_simulate.py", args, BENCHMARKS)
    body = bench_render(report, QUICK_RENDER_RUNS if args.quick else 5)
    return report.finish({"simulate-render": body})


if __name__ == "__main__":
    raise SystemExit(main())
