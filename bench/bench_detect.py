"""Detection benchmarks: accuracy of candidate detectors, and throughput of `detect`.

Usage::

    python bench/bench_detect.py accuracy [--images N] [--seed S]
        Render N split images with exactly known corners (analytic renders under random
        board poses, see endomeasure.features.synthetic), noise-free and noisy, run every
        chessboard method of endomeasure.features.chessboard and print per method:
        detection rate, corner RMS error against the truth (px) and id agreement.
        The numbers go to docs/accuracy.md ("Detection").
    python bench/bench_detect.py throughput [--images DIR --board SPEC --split N]
        Images per second of `detect` (the pipeline: read, detect both halves, store)
        with 1 and 2 workers, against a bare loop of the same OpenCV calls (imread,
        findChessboardCornersSBWithMeta and cornerSubPix per half) on the same images,
        in the same run. Without --images: 12 analytic renders (for the sample set:
        --images sample_sessions/calib --board SPEC). Writes the "detect" section of
        docs/benchmarks.md.
    python bench/bench_detect.py refinement [--sets DIR,DIR]
        Sub-pixel refinements compared on the simulator's calibration and test sets
        (default: sample_sessions/ with noise, and its noise-free twin rendered once
        into /tmp/endomeasure-noise-free if missing): the sector-based finder's grid of
        every half is refined by each candidate (SB's own fit, cornerSubPix windows,
        saddle-point fit, point symmetry with and without the illumination term, window
        sizes) and compared with the exact corner pixels of the truth JSON.
    python bench/bench_detect.py
        Accuracy and throughput, with small sizes (what `make bench` runs).

Common options (before or after the command): ``--quick`` (2 accuracy renders, 4
images and one run for the throughput; implies ``--no-write``), ``--no-write``. No
targets: issue 5's detection targets are checked by ``bench/accuracy_detect.py``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _common import BENCHMARKS, Report, script_parser
from endomeasure.conventions import Half
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.chessboard import CHESSBOARD_METHODS, detect_chessboard
from endomeasure.features.synthetic import (
    apply_homography,
    homography_from_pose,
    render_split_image,
)

IMAGE_SIZE = (800, 600)
SPLIT = 400
FOCAL_PX = 420.0
# The default noisy render: sigma in grey levels, close to a good CCD at mid exposure.
NOISE_SIGMA = 2.0
BOARDS = ("chessboard:9x6:1.0", "chessboard:7x5:2.0", "chessboard:8x6:0.5")
ROOT = Path(__file__).resolve().parent.parent


def random_scene(rng: np.random.Generator, spec) -> dict:
    """Two homographies (left, right) of one board pose seen through a biprism-like pair.

    The two views are two pinhole cameras 1.2 mm apart looking at the same board, with
    principal points at the centres of the two halves.
    """
    width, height = IMAGE_SIZE
    extent = np.array([spec.cols, spec.rows]) * spec.square_mm
    # Distance so that the board fills 35-75 % of the half width.
    fill = rng.uniform(0.35, 0.75)
    distance = FOCAL_PX * extent[0] / (fill * SPLIT)
    tilt = np.radians(rng.uniform(-30, 30, size=2))
    roll = np.radians(rng.uniform(-20, 20))
    rvec = np.array([tilt[0], tilt[1], roll])
    centre_offset = rng.uniform(-0.08, 0.08, size=2) * distance
    homographies = {}
    halves = ((Half.LEFT, -0.6, SPLIT / 2), (Half.RIGHT, 0.6, SPLIT + (width - SPLIT) / 2))
    for half, baseline_x, centre_u in halves:
        tvec = np.array([centre_offset[0] - baseline_x, centre_offset[1], distance])
        h0 = homography_from_pose(FOCAL_PX, (centre_u, height / 2), rvec, tvec)
        # Shift so the board centre lands near the half's centre (plus a random offset).
        centre_px = apply_homography(h0, extent / 2)
        axis_px = np.array([centre_u, height / 2]) + centre_offset * FOCAL_PX / distance
        shift = np.array(
            [[1, 0, axis_px[0] - centre_px[0]], [0, 1, axis_px[1] - centre_px[1]], [0, 0, 1.0]]
        )
        homographies[half] = shift @ h0
    return homographies


def accuracy(n_images: int, seed: int, methods: tuple[str, ...]) -> dict:
    rng = np.random.default_rng(seed)
    scenes = []
    for index in range(n_images):
        spec = parse_board_spec(BOARDS[index % len(BOARDS)])
        homographies = random_scene(rng, spec)
        clean = render_split_image(spec, homographies, IMAGE_SIZE, SPLIT, blur_sigma_px=0.8)
        noisy = render_split_image(
            spec,
            homographies,
            IMAGE_SIZE,
            SPLIT,
            blur_sigma_px=0.8,
            noise_sigma=NOISE_SIGMA,
            rng=rng,
        )
        scenes.append((spec, clean, noisy))
    results = {}
    for method in methods:
        for label, pick in (("noise-free", 1), ("noisy", 2)):
            errors, found, tried, same_ids, seconds = [], 0, 0, 0, 0.0
            for scene in scenes:
                spec, render = scene[0], scene[pick]
                for half in Half:
                    lo, hi = (0, SPLIT) if half is Half.LEFT else (SPLIT, IMAGE_SIZE[0])
                    crop = np.ascontiguousarray(render.image[:, lo:hi])
                    truth = render.true_pixels[half]
                    if np.isnan(truth).any():
                        continue
                    tried += 1
                    start = time.perf_counter()
                    result = detect_chessboard(crop, spec, method)
                    seconds += time.perf_counter() - start
                    if not result.ok:
                        continue
                    found += 1
                    pixels = result.pixels + [lo, 0]
                    error = np.linalg.norm(pixels - truth, axis=1)
                    # An id is right when its pixel is nearer its own true corner than any other.
                    nearest = np.linalg.norm(pixels[:, None] - truth[None], axis=-1).argmin(axis=1)
                    same_ids += int((nearest == np.arange(len(truth))).all())
                    errors.append(error)
            all_errors = np.concatenate(errors) if errors else np.array([np.nan])
            results[(method, label)] = {
                "halves": tried,
                "found": found,
                "ids_right": same_ids,
                "rms_px": float(np.sqrt(np.mean(all_errors**2))),
                "p95_px": float(np.percentile(all_errors, 95)),
                "ms_per_half": 1000 * seconds / max(tried, 1),
            }
    return results


def _simulator_halves(root: Path) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(set, crop, SB grid (rows, cols, 2), true pixels (n, 2)) of every half SB finds."""
    import json

    import cv2

    manifest = json.loads((root / "simulation.json").read_text())
    split = manifest["split"]
    halves = []
    for set_name in ("calib", "test"):
        for item in manifest["sets"][set_name]["images"]:
            truth = json.loads((root / item["truth"]).read_text())
            gray = cv2.imread(str(root / item["image"]), cv2.IMREAD_GRAYSCALE)
            spec = parse_board_spec(item["board_spec"])
            for index, half in enumerate(("left", "right")):
                lo, hi = (0, split) if index == 0 else (split, gray.shape[1])
                crop = np.ascontiguousarray(gray[:, lo:hi])
                found = detect_chessboard(crop, spec, "sb")
                if not found.ok:
                    continue
                true_px = np.array(truth["corners"]["pixels"][half], dtype=float) - [lo, 0]
                grid = found.pixels.reshape(spec.rows, spec.cols, 2)
                halves.append((set_name, crop, grid, true_px))
    return halves


