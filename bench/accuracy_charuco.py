"""ChArUco detection against the simulator's truth: a board larger than the view (issue 5).

Renders the default preset's ``charuco`` set (a 24 x 20-square ChArUco board at
10-20 mm, tilted up to 30 degrees about x and y, rolled up to 20, cut by the field in
both halves) for several seeds, with the default sensor noise and noise-free, and
compares every ChArUco corner the detector reports in each half with the true pixel of
the same id (exact ray aiming through the truth optics):

- ``opencv``: ``cv2.aruco.CharucoDetector``'s own corners;
- ``subpix``: then ``cornerSubPix`` with its window inside the white gap;
- ``symmetry``: the centre of point symmetry from the detector's corners, with its
  window cut inside the symmetric zone around the corner (gap + marker border),
  ``subpix`` where it does not converge; ``--sweep`` tries several cuts.

Wrong ids: a reported corner farther than a quarter of a square from its id's true
pixel, or without a true pixel in that half. Writes the ``charuco-simulator`` section
of docs/accuracy.md unless ``--no-write``.

    .venv/bin/python bench/accuracy_charuco.py [--seeds 3] [--sweep] [--quick] [--no-write]

Target (issue 5, ChArUco): no wrong id with ``detect``'s default refinement, both renders.
``--quick``: one seed.
"""

from __future__ import annotations

import argparse
import textwrap
import time

import numpy as np

from _common import ACCURACY, Report, Target, script_parser

SECTION = "charuco-simulator"
WRONG_IDS_TARGET = Target(
    "ChArUco wrong ids with the default refinement, both renders", "==", 0, "", "issue 5"
)
WRONG_ID_SQUARES = 0.25  # a wrong id is at least a whole square (>= 14 px) away
SWEEP_FRACTIONS = (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.2, 1.5)


def render_set(preset, seeds, noise_free):
    from endomeasure.simulate.render import render
    from endomeasure.simulate.scenes import plan_set
    from endomeasure.simulate.truth import true_pixels

    out = []
    for seed in seeds:
        for shot in plan_set(preset, "charuco", seed):
            rng = np.random.default_rng([seed, shot.index, 0x636861])
            image = render(preset, shot.target, rng=rng, noise_free=noise_free).image
            truth = true_pixels(preset, shot.target.corners_camera)
            truth = {
                k: np.array([p if p is not None else [np.nan, np.nan] for p in v])
                for k, v in truth.items()
            }
            out.append((f"seed {seed} {shot.name}", shot.target, image, truth))
    return out


def evaluate(preset, renders, variants):
    """Per variant: errors (px), wrong ids, halves found, of every detected corner."""
    import cv2

    from endomeasure.features.boards import parse_board_spec
    from endomeasure.features.charuco import (
        detect_charuco,
        refine_charuco_symmetric,
    )

    split = preset.split
    stats = {name: {"errors": [], "wrong": 0, "halves": 0, "total": 0} for name in variants}
    square_sizes = []
    for _, board, image, truth in renders:
        spec = parse_board_spec(board.spec)
        for label, (a, b) in (("left", (0, split)), ("right", (split, image.shape[1]))):
            gray = np.ascontiguousarray(image[:, a:b])
            base = {
                "opencv": detect_charuco(gray, spec, "opencv"),
                "subpix": detect_charuco(gray, spec, "subpix"),
            }
            true = truth[label]
            square_px = _square_px(true, spec.cols)
            square_sizes.append(square_px)
            for name, how in variants.items():
                stats[name]["total"] += 1
                result = base["subpix" if how[0] == "symmetry" else how[0]]
                if not result.ok:
                    continue
                pixels = result.pixels
                if how[0] == "symmetry":  # as detect_charuco's: from the detector's corners
                    symmetric, converged, _ = refine_charuco_symmetric(
                        gray, result.ids, base["opencv"].pixels, spec, window_fraction=how[1]
                    )
                    pixels = np.where(converged[:, None], symmetric, pixels)
                err = np.linalg.norm(pixels + [a, 0] - true[result.ids], axis=1)
                bad = ~(err < WRONG_ID_SQUARES * square_px)
                stats[name]["wrong"] += int(bad.sum())
                stats[name]["errors"].append(err[~bad])
                stats[name]["halves"] += 1
    del cv2
    return stats, square_sizes


