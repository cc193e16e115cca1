"""Dense surfaces on the default preset's scene images against the simulator's depth.

For each scene image of the demo session (``make demo``; ``--session``) the ``raytrace``
model's dense surface of the whole left half is compared, pixel by pixel, with the true
depth of :func:`endomeasure.simulate.truth.true_depth` (the truth optics, not the fitted
model). Counted pixels: the truth sees the target there and the true point projects into
the right half. Reports coverage, median |z error| / z, the share of errors inside the
predicted 2 sigma, the time of a whole frame, the ratio to OpenCV's StereoSGBM alone on
the same halves, and the peak memory; and the coverage bound: where the matches at the
true surface pass the gates. With ``--designs WORK`` the same on random probe
designs: each design's calibrated session ``WORK/design_NNN.h5`` and scene set
``WORK/design_NNN_scene`` (both from ``bench/accuracy_designs.py`` and
``bench/operator_designs.py``), the truth from the design's own preset. Writes the
``dense-surface`` section of docs/accuracy.md unless ``--no-write``; targets: issue 20.
"""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import (  # noqa: E402
    ACCURACY,
    Report,
    Target,
    calibration_dz,
    command_line,
    design_scenes,
    parse_seeds,
    scene_options,
    script_parser,
    window_range,
)

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


class Frame(NamedTuple):
    """One scene image's figures against the truth."""

    label: str
    errors: np.ndarray  # |z error| / z of the measured counted pixels
    within: np.ndarray  # bool: inside the predicted 2 sigma
    sigma: np.ndarray  # predicted sigma / z
    counted: int
    refused: dict
    z_mm: float
    seconds: float
    sgbm_ratio: float
    size: tuple
    match_errors: np.ndarray  # |z - z of the true match under the model| / z
    match_within: np.ndarray  # bool: inside the match's own 2 sigma
    calibration_bias: float  # median (z of the true match under the model - z) / z
    calibration_dz: tuple  # near, far z error of true points; their sigma, mm (calibration_dz)
    by_grey: np.ndarray  # (bins, 2): counted and measured pixels per GREY_BINS bin
    bound: int  # counted pixels whose match at the true surface passes the gates (gates_at)


GREY_BINS = (0.0, 10.0, 30.0, 100.0, np.inf)
"""Bins of the left half's local mean grey level (a window of the smallest refinement
size), DN: where the scene is too dim for any window, coverage falls with the signal."""


class Truth(NamedTuple):
    """A frame's truth over the whole left half (h, w): the true depth (truth optics),
    the counted pixels (the right half sees their true point), the calibrated model's
    depth of their true match (:func:`_model_depth`) and that match, the truth optics'
    right pixel (h, w, 2)."""

    depth: np.ndarray
    both: np.ndarray
    z_model: np.ndarray
    right: np.ndarray


def true_right(preset, depth: np.ndarray, scale: float = 1.0):
    """The truth optics' right-half projection (pixels (h, w, 2), seen (h, w)) of every
    left pixel's true point at ``depth`` (h, w), moved to ``scale`` times its distance
    along the left ray."""
    from endomeasure.conventions import Half

    height, width = depth.shape
    uu, vv = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    rays = preset.truth_optics.rays(np.stack([uu, vv], -1).reshape(-1, 2), Half.LEFT)
    t = scale * (depth.reshape(-1) - rays.origins[:, 2]) / rays.directions[:, 2]
    seen = preset.truth_optics.project(rays.origins + t[:, None] * rays.directions, Half.RIGHT)
    return seen.pixels.reshape(height, width, 2), (seen.status == 0).reshape(height, width)


def _truth(model, preset, target) -> Truth:
    from endomeasure.simulate.truth import true_depth

    split, height = model.config.split, model.config.image_size[1]
    truth = true_depth(preset, target).astype(np.float64)[:, :split]
    right, seen = true_right(preset, truth)
    both = np.isfinite(truth) & seen
    return Truth(truth, both, _model_depth(model, (0, 0, split, height), both, right), right)


