"""Speed of the error prediction: one measurement's unscented transform, and a
10,000-point error map of the working volume, each against a peer in the same run.

Usage::

    .venv/bin/python bench/bench_uncertainty.py [--map-points N] [--quick] [--no-write]

Prints the timings and rewrites the ``uncertainty`` section of docs/benchmarks.md
(``--no-write``: print only). Model: the raytrace design of ``bench_models.py``. Targets
(issue 8): one measurement's UT under 20 ms, a 10,000-point map under 10 s. A 5-point
area shows the cost of the UT's cross points (measurements of three or more points).
``--quick``: a 1,000-point map and 5 runs per median (the targets are then not enforced).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

import endomeasure  # noqa: F401  (pins BLAS threads before numpy loads)
from _common import BENCHMARKS, Report, Target, machine, median_time, script_parser
from bench_models import raytrace_model
from endomeasure.measure.predict import (
    ImageNoise,
    error_map,
    predict_measurement_error,
    volume_grid,
)
from endomeasure.solvers.misfit import ModelMisfit
from endomeasure.solvers.triangulate import triangulate

SIGMA_PX = 0.05
NOISE = ImageNoise(SIGMA_PX)
MAP_POINTS = 10_000
QUICK_MAP_POINTS, QUICK_RUNS = 1_000, 5
UT_TARGET = Target("one measurement's UT, image noise", "<", 20.0, " ms", "issue 8")
UT_CALIBRATION_TARGET = Target(
    "one measurement's UT, image noise + calibration", "<", 20.0, " ms", "issue 8"
)
UT_MODEL_TARGET = Target(
    "one measurement's UT, image noise + calibration + model error", "<", 20.0, " ms", "issue 17"
)
MAP_TARGET = Target("10,000-point error map", "<", 10.0, " s", "issue 8")
MAP_MODEL_TARGET = Target("10,000-point error map with model error", "<", 10.0, " s", "issue 17")
MISFIT = ModelMisfit([[0.02, 0.01], [0.02, 0.01]], [-0.6, -0.2], 17.0, 60.0, [[0.01] * 2] * 2)
"""A model misfit of the size design 18's raytrace calibration shows (1.5 times its noise)."""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = script_parser(__doc__)
    parser.add_argument(
        "--map-points", type=int, default=MAP_POINTS, help=f"error map points ({MAP_POINTS:,})"
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.map_points = min(args.map_points, QUICK_MAP_POINTS)
    return args


def time_one_measurement(model, runs: Callable[[int], int]) -> dict[str, float]:
    """Median wall times (s) of one length's triangulation and its predictions, and of a
    5-point area's; ``runs(n)``: the runs for a figure that asks for n."""
    # one 4 mm length at 20 mm
    pts = np.array([[-2.0, 0.0, 20.0], [2.0, 0.5, 20.5]])
    ql, qr = model.project(pts, "left").pixels, model.project(pts, "right").pixels
    free = model.free_mask
    param_cov = np.diag((1e-4 * np.maximum(np.abs(model.params[free]), 1.0)) ** 2)
    t = {"tri": median_time(lambda: triangulate(model, ql, qr), runs=runs(50))}
    t["ut"] = median_time(
        lambda: predict_measurement_error(model, "length", ql, qr, noise=NOISE), runs=runs(50)
    )
    t["lin"] = median_time(
        lambda: predict_measurement_error(model, "length", ql, qr, noise=NOISE, method="linear"),
        runs=runs(50),
    )
    # a 5-point area at 20 mm: 2L+1 = 41 sigma points and 190 cross points
    ang = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    poly = np.stack([2 * np.cos(ang), 2 * np.sin(ang), 20.0 + 0.2 * np.cos(ang)], -1)
    al, ar = model.project(poly, "left").pixels, model.project(poly, "right").pixels
    t["area"] = median_time(
        lambda: predict_measurement_error(model, "area", al, ar, noise=NOISE), runs=runs(20)
    )
    t["area_plain"] = median_time(
        lambda: predict_measurement_error(model, "area", al, ar, noise=NOISE, cross=None),
        runs=runs(20),
    )
    t["utc"] = median_time(
        lambda: predict_measurement_error(
            model, "length", ql, qr, noise=NOISE, param_cov=param_cov
        ),
        runs=runs(10),
    )
    t["utcm"] = median_time(
        lambda: predict_measurement_error(
            model, "length", ql, qr, noise=NOISE, param_cov=param_cov, misfit=MISFIT
        ),
        runs=runs(10),
    )
    return t


def time_error_map(model, n_points: int) -> tuple[float, float, float, int]:
    """Wall times (s) of an ``n_points`` error map, of the same with a model misfit and of
    its peer triangulation, and the number of its templates visible in both halves."""
    # the volume map: an x-segment of 1 mm centred at grid points seen by both halves
    grid = volume_grid(model, np.linspace(10.0, 45.0, 15), n_u=60, n_v=45)
    if grid.shape[0] < n_points:
        raise SystemExit(f"the grid has only {grid.shape[0]} visible points")
    centres = grid[np.linspace(0, grid.shape[0] - 1, n_points).astype(int)]
    start = time.perf_counter()
    em = error_map(model, centres, "x-segment", 1.0, noise=NOISE)
    t_map = time.perf_counter() - start
    start = time.perf_counter()
    error_map(model, centres, "x-segment", 1.0, noise=NOISE, misfit=MISFIT)
    t_map_model = time.perf_counter() - start
    # peer: triangulating the map's own noise-free correspondences once
    tp = centres[:, None, :] + np.array([[-0.5, 0, 0], [0.5, 0, 0]])
    pl, pr = model.project(tp, "left").pixels, model.project(tp, "right").pixels
    start = time.perf_counter()
    triangulate(model, pl, pr)
    return t_map, t_map_model, time.perf_counter() - start, int(em.visible.sum())


def section_body(t: dict[str, float], n_free: int, n_points: int, t_map: tuple[float, float],
                 t_peer: float, n_visible: int, checks: tuple) -> str:  # fmt: skip
    """The ``uncertainty`` section."""
    t_tri, t_ut, t_lin, t_utc, t_utcm = t["tri"], t["ut"], t["lin"], t["utc"], t["utcm"]
    t_area, t_area_plain = t["area"], t["area_plain"]
    t_map, t_map_model = t_map
    ut, utc, utcm, map_, map_model = checks
    L = 8
    return f"""## Error prediction (`bench/bench_uncertainty.py`)

Raytrace design of `tests/conftest.py`, sigma = {SIGMA_PX} px ({machine()}).

One measurement (a 4 mm length at 20 mm, L = {L} pixel inputs, 2L+1 = {2 * L + 1} sigma
points in one batched triangulation), median of 50 runs:

| what | wall time | ratio to one triangulation |
|---|---:|---:|
| ML triangulation of its 2 correspondences (peer) | {t_tri * 1e3:.2f} ms | 1.0 |
| UT, image noise | {t_ut * 1e3:.2f} ms | {t_ut / t_tri:.1f} |
| linear, image noise | {t_lin * 1e3:.2f} ms | {t_lin / t_tri:.1f} |
| UT, image noise + calibration ({n_free} free parameters, median of 10) | {t_utc * 1e3:.1f} ms | {t_utc / t_tri:.1f} |
| UT, image noise + calibration + model error (8 offset inputs, median of 10) | {t_utcm * 1e3:.1f} ms | {t_utcm / t_tri:.1f} |
| UT of a 5-point area, 41 sigma points + 190 cross points (median of 20) | {t_area * 1e3:.2f} ms | {t_area / t_tri:.1f} |
| same, plain 41-point UT (`cross=None`) | {t_area_plain * 1e3:.2f} ms | {t_area_plain / t_tri:.1f} |

With the calibration covariance every parameter sigma point is another model; all
of them are triangulated in the same batched solve, with a parameter vector per
correspondence (`triangulate(..., params=...)`; one solve per model took 125 ms in
this script before that change, 2026-11-23).
Measurements of three or more points also get one cross point per pair of pixel
coordinates (the variance then is second-order exact,
`endomeasure.solvers.uncertainty`); each moves at most two points, and only distinct
points are triangulated.

Error map: a 1 mm x-segment centred at each of {n_points:,} grid points seen by
both halves (10-45 mm), UT with image noise ({n_visible:,} templates visible in
both halves):

| what | wall time | ratio |
|---|---:|---:|
| ML triangulation of the templates' {2 * n_points:,} correspondences (peer) | {t_peer:.2f} s | 1.0 |
| error map (projection + UT) | {t_map:.2f} s | {t_map / t_peer:.1f} |
| the same with a model misfit (each template its own input covariance, batches of 1024) | {t_map_model:.2f} s | {t_map_model / t_peer:.1f} |

Targets ({UT_TARGET.source}, issue 17): one measurement's UT under {UT_TARGET.limit:g} ms,
with image noise ({ut}), with the calibration too ({utc}) and with the model error as
well ({utcm}); 10,000-point map under {MAP_TARGET.limit:g} s ({map_}; with the model error
{map_model}).
"""  # noqa: E501


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    report = Report("bench/bench_uncertainty.py", args, BENCHMARKS)

    def runs(n: int) -> int:
        return min(n, QUICK_RUNS) if args.quick else n

    model = raytrace_model()
    t = time_one_measurement(model, runs)
    t_map, t_map_model, t_peer, n_visible = time_error_map(model, args.map_points)
    ut = report.check(UT_TARGET, t["ut"] * 1e3)
    utc = report.check(UT_CALIBRATION_TARGET, t["utc"] * 1e3)
    utcm = report.check(UT_MODEL_TARGET, t["utcm"] * 1e3)
    # the map target is about 10,000 points: another size is scaled to it (linear in n)
    scale = MAP_POINTS / args.map_points
    map_ = report.check(MAP_TARGET, t_map * scale)
    map_model = report.check(MAP_MODEL_TARGET, t_map_model * scale)
    n_free = int(model.free_mask.sum())
    body = section_body(t, n_free, args.map_points, (t_map, t_map_model), t_peer, n_visible,
                        (ut, utc, utcm, map_, map_model))  # fmt: skip
    return report.finish({"uncertainty": body})


if __name__ == "__main__":
    raise SystemExit(main())