def _refiners() -> dict:
    """Candidate refinements: (crop uint8, SB grid) -> pixels (n, 2)."""
    import cv2

    from endomeasure.features.chessboard import refine_symmetric
    from endomeasure.features.subpixel import saddle_corners, symmetric_corners

    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)

    def subpix(fraction: float, zero_zone: float = 0.0):
        def refine(crop, grid):
            spacing = min(
                np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
                np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
            )
            half = int(np.clip(np.floor(fraction * spacing), 2, 15))
            zero = max(1, round(zero_zone * half)) if zero_zone else -1
            corners = np.ascontiguousarray(grid.reshape(-1, 1, 2), dtype=np.float32)
            out = cv2.cornerSubPix(crop, corners, (half, half), (zero, zero), criteria)
            return out.reshape(-1, 2).astype(float)

        return refine

    def symmetric(**options):
        return lambda crop, grid: symmetric_corners(crop, grid, **options).pixels

    return {
        "SB's own sub-pixel fit": lambda crop, grid: grid.reshape(-1, 2),
        "cornerSubPix, half-window 0.4 x spacing": subpix(0.4),
        "cornerSubPix, half-window 0.5 x spacing (previous default)": subpix(0.5),
        "cornerSubPix, half-window 0.6 x spacing": subpix(0.6),
        "cornerSubPix, 0.5 x spacing, zero zone 0.2 x window": subpix(0.5, 0.2),
        "saddle point of a quadratic fit (sigma 0.1 square)": (
            lambda crop, grid: saddle_corners(crop, grid).pixels
        ),
        "point symmetry, no illumination term (sigma 0.3 square)": symmetric(illumination=False),
        "point symmetry + illumination gradient, sigma 0.2 square": symmetric(sigma_squares=0.2),
        "point symmetry + illumination gradient, sigma 0.25 square": symmetric(sigma_squares=0.25),
        "point symmetry + illumination gradient, sigma 0.35 square": symmetric(sigma_squares=0.35),
        "**cornerSubPix start, point symmetry + illumination, sigma 0.3** (adopted)": (
            refine_symmetric
        ),
    }


