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

import time

import numpy as np

import endomeasure  # noqa: F401  (pins BLAS threads before numpy loads)
from _common import BENCHMARKS, Report, Target, machine, median_time, script_parser
from bench_models import raytrace_model
from endomeasure.measure.predict import error_map, predict_measurement_error, volume_grid
from endomeasure.solvers.triangulate import triangulate

SIGMA_PX = 0.05
MAP_POINTS = 10_000
QUICK_MAP_POINTS, QUICK_RUNS = 1_000, 5
UT_TARGET = Target("one measurement's UT, image noise", "<", 20.0, " ms", "issue 8")
UT_CALIBRATION_TARGET = Target(
    "one measurement's UT, image noise + calibration", "<", 20.0, " ms", "issue 8"
)
MAP_TARGET = Target("10,000-point error map", "<", 10.0, " s", "issue 8")


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument(
        "--map-points", type=int, default=MAP_POINTS, help=f"error map points ({MAP_POINTS:,})"
    )
    args = parser.parse_args(argv)
    report = Report("bench/bench_uncertainty.py", args, BENCHMARKS, argv=argv)
    if args.quick:
        args.map_points = min(args.map_points, QUICK_MAP_POINTS)

    def runs(n: int) -> int:
        return min(n, QUICK_RUNS) if args.quick else n

    model = raytrace_model()

    # one 4 mm length at 20 mm
    pts = np.array([[-2.0, 0.0, 20.0], [2.0, 0.5, 20.5]])
    ql, qr = model.project(pts, "left").pixels, model.project(pts, "right").pixels
    free = model.free_mask
    param_cov = np.diag((1e-4 * np.maximum(np.abs(model.params[free]), 1.0)) ** 2)
    t_tri = median_time(lambda: triangulate(model, ql, qr), runs=runs(50))
    t_ut = median_time(
        lambda: predict_measurement_error(model, "length", ql, qr, sigma=SIGMA_PX), runs=runs(50)
    )
    t_lin = median_time(
        lambda: predict_measurement_error(model, "length", ql, qr, sigma=SIGMA_PX, method="linear"),
        runs=runs(50),
    )
    # a 5-point area at 20 mm: 2L+1 = 41 sigma points and 190 cross points
    ang = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    poly = np.stack([2 * np.cos(ang), 2 * np.sin(ang), 20.0 + 0.2 * np.cos(ang)], -1)
    al, ar = model.project(poly, "left").pixels, model.project(poly, "right").pixels
    t_area = median_time(
        lambda: predict_measurement_error(model, "area", al, ar, sigma=SIGMA_PX), runs=runs(20)
    )
    t_area_plain = median_time(
        lambda: predict_measurement_error(model, "area", al, ar, sigma=SIGMA_PX, cross=None),
        runs=runs(20),
    )
    t_utc = median_time(
        lambda: predict_measurement_error(
            model, "length", ql, qr, sigma=SIGMA_PX, param_cov=param_cov
        ),
        runs=runs(10),
    )

    # the volume map: an x-segment of 1 mm centred at grid points seen by both halves
    grid = volume_grid(model, np.linspace(10.0, 45.0, 15), n_u=60, n_v=45)
    if grid.shape[0] < args.map_points:
        raise SystemExit(f"the grid has only {grid.shape[0]} visible points")
    centres = grid[np.linspace(0, grid.shape[0] - 1, args.map_points).astype(int)]
    start = time.perf_counter()
    em = error_map(model, centres, "x-segment", 1.0, sigma=SIGMA_PX)
    t_map = time.perf_counter() - start
    # peer: triangulating the map's own noise-free correspondences once
    tp = centres[:, None, :] + np.array([[-0.5, 0, 0], [0.5, 0, 0]])
    pl, pr = model.project(tp, "left").pixels, model.project(tp, "right").pixels
    start = time.perf_counter()
    triangulate(model, pl, pr)
    t_peer = time.perf_counter() - start

    L = 8
    ut = report.check(UT_TARGET, t_ut * 1e3)
    utc = report.check(UT_CALIBRATION_TARGET, t_utc * 1e3)
    # the map target is about 10,000 points: another size is scaled to it (linear in n)
    map_ = report.check(MAP_TARGET, t_map * MAP_POINTS / args.map_points)
    body = f"""## Error prediction (`bench/bench_uncertainty.py`)

Raytrace design of `tests/conftest.py`, sigma = {SIGMA_PX} px ({machine()}).

One measurement (a 4 mm length at 20 mm, L = {L} pixel inputs, 2L+1 = {2 * L + 1} sigma
points in one batched triangulation), median of 50 runs:

| what | wall time | ratio to one triangulation |
|---|---:|---:|
| ML triangulation of its 2 correspondences (peer) | {t_tri * 1e3:.2f} ms | 1.0 |
| UT, image noise | {t_ut * 1e3:.2f} ms | {t_ut / t_tri:.1f} |
| linear, image noise | {t_lin * 1e3:.2f} ms | {t_lin / t_tri:.1f} |
| UT, image noise + calibration ({int(free.sum())} free parameters, median of 10) | {t_utc * 1e3:.1f} ms | {t_utc / t_tri:.1f} |
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

Error map: a 1 mm x-segment centred at each of {args.map_points:,} grid points seen by
both halves (10-45 mm), UT with image noise ({em.visible.sum():,} templates visible in
both halves):

| what | wall time | ratio |
|---|---:|---:|
| ML triangulation of the templates' {2 * args.map_points:,} correspondences (peer) | {t_peer:.2f} s | 1.0 |
| error map (projection + UT) | {t_map:.2f} s | {t_map / t_peer:.1f} |

Targets ({UT_TARGET.source}): one measurement's UT under {UT_TARGET.limit:g} ms, with image
noise ({ut}) and with the calibration too ({utc}); 10,000-point map under
{MAP_TARGET.limit:g} s ({map_}).
"""  # noqa: E501
    return report.finish({"uncertainty": body})


if __name__ == "__main__":
    raise SystemExit(main())