def frame(label, cm, preset, target, image, settings) -> Frame:
    """The dense surface of the whole left half against the truth optics' depth."""
    from endomeasure.measure.dense import DenseStatus, dense_surface, gates_at

    start = time.perf_counter()
    misfit = None if cm.misfit is None else cm.misfit.covariance(np.zeros((1, 2)))
    surface = dense_surface(
        cm.model, image, None, settings, param_cov=cm.param_cov, misfit_cov=misfit
    )  # fmt: skip  (as `endomeasure surface`)
    seconds = time.perf_counter() - start
    ratio = seconds / _sgbm_seconds(image, cm.model.config.split)
    truth, both, z_model, _ = _truth(cm.model, preset, target)
    ok = both & (surface.status == DenseStatus.OK)
    err = np.abs(surface.depth[ok] - truth[ok])
    refused = {s.label: int(((surface.status == s) & both).sum()) for s in DenseStatus if s}
    match_err, match_within, bias = _split_budget(cm, misfit, surface, ok, truth, z_model)
    gates = gates_at(cm.model, image, _true_surface(cm.model, z_model), None, settings)
    return Frame(label, err / truth[ok], err <= 2 * surface.sigma_depth[ok],
                 surface.sigma_depth[ok] / truth[ok], int(both.sum()), refused,
                 float(np.nanmedian(truth)), seconds, ratio, image.shape, match_err,
                 match_within, bias,
                 calibration_dz(cm.model, cm.param_cov, cm.depth_range_mm, preset.truth_optics),
                 _by_grey(surface, both, ok, settings.window_range_px[0]),
                 int((gates.passed & both).sum()))  # fmt: skip


class Bound(NamedTuple):
    """One frame's bound (``--bound-only``): the counted pixels, those the gates pass at
    the true surface, and the predicted sigma / z of the matches there (passed pixels)."""

    label: str
    counted: int
    passed: int
    sigma: np.ndarray
    unseen: int  # counted pixels no window of the ladder sees whole in the other half


def bound_frame(label, cm, preset, target, image, settings) -> Bound:
    """The gates on the matches at the true surface alone (no search)."""
    from endomeasure.measure.dense import gates_at

    _, both, z_model, _ = _truth(cm.model, preset, target)
    gates = gates_at(cm.model, image, _true_surface(cm.model, z_model), None, settings)
    passed = gates.passed & both
    # sigma_w / w = sigma_z / z to first order
    unseen = int((both & ~np.isfinite(gates.precision_px)).sum())
    return Bound(label, int(both.sum()), int(passed.sum()), (gates.sigma_w * z_model)[passed],
                 unseen)  # fmt: skip


def _model_depth(model, region, both, true_right) -> np.ndarray:
    """z (h, w) of each counted pixel's true match (the truth optics' right pixel of its
    true surface point) triangulated with the calibrated model: where an exact match
    puts the depth (NaN elsewhere)."""
    from endomeasure.solvers.triangulate import triangulate

    u0, v0, u1, v1 = region
    ql = np.stack(np.meshgrid(np.arange(u0, u1, dtype=float),
                              np.arange(v0, v1, dtype=float)), -1)  # fmt: skip
    tri = triangulate(model, ql[both], true_right[both])
    out = np.full(both.shape, np.nan)
    out[both] = np.where(tri.status == 0, tri.points[:, 2], np.nan)
    return out


def _true_surface(model, z_model: np.ndarray) -> np.ndarray:
    """The model's inverse depth of the true matches over the whole left half, carried
    on to the pixels the right half does not see by the nearest known one (a window there
    needs the surface's continuation, not a hole), for :func:`gates_at`."""
    from scipy.ndimage import distance_transform_edt

    known = np.isfinite(z_model)
    _, (iy, ix) = distance_transform_edt(~known, return_indices=True)
    return 1.0 / z_model[iy, ix]


def _by_grey(surface, both, ok, window: int) -> np.ndarray:
    """Counted and measured pixels per bin of the local mean grey level (GREY_BINS)."""
    import cv2

    mean = cv2.blur(surface.grey.astype(np.float32), (window, window))
    bins = np.digitize(mean, GREY_BINS[1:-1])
    return np.array([[int((both & (bins == k)).sum()), int((ok & (bins == k)).sum())]
                     for k in range(len(GREY_BINS) - 1)])  # fmt: skip