def refinement(roots: list[Path]) -> list[str]:
    """Table rows: per refinement, RMS / max error per set and render, ms per half."""
    import json

    data = {}
    for root in roots:
        noise_free = json.loads((root / "simulation.json").read_text())["noise_free"]
        data["noise-free" if noise_free else "noisy"] = _simulator_halves(root)
    rows = []
    for name, refine in _refiners().items():
        cells, seconds, halves = [], 0.0, 0
        for label in ("noise-free", "noisy"):
            for set_name in ("calib", "test"):
                errors = []
                for set_of, crop, grid, true_px in data.get(label, []):
                    if set_of != set_name:
                        continue
                    start = time.perf_counter()
                    pixels = refine(crop, grid)
                    seconds += time.perf_counter() - start
                    halves += 1
                    diff = pixels - true_px
                    errors.append(diff[np.isfinite(diff).all(axis=1)])
                e = np.linalg.norm(np.concatenate(errors), axis=1) if errors else np.array([np.nan])
                cells.append(f"{np.sqrt(np.mean(e**2)):.3f} / {e.max():.2f}")
        rows.append(f"| {name} | {' | '.join(cells)} | {1000 * seconds / max(halves, 1):.1f} |")
    return rows


def _bare_loop(files: list[str], pattern: tuple[int, int], split: int) -> int:
    """The OpenCV calls `detect` makes per image, without anything around them."""
    import cv2

    from endomeasure.features.chessboard import adaptive_subpix_halfwindow

    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    found = 0
    for path in files:
        gray = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        for crop in (gray[:, :split], gray[:, split:]):
            crop = np.ascontiguousarray(crop)
            ok, corners, meta = cv2.findChessboardCornersSBWithMeta(
                crop, pattern, cv2.CALIB_CB_LARGER
            )
            if ok:
                grid = corners.reshape(meta.shape[0], meta.shape[1], 2)
                half = adaptive_subpix_halfwindow(grid.astype(float))
                cv2.cornerSubPix(crop, corners, (half, half), (-1, -1), criteria)
                found += 1
    return found