def _square_px(true: np.ndarray, cols: int) -> float:
    step = np.linalg.norm(true[1:] - true[:-1], axis=1)
    step[(np.arange(1, len(true)) % cols) == 0] = np.nan  # across a row end
    return float(np.nanmedian(step))


def table(stats, render_label) -> list[str]:
    rows = []
    for name, s in stats.items():
        e = np.concatenate(s["errors"]) if s["errors"] else np.empty(0)
        rows.append(
            f"| {name} | {render_label} | {s['halves']}/{s['total']} | {e.size} | "
            f"{np.sqrt(np.mean(e**2)):.3f} | {np.percentile(e, 95):.3f} | {e.max():.3f} | "
            f"{s['wrong']} |"
        )
    return rows


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = script_parser(__doc__)
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 of the set (3)")
    parser.add_argument("--sweep", action="store_true", help="also try other window cuts")
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds = 1
    return args


def refinement_variants(sweep: bool) -> dict[str, tuple]:
    """The refinements compared, by table label: ``(how,)`` or ``("symmetry", cut)``."""
    from endomeasure.features.charuco import SYMMETRY_WINDOW_FRACTION

    variants = {
        "`opencv`: CharucoDetector": ("opencv",),
        "`subpix`: + cornerSubPix (window in the gap)": ("subpix",),
        f"`symmetry`: point symmetry, cut {SYMMETRY_WINDOW_FRACTION:g}": (
            "symmetry",
            SYMMETRY_WINDOW_FRACTION,
        ),
    }
    if sweep:
        for f in SWEEP_FRACTIONS:
            if f != SYMMETRY_WINDOW_FRACTION:
                variants[f"point symmetry, cut {f:g}"] = ("symmetry", f)
    return variants


def run_renders(preset, seeds: list[int], variants: dict) -> dict:
    """Both renders (default noise, noise-free) of every seed, every variant evaluated:
    the table rows, the default refinement's stats per render, the RMS per refinement
    with the default noise, the square sizes and the image count."""
    from endomeasure.features.charuco import DEFAULT_CHARUCO_REFINEMENT

    lines, squares, summary, rms, worst, n_images = [], [], {}, {}, {}, 0
    default_name = next(n for n, how in variants.items() if how[0] == DEFAULT_CHARUCO_REFINEMENT)
    for noise_free, label in ((False, "default noise"), (True, "noise-free")):
        renders = render_set(preset, seeds, noise_free)
        n_images = len(renders)
        stats, sizes = evaluate(preset, renders, variants)
        squares += sizes
        lines += table(stats, label)
        summary[label] = stats[default_name]
        if label == "default noise":
            errors = {
                how[0]: np.concatenate(stats[n]["errors"])
                for n, how in variants.items()
                if n == default_name or how[0] != "symmetry"
            }
            rms = {k: float(np.sqrt(np.mean(e**2))) for k, e in errors.items()}
            worst = {k: float(np.max(np.abs(e))) for k, e in errors.items()}
    return {"lines": lines, "squares": squares, "summary": summary, "rms": rms,
            "worst": worst, "n_images": n_images}  # fmt: skip