def _split_budget(cm, misfit, surface, ok, truth, z_model):
    """The matching's and the calibration's shares of the errors, apart.

    ``z_model`` (:func:`_model_depth`) is where a perfect match would put the depth: the
    measured depth against it is the matching's error, to be held by the match's own
    sigma (the reported sigma without the calibration's share, which is added in
    quadrature); it against the truth is the calibration's error."""
    from endomeasure.measure.dense import _calibration_sigma

    u0, v0, u1, v1 = surface.region
    ql = np.stack(np.meshgrid(np.arange(u0, u1, dtype=float),
                              np.arange(v0, v1, dtype=float)), -1)[ok]  # fmt: skip
    z = z_model[ok]
    sigma = surface.sigma_depth[ok]
    if cm.param_cov is not None or misfit is not None:
        cal = _calibration_sigma(cm.model, cm.param_cov, misfit, ql, surface.right[ok])
        sigma = np.sqrt(np.maximum(sigma**2 - cal**2, 0.0))
    good = np.isfinite(z)
    diff = np.abs(surface.depth[ok] - z)[good]
    bias = float(np.median((z - truth[ok])[good] / truth[ok][good])) if good.any() else np.nan
    return diff / truth[ok][good], diff <= 2 * sigma[good], bias


def _row(f: Frame) -> str:
    def pct(x, fn, digits):
        return f"{100 * fn(x):.{digits}f}" if x.size else "-"

    return (
        f"| {f.label} | {f.z_mm:.1f} | {100 * f.errors.size / max(f.counted, 1):.1f} | "
        f"{100 * f.bound / max(f.counted, 1):.1f} | "
        f"{pct(f.errors, np.median, 3)} | {pct(f.within, np.mean, 1)} | "
        f"{pct(f.sigma, np.median, 3)} | {pct(f.match_errors, np.median, 3)} | "
        f"{pct(f.match_within, np.mean, 1)} | {100 * f.calibration_bias:+.3f} | "
        f"{f.calibration_dz[0]:+.3f} +- {f.calibration_dz[2]:.3f} / "
        f"{f.calibration_dz[1]:+.3f} +- {f.calibration_dz[3]:.3f} | {f.seconds:.1f} | "
        + ", ".join(f"{k} {v}" for k, v in f.refused.items() if v)
        + " |"
    )


def _bin_label(k: int) -> str:
    lo, hi = GREY_BINS[k], GREY_BINS[k + 1]
    return f"grey >= {lo:g} DN" if np.isinf(hi) else f"grey {lo:g}-{hi:g} DN"


def _grey_row(name: str, frames: list[Frame]) -> str:
    counts = np.sum([f.by_grey for f in frames], axis=0)
    share = 100 * counts[:, 0] / max(int(counts[:, 0].sum()), 1)
    covered = 100 * counts[:, 1] / np.maximum(counts[:, 0], 1)
    cells = [
        f"{a:.0f} % of pixels, {b:.1f} % with depth" for a, b in zip(share, covered, strict=True)
    ]
    return f"| {name} | " + " | ".join(cells) + " |"


def default_frames(session: Path, settings_for, measure=frame) -> list:
    from endomeasure.io.session import open_session
    from endomeasure.pipeline import calibrated_model
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.scenes import plan_set

    preset = load_preset("default")
    shots = {s.name: s for s in plan_set(preset, "scene", 0)}
    with open_session(session) as reader:
        cm = calibrated_model(reader, "raytrace", session)
        images = {n: reader.image(n) for n in sorted(shots) if n in reader.image_names()}
    settings = settings_for(cm)
    return [measure(n, cm, preset, shots[n].target, im, settings) for n, im in images.items()]


def design_frames(work: Path, seed: int, images: int, settings_for, measure=frame) -> list:
    """``measure`` (:func:`frame` or :func:`bound_frame`) of the first ``images`` scene
    images of one random design (none: no usable calibration or no scene set)."""
    design = design_scenes(work, seed, images)
    if design is None:
        return []
    settings = settings_for(design.cm)
    return [measure(f"design {seed} / {shot.name}", design.cm, design.preset, shot.target,
                  design.images[shot.name], settings) for shot in design.shots]  # fmt: skip


def scene_frames(args, settings_for, measure) -> tuple[list, list]:
    """``measure`` of the default preset's scene images and, with ``--designs``, of each
    design's first ``--images`` scene images (:func:`scene_options`' arguments)."""
    frames = default_frames(args.session, settings_for, measure)
    design = []
    if args.designs is not None:
        for seed in parse_seeds(args.design_seeds):
            design += design_frames(args.designs, seed, args.images, settings_for, measure)
            print(f"design {seed}: {len(design)} frames", file=sys.stderr, flush=True)
    return frames, design


def _expected_median(sigma: np.ndarray) -> float:
    """Median |error| (percent) of errors drawn from each pixel's own Gaussian (seeded):
    what an exact search's depths would show if the predicted sigmas hold."""
    draws = np.random.default_rng(0).standard_normal(sigma.size)
    return 100 * float(np.median(np.abs(sigma * draws))) if sigma.size else np.nan