def throughput(files: list[str], board: str, split: int, repeats: int = 3) -> dict:
    """Images/s of the bare OpenCV loop and of ``detect`` with 1 and 2 workers (best of
    ``repeats``)."""
    import tempfile

    import cv2

    from endomeasure.pipeline.detect import detect_images

    spec = parse_board_spec(board)
    cv2.setNumThreads(1)  # as in detect's workers: parallelism by processes only
    timings = {}

    def best(fn) -> float:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return min(times)

    timings["bare"] = best(lambda: _bare_loop(files, spec.pattern_size, split))
    with tempfile.TemporaryDirectory() as tmp:
        for workers in (1, 2):
            counter = iter(range(1000))

            def run(workers=workers, counter=counter):
                # a fresh session every run: detect on a stored session would skip nothing,
                # but the embedding cost must be paid each time
                session = f"{tmp}/s{workers}-{next(counter)}.h5"
                detect_images(session, files, board, split=split, workers=workers)

            timings[f"workers{workers}"] = best(run)
    n = len(files)
    return {key: n / value for key, value in timings.items()}


SAMPLE_THROUGHPUT_BOARD = "chessboard:6x5:2"  # 12 images of the sample calibration set


def _default_images(board_default: str, count: int = 12) -> tuple[list[str], str, int]:
    """Analytic renders written to a temp dir (pass --images for a real set)."""
    import tempfile

    import cv2

    from endomeasure.features.synthetic import render_split_image as render

    folder = Path(tempfile.mkdtemp(prefix="bench-detect-"))
    rng = np.random.default_rng(5)
    spec = parse_board_spec(board_default)
    files = []
    for index in range(count):
        scene = render(
            spec, random_scene(rng, spec), IMAGE_SIZE, SPLIT, noise_sigma=NOISE_SIGMA, rng=rng
        )
        path = folder / f"img{index:02d}.png"
        cv2.imwrite(str(path), scene.image)
        files.append(str(path))
    return files, board_default, SPLIT


def _noise_free_twin() -> Path:
    """The noise-free render of sample_sessions' calib and test sets (rendered once)."""
    import json
    import subprocess

    folder = Path("/tmp/endomeasure-noise-free")
    if not (folder / "simulation.json").exists():
        seed = json.loads((ROOT / "sample_sessions" / "simulation.json").read_text())["seed"]
        exe = Path(sys.executable).parent / "endomeasure"
        subprocess.run(
            [str(exe), "simulate", str(folder), "--preset", "default", "--set", "calib,test",
             "--seed", str(seed), "--noise-free"],
            check=True, capture_output=True,
        )  # fmt: skip
    return folder


