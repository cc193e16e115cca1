"""Throughput of the camera models against cv2.projectPoints on the same points.

Writes the ``models`` section of docs/benchmarks.md. Run with ``make bench`` or
``.venv/bin/python bench/bench_models.py``. The raytrace model is the one of
``tests/conftest.py`` (640x480 sensor, N-BK7 biprism with 18-degree faces).
"""

from __future__ import annotations

import math
import sys

import cv2
import numpy as np

import endomeasure  # noqa: F401  (pins BLAS threads before numpy loads)
from _common import machine, median_time, write_section
from endomeasure.conventions import Status
from endomeasure.models import ModelConfig, PinholeModel, RaytraceModel

N_POINTS = 1_000_000
SEED = 7


def raytrace_model() -> RaytraceModel:
    tilt = math.radians(18.0)
    values = dict(
        fx=230.0, fy=230.0, cx=319.5, cy=239.5, k1=-0.12, k2=0.02, k3=0.0, p1=0.0, p2=0.0,
        rear_a=0.0, rear_b=0.0, rear_d=0.6, left_a=-tilt, left_b=0.0, left_d=2.2 * math.cos(tilt),
        right_a=tilt, right_b=0.0, right_d=2.2 * math.cos(tilt), n_glass=1.5168,
    )  # fmt: skip
    params = [values[n] for n in RaytraceModel.PARAM_NAMES]
    return RaytraceModel(
        np.array(params), ModelConfig((640, 480), 320, RaytraceModel.DEFAULT_FIXED)
    )


def main() -> None:
    rng = np.random.default_rng(SEED)
    model = raytrace_model()
    # points in the left half's field, 8-60 mm: from random pixels of the half
    q = np.stack([rng.uniform(0, 319, N_POINTS), rng.uniform(0, 479, N_POINTS)], axis=-1)
    rays = model.rays(q, "left")
    depth = rng.uniform(8, 60, N_POINTS)
    s = (depth - rays.origins[:, 2]) / rays.directions[:, 2]
    points = rays.origins + s[:, None] * rays.directions

    intr = np.array([230.0, 230.0, 160.0, 239.5, -0.1, 0.01, 0.0, 0.0, 0.001])
    pinhole = PinholeModel(np.concatenate([intr, intr, np.zeros(6)]), ModelConfig((640, 480), 320))
    K = np.array([[230.0, 0, 160.0], [0, 230.0, 239.5], [0, 0, 1]])
    dist = np.array([-0.1, 0.01, 0.0, 0.0, 0.001])

    model.project(points[:10], "left")  # builds the start table, compiles the kernels
    t_cv2 = median_time(lambda: cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist))
    t_ray = median_time(lambda: model.project(points, "left"))
    t_pin = median_time(lambda: pinhole.project(points, "left"))
    t_ray_back = median_time(lambda: model.rays(q, "left"))
    t_pin_back = median_time(lambda: pinhole.rays(q, "left"))
    t_start = median_time(lambda: raytrace_model().aim_map("left"), runs=3)
    valid = np.mean(model.project(points, "left").status == Status.OK)

    def row(name, t, peer=t_cv2):
        return f"| {name} | {N_POINTS / t / 1e6:.2f} M/s | {peer / t:.2f} |"

    ratio = t_cv2 / t_ray
    body = f"""## Camera models: projection throughput

{N_POINTS:,} points at 8-60 mm in the left half's field, median of 5 runs after a warm-up,
one thread, measured by `bench/bench_models.py` in one run ({machine()}). Ratio = speed
relative to `cv2.projectPoints` on the same points (higher is faster).

| operation | throughput | ratio to cv2.projectPoints |
|---|---:|---:|
| `cv2.projectPoints` (peer) | {N_POINTS / t_cv2 / 1e6:.2f} M/s | 1.00 |
{row("`raytrace.project` (ray aiming)", t_ray)}
{row("`pinhole.project`", t_pin)}
{row("`raytrace.rays` (backward)", t_ray_back)}
{row("`pinhole.rays` (backward, iterative undistortion)", t_pin_back)}

{valid:.1%} of the points projected with status OK. Building a model's ray-aiming start
table (both the polynomial and the look-up table, once per half and per model; models
derived by small parameter steps inherit it) takes {t_start * 1e3:.0f} ms.
Target: `raytrace.project` at least as fast as `cv2.projectPoints` (ratio >= 1.0);
this run {"meets" if ratio >= 1.0 else "MISSES"} it (ratio {ratio:.2f}).
"""
    if "--no-write" in sys.argv:
        print(body)
    else:
        write_section("models", body)


if __name__ == "__main__":
    main()