def _bound_table(frames: list[Bound], design: list[Bound], windows, prefilter, limit) -> str:
    """``--bound-only``'s table: per frame and group, the gates at the true surface."""

    def row(name, bounds):
        counted = max(sum(b.counted for b in bounds), 1)
        sigma = np.concatenate([b.sigma for b in bounds])
        return (f"| {name} | {100 * sum(b.passed for b in bounds) / counted:.1f} | "
                f"{100 * sum(b.unseen for b in bounds) / counted:.1f} | "
                f"{_expected_median(sigma):.3f} |")  # fmt: skip

    groups = [("default preset", frames)] + ([("random designs", design)] if design else [])
    return "\n".join([
        f"The gates at the true surface: windows {windows[0]}-{windows[1]} px, prefiltered "
        f"ladder {prefilter:g} px, precision limit {limit:g} px. Expected median: the "
        "matching's median |z error| / z if every passed pixel were matched exactly up to "
        "its predicted sigma (no calibration error). No window seen whole: the counted "
        "pixels whose every window leaves the other half (the overlap's edges).",
        "",
        "| frames | the gates pass % of the counted pixels | no window seen whole % | "
        "expected median % of z |",
        "|---|---:|---:|---:|",
        *[row(b.label, [b]) for b in frames + design],
        *[row(f"**{name}**", bounds) for name, bounds in groups],
        row("**all**", frames + design),
    ])  # fmt: skip


def _summary(frames: list[Frame]) -> tuple[float, float, float]:
    errors = np.concatenate([f.errors for f in frames])
    within = np.concatenate([f.within for f in frames])
    coverage = 100 * errors.size / max(sum(f.counted for f in frames), 1)
    return coverage, 100 * float(np.median(errors)), 100 * float(np.mean(within))


def _bound(frames: list[Frame]) -> float:
    """Percentage of the counted pixels the gates pass at the true surface."""
    return 100 * sum(f.bound for f in frames) / max(sum(f.counted for f in frames), 1)


def _match_summary(frames: list[Frame]) -> tuple[float, float]:
    errors = np.concatenate([f.match_errors for f in frames])
    within = np.concatenate([f.match_within for f in frames])
    return 100 * float(np.median(errors)), 100 * float(np.mean(within))