DEFAULT_ACCURACY_IMAGES, QUICK_ACCURACY_IMAGES = 6, 2
DEFAULT_METHODS = "sb,classic-subpix,sb-subpix,sb-classic-symmetry"
QUICK_THROUGHPUT_IMAGES = 4
THROUGHPUT_REPEATS = 3


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__)
    sub = parser.add_subparsers(dest="command")
    acc = sub.add_parser("accuracy", help="compare chessboard detectors against exact corners")
    acc.add_argument("--images", type=int, default=24)
    acc.add_argument("--seed", type=int, default=1)
    acc.add_argument("--methods", default=",".join(CHESSBOARD_METHODS))
    thr = sub.add_parser("throughput", help="images/s of detect against a bare OpenCV loop")
    thr.add_argument("--images", default=None, help="directory of images")
    thr.add_argument("--board", default=BOARDS[0])
    thr.add_argument("--split", type=int, default=None)
    ref = sub.add_parser("refinement", help="compare sub-pixel refinements on simulator sets")
    ref.add_argument("--sets", default=None, help="comma-separated simulator output folders")
    for command in (acc, thr, ref):  # the common options after the command too
        command.add_argument("--quick", action="store_true", default=argparse.SUPPRESS)
        command.add_argument("--no-write", action="store_true", default=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    common = [flag for flag, on in (("--quick", args.quick), ("--no-write", args.no_write)) if on]
    if args.command is None:
        images = QUICK_ACCURACY_IMAGES if args.quick else DEFAULT_ACCURACY_IMAGES
        status = main(["accuracy", "--images", str(images), "--methods", DEFAULT_METHODS, *common])
        return max(status, main(["throughput", *common]))
    report = Report("bench/bench_detect.py", args, BENCHMARKS)
    if args.command == "throughput":
        if args.images:
            files = sorted(
                str(p) for p in Path(args.images).iterdir() if p.suffix.lower() in (".png", ".tif")
            )
            board, split = args.board, args.split
            if split is None:
                import cv2

                from endomeasure.features.split import find_split

                split = find_split(cv2.imread(files[0], cv2.IMREAD_GRAYSCALE)).split
        elif (ROOT / "sample_sessions" / "simulation.json").exists():
            # the sample calibration set: its 2 mm board images, at the manifest's split
            from endomeasure.simulate.manifest import board_groups, load_manifest

            samples = ROOT / "sample_sessions"
            board = SAMPLE_THROUGHPUT_BOARD
            files = [str(p) for p in dict(board_groups(samples, "calib"))[board]]
            split = int(load_manifest(samples)["split"])
        else:
            files, board, split = _default_images(args.board)
        repeats = THROUGHPUT_REPEATS
        if args.quick:
            files, repeats = files[:QUICK_THROUGHPUT_IMAGES], 1
        rates = throughput(files, board, split, repeats)
        body = (
            "## detect throughput\n\n"
            f"`bench/bench_detect.py throughput`: {len(files)} images of board `{board}`, "
            f"split {split}; best of {repeats} runs, {platform.python_version()}, "
            f"{os.cpu_count()} cores. The bare loop is the same OpenCV calls (imread, "
            "findChessboardCornersSBWithMeta with CALIB_CB_LARGER, cornerSubPix per half) "
            "with nothing around them, one OpenCV thread, as detect's workers.\n\n"
            "| what | images/s | ratio to bare loop |\n|---|---:|---:|\n"
            f"| bare OpenCV loop (peer) | {rates['bare']:.1f} | 1.00 |\n"
            f"| `detect --workers 1` | {rates['workers1']:.1f} | "
            f"{rates['workers1'] / rates['bare']:.2f} |\n"
            f"| `detect --workers 2` | {rates['workers2']:.1f} | "
            f"{rates['workers2'] / rates['bare']:.2f} |\n\n"
            f"Two workers against one: {rates['workers2'] / rates['workers1']:.2f}x. "
            "`detect` also refines every corner to its centre of point symmetry "
            "(`features/subpixel.py`, about 5 ms per half), hashes and embeds every image, "
            "measures edge widths and checks each grid's outer lines, and pays process "
            "start-up with 2 workers.\n"
        )
        return report.finish({"detect": body})
    if args.command == "refinement":
        if args.sets:
            roots = [Path(p) for p in args.sets.split(",")]
        else:
            roots = [ROOT / "sample_sessions", _noise_free_twin()]
        print(
            "| refinement | noise-free calib | noise-free test | noisy calib | noisy test "
            "| ms/half |\n|---|---:|---:|---:|---:|---:|"
        )
        print("\n".join(refinement(roots)))
        return 0
    if args.command == "accuracy":
        methods = tuple(m for m in args.methods.split(",") if m)
        results = accuracy(args.images, args.seed, methods)
        print("| method | render | halves found | ids right | RMS px | 95 % px | ms/half |")
        print("|---|---|---|---|---|---|---|")
        for (method, label), r in results.items():
            print(
                f"| {method} | {label} | {r['found']}/{r['halves']} | "
                f"{r['ids_right']}/{r['found']} | {r['rms_px']:.4f} | {r['p95_px']:.4f} | "
                f"{r['ms_per_half']:.1f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
