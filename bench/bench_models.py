"""Throughput of the camera models against cv2.projectPoints on the same points.

    .venv/bin/python bench/bench_models.py [--points N] [--seed S] [--quick] [--no-write]

Writes the ``models`` section of docs/benchmarks.md (``make bench`` runs it). The raytrace
model is the simulator's default ground-truth optics. Target (issue 3): ``raytrace.project``
at least as fast as ``cv2.projectPoints`` (ratio >= 1.0). ``--quick``: 100,000 points.
"""

from __future__ import annotations

import cv2
import numpy as np

import endomeasure  # noqa: F401  (pins BLAS threads before numpy loads)
from _common import BENCHMARKS, Report, Target, machine, median_time, script_parser
from endomeasure.conventions import Status
from endomeasure.models import ModelConfig, PinholeModel, RaytraceModel
from endomeasure.simulate.preset import load_preset

N_POINTS = 1_000_000
QUICK_POINTS = 100_000
SEED = 7
PROJECT_TARGET = Target(
    "`raytrace.project` throughput / `cv2.projectPoints`", ">=", 1.0, "x", "issue 3"
)


def raytrace_model() -> RaytraceModel:
    """The simulator's ground-truth optics of the default preset (docs/simulator.md)."""
    return load_preset("default").truth_model


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, seed=SEED)
    parser.add_argument("--points", type=int, default=N_POINTS, help=f"points ({N_POINTS:,})")
    args = parser.parse_args(argv)
    report = Report("bench/bench_models.py", args, BENCHMARKS)
    n_wanted = min(args.points, QUICK_POINTS) if args.quick else args.points
    rng = np.random.default_rng(args.seed)
    model = raytrace_model()
    # points in the left half's field, 8-60 mm: from random pixels of the half
    q = np.stack([rng.uniform(0, 319, n_wanted), rng.uniform(0, 479, n_wanted)], axis=-1)
    rays = model.rays(q, "left")
    valid = rays.status == Status.OK  # pixels in the apex band's TIR corner have no ray
    q, rays = q[valid], type(rays)(*(a[valid] for a in rays))
    depth = rng.uniform(8, 60, len(q))
    s = (depth - rays.origins[:, 2]) / rays.directions[:, 2]
    points = rays.origins + s[:, None] * rays.directions

    intr = np.array([230.0, 230.0, 160.0, 239.5, -0.1, 0.01, 0.0, 0.0, 0.001])
    pinhole = PinholeModel(np.concatenate([intr, intr, np.zeros(6)]), ModelConfig((640, 480), 320))
    K = np.array([[230.0, 0, 160.0], [0, 230.0, 239.5], [0, 0, 1]])
    dist = np.array([-0.1, 0.01, 0.0, 0.0, 0.001])

    n_points = len(points)
    model.project(points[:10], "left")  # compiles the kernels
    t_cv2 = median_time(lambda: cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist))
    t_ray = median_time(lambda: model.project(points, "left"))
    t_pin = median_time(lambda: pinhole.project(points, "left"))
    t_ray_back = median_time(lambda: model.rays(q, "left"))
    t_pin_back = median_time(lambda: pinhole.rays(q, "left"))
    fresh = model.params * 1.01  # > 1e-3 relative: no inherited start data

    def build(table):
        return lambda: model.with_params(fresh).aim_map("left", table=table)

    t_start, t_table = median_time(build(False), runs=3), median_time(build(True), runs=3)
    valid = np.mean(model.project(points, "left").status == Status.OK)

    def row(name, t, peer=t_cv2):
        return f"| {name} | {n_points / t / 1e6:.2f} M/s | {peer / t:.2f} |"

    ratio = t_cv2 / t_ray
    check = report.check(PROJECT_TARGET, ratio)
    body = f"""## Camera models: projection throughput

{n_points:,} points at 8-60 mm in the left half's field of the default preset's optics
(the simulator's truth: 37-degree biprism, 640x480), median of 5 runs after a warm-up,
one thread, measured by `bench/bench_models.py` in one run ({machine()}). Ratio = speed
relative to `cv2.projectPoints` on the same points (higher is faster).

| operation | throughput | ratio to cv2.projectPoints |
|---|---:|---:|
| `cv2.projectPoints` (peer) | {n_points / t_cv2 / 1e6:.2f} M/s | 1.00 |
{row("`raytrace.project` (ray aiming)", t_ray)}
{row("`pinhole.project`", t_pin)}
{row("`raytrace.rays` (backward)", t_ray_back)}
{row("`pinhole.rays` (backward, iterative undistortion)", t_pin_back)}

{valid:.1%} of the points projected with status OK. A model's ray-aiming start data
per half, built on first use (models derived by small parameter steps inherit it), takes
{t_start * 1e3:.0f} ms to build as the polynomial alone and {t_table * 1e3:.0f} ms with the
look-up table that batches of 200,000 points or more use.
Target ({PROJECT_TARGET.source}): `raytrace.project` at least as fast as
`cv2.projectPoints` (ratio >= {PROJECT_TARGET.limit:g}); this run: {check} (ratio {ratio:.2f}).
"""
    return report.finish({"models": body})


if __name__ == "__main__":
    raise SystemExit(main())