def main() -> int:
    parser = script_parser(__doc__)
    scene_options(parser)
    parser.add_argument("--window-range", type=window_range, default=None,
                        help="refinement windows LO,HI px (default: surface's)")  # fmt: skip
    parser.add_argument(
        "--prefilter",
        type=float,
        default=None,
        help="prefiltered ladder's sigma, px (0: none; default: surface's)",
    )
    parser.add_argument("--sweep-window", type=int, default=None,
                        help="the plane sweep's window, px (default: surface's)")  # fmt: skip
    parser.add_argument("--max-precision", type=float, default=None,
                        help="worst accepted match precision, px (default: surface's)")  # fmt: skip
    parser.add_argument("--bound-only", action="store_true",
                        help="only the gates at the true surface (no search; prints, "
                             "writes nothing)")  # fmt: skip
    args = parser.parse_args()
    from endomeasure import defaults
    from endomeasure.measure.dense import DenseSettings
    from endomeasure.pipeline import search_depths

    windows = args.window_range or defaults.DENSE_WINDOW_RANGE_PX

    default = DenseSettings()
    prefilter = default.prefilter_px if args.prefilter is None else args.prefilter
    sweep = default.window_px if args.sweep_window is None else args.sweep_window
    limit = default.max_precision_px if args.max_precision is None else args.max_precision

    def settings_for(cm):  # as `endomeasure surface` does
        return DenseSettings(depth_range_mm=search_depths(cm), window_range_px=windows,
                             prefilter_px=prefilter, window_px=sweep,
                             max_precision_px=limit)  # fmt: skip

    frames, design = scene_frames(args, settings_for, bound_frame if args.bound_only else frame)
    if args.bound_only:
        print(_bound_table(frames, design, windows, prefilter, limit))
        return 0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    report = Report("accuracy_dense", args, ACCURACY)
    everything = frames + design
    coverage, median, band = _summary(everything)
    vga = [f.seconds for f in everything if f.size == (480, 640)]
    checks = {
        "coverage": report.check(COVERAGE_TARGET, coverage),
        "error": report.check(ERROR_TARGET, median),
        "band": report.check(BAND_TARGET, band),
        "time": report.check(TIME_TARGET, max(vga)),
    }
    groups = [("default preset", frames)] + ([("random designs", design)] if design else [])
    per_group = []
    for name, fs in groups:
        cov, med, inside = _summary(fs)
        match_med, match_inside = _match_summary(fs)
        per_group.append(f"| {name} | {len(fs)} | {cov:.1f} | {_bound(fs):.1f} | {med:.3f} | "
                         f"{inside:.1f} | "
                         f"{match_med:.3f} | {match_inside:.1f} |")  # fmt: skip
    designs = args.designs is not None
    command = command_line(
        "accuracy_dense.py", ("--session", args.session), ("--designs", args.designs),
        ("--design-seeds", args.design_seeds if designs else None),
        ("--images", args.images if designs else None),
        ("--window-range", None if args.window_range is None else f"{windows[0]},{windows[1]}"),
        ("--prefilter", None if args.prefilter is None else f"{args.prefilter:g}"),
        ("--sweep-window", None if args.sweep_window is None else sweep),
        ("--max-precision", None if args.max_precision is None else f"{limit:g}"),
    )  # fmt: skip
    body = "\n".join([
        "## Dense surfaces on the scene images",
        "",
        f"`{command}` (the default preset: the demo's raytrace calibration, seed 0; a random "
        "design: its own calibration from its own images). Truth: the simulator's per-pixel "
        "depth through the truth optics; counted: left pixels whose true surface point the "
        f"right half sees. Sweep window {sweep} px, refinement windows "
        f"{windows[0]}-{windows[1]} px, prefiltered ladder {prefilter:g} px, precision "
        f"limit {limit:g} px. *Matching "
        "alone*: the depth against the calibrated model's own depth of the true match "
        "(the truth optics' right pixel of the true point, triangulated with the model), "
        "against the match's sigma without the calibration's share; the *calibration's "
        "depth bias* is that depth against the truth: what no matching can remove, and "
        "what the calibration's covariance and misfit must hold. The *calibration's z "
        "error* at the nearest and farthest depth its boards were seen at (true points "
        "over the field, triangulated from their true pixels): constant in mm, it is the "
        "model frame's origin set off the truth's along the axis, which no length sees; "
        "the +- is the calibration's own 1-sigma of that z (its covariance, with the "
        "extensions the fit held but cannot rule out: docs/models.md). *The gates at the "
        "true surface*: the counted pixels where some window's match at the model's depth "
        "of the true match passes the precision and score gates (`gates_at`): what an "
        "exact search could measure with these windows and gates, the texture against the "
        "noise; coverage cannot exceed it.",
        "",
        "| images | frames | depth for % | the gates at the true surface pass % | median abs z "
        "error % of z | inside 2 sigma % | matching alone: median % of z | matching alone: "
        "inside its 2 sigma % |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
        *per_group,
        "",
        "| image | z mm | depth for % | the gates at the true surface pass % | median abs z "
        "error % of z | inside 2 sigma % | "
        "median predicted sigma % of z | matching alone: median % of z | matching alone: "
        "inside its 2 sigma % | calibration's depth bias % of z | calibration's z error "
        "+- its sigma at its nearest / farthest board depth, mm | s | counted pixels refused |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        *[_row(f) for f in everything],
        "",
        "Coverage by the left half's local mean grey level (over the smallest window), "
        "all frames of each group: the share of the counted pixels in each bin and the "
        "share of those with a depth.",
        "",
        "| images | " + " | ".join(_bin_label(k) for k in range(len(GREY_BINS) - 1)) + " |",
        "|---|" + "---:|" * (len(GREY_BINS) - 1),
        *[_grey_row(name, fs) for name, fs in groups],
        "",
        f"- {checks['coverage'].target}: {coverage:.1f} % ({checks['coverage']}); the gates "
        f"pass {_bound(everything):.1f} % at the true surface",
        f"- {checks['error'].target}: {median:.3f} % ({checks['error']})",
        f"- {checks['band'].target}: {band:.1f} % ({checks['band']})",
        f"- {checks['time'].target}: {max(vga):.1f} s at most "
        f"({checks['time']}); {np.median([f.sgbm_ratio for f in everything]):.0f} x StereoSGBM "
        f"alone on the same halves (128 disparities, 9 px block); peak memory {peak_mb:.0f} MB "
        "(max RSS).",
    ])  # fmt: skip
    return report.finish({"dense-surface": body})


if __name__ == "__main__":
    sys.exit(main())