def section_body(args, board, spec, runs: dict, seconds: float, report: Report) -> str:
    """The section: how it was made, the table and the verdict (checks the target)."""
    from endomeasure.features.charuco import DEFAULT_CHARUCO_REFINEMENT, symmetric_radius_squares

    seeds = list(range(args.seeds))
    summary, rms, squares = runs["summary"], runs["rms"], runs["squares"]
    worst = runs["worst"]
    r_sym = symmetric_radius_squares(spec)
    n_corners = sum(sum(e.size for e in s["errors"]) + s["wrong"] for s in summary.values())
    n_wrong = sum(s["wrong"] for s in summary.values())
    n_halves = sum(s["halves"] for s in summary.values())
    n_total = sum(s["total"] for s in summary.values())
    check = report.check(WRONG_IDS_TARGET, n_wrong)
    text = (
        f"Made by `.venv/bin/python bench/accuracy_charuco.py --seeds {args.seeds}"
        f"{' --sweep' if args.sweep else ''}` ({time.strftime('%Y-%m-%d')}, "
        f"{seconds:.0f} s): the default preset's `charuco` set for seeds "
        f"{seeds[0]}-{seeds[-1]} ({runs['n_images']} images of `{board.spec}`, "
        f"{board.squares_x * board.square_mm:g} x {board.squares_y * board.square_mm:g} mm, "
        "at 10-20 mm, tilted up to 30 degrees about x and y, rolled up to 20; the board is "
        "cut by the field in both halves of every image), rendered with the default noise "
        "and noise-free. Every corner the detector reports in a half is compared with the "
        "true pixel of its id (ray aiming through the truth optics). Wrong ids: farther "
        "than a quarter square from the own id's true pixel, or no true pixel in that "
        "half; they are left out of the RMS. A wrong id would be at least a whole square "
        f"off: {min(squares):.0f}-{max(squares):.0f} px here (median column step per half). "
        "The symmetric zone around a corner reaches the markers' inner bits, gap + border "
        f"cell = {r_sym:.3f} squares; the point-symmetry window (Gaussian, cut at 2 sigma) "
        "is cut at the stated fraction of it."
    )
    verdict = (
        f"**Acceptance (issue 5, ChArUco):** with `detect`'s default refinement "
        f"(`{DEFAULT_CHARUCO_REFINEMENT}`) {n_wrong} wrong ids among {n_corners} corners "
        f"in {n_halves}/{n_total} halves found, both renders; every half shows only part "
        f"of the board, and the same id in both halves is the same physical corner (target: "
        f"no wrong id; {check}). With "
        "the default noise the point-symmetry refinement beats `cornerSubPix` by a factor "
        f"of {rms['subpix'] / rms['symmetry']:.1f} ({rms['subpix']:.3f} -> "
        f"{rms['symmetry']:.3f} px RMS; the detector's own corners {rms['opencv']:.3f}; "
        "the chessboards' refinement: section \"Detection against the simulator's "
        f'truth"). `cornerSubPix` also walks up to {worst["subpix"]:.1f} px off a corner '
        "(its window must stay inside the white gap), which is why the symmetric fit "
        "starts from the detector's corners. "
        "`tests/features/test_charuco_simulated.py` repeats this end to end on one image "
        "(`detect_split_image` with the truth's spec)."
    )
    return "\n".join(
        [
            "## ChArUco against the simulator's truth",
            "",
            textwrap.fill(text, 88, break_on_hyphens=False),
            "",
            "| refinement | render | halves found | corners | RMS px | 95 % px | max px "
            "| wrong ids |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
            *runs["lines"],
            "",
            textwrap.fill(verdict, 88, break_on_hyphens=False),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    report = Report("bench/accuracy_charuco.py", args, ACCURACY)
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.targets import target_from_preset

    preset = load_preset("default")
    board = target_from_preset("charuco", preset.targets["charuco"])
    start = time.perf_counter()
    runs = run_renders(preset, list(range(args.seeds)), refinement_variants(args.sweep))
    seconds = time.perf_counter() - start
    body = section_body(args, board, parse_board_spec(board.spec), runs, seconds, report)
    return report.finish({SECTION: body})


if __name__ == "__main__":
    raise SystemExit(main())
