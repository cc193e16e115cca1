"""Epipolar curves: where the ray of a pixel in one half lands in the other half.

For a pixel ``q`` in one half, every point of its ray ``o + t d`` (the model's backward
trace; non-central models have their own origin per pixel) projects into the other half
somewhere. Over the working depth range the projections form the *epipolar curve* of
``q``: a straight line for an undistorted central pair, a gently curved one for the
``pinhole`` model with distortion, and a curve for the ``raytrace`` model, whose two
halves look through different prism faces (SPEC section 7, "operator points").

The curve is sampled densely enough that consecutive projected samples are at most
``spacing_px`` apart, so a correspondence search along it misses nothing.

Sampling in inverse depth
-------------------------
The image position of a point seen from a second viewpoint moves, to first order, in
proportion to inverse depth (disparity = baseline * focal / depth). Samples uniform in
``w = 1 / z`` are therefore nearly uniform in pixels along the curve, so a first coarse
pass that measures the largest pixel rate ``|dq/dw|`` fixes the number of samples for
the fine pass, which is then checked (and refined if a stretch is still too sparse).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from endomeasure.conventions import Half, Status

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel

__all__ = [
    "EpipolarCurve",
    "epipolar_curve",
    "other_half",
    "SPACING_PX",
    "COARSE_SAMPLES",
    "DEPTH_RANGE_MM",
]

DEPTH_RANGE_MM = (8.0, 60.0)
"""Default depths a curve spans, mm: around the working range of the paper's probe
(10-45 mm); a probe that works nearer or farther needs its own range."""

SPACING_PX = 0.4
"""Default largest distance between consecutive curve samples: below half a pixel, so the
sampled correlation along the curve resolves its peak to within a quarter pixel before
sub-pixel refinement."""
COARSE_SAMPLES = 65
"""Samples of the first pass that measures how fast the projection moves with depth."""
_MAX_PASSES = 4
"""Fine passes allowed to reach the spacing; each multiplies the sample count."""
_MAX_SAMPLES = 20000
"""Upper bound on the samples of one curve (a curve across a whole 640 px half at
0.4 px spacing needs about 1600)."""


class EpipolarCurve(NamedTuple):
    """Samples of a pixel's ray and their projections into the other half.

    Attributes
    ----------
    pixels : ndarray, shape (M, 2), px
        Projections into the other half, NaN where ``status`` is not OK.
    depths_mm : ndarray, shape (M,), mm
        z coordinate of each sample point, decreasing (samples run from the far end of
        the depth range to the near end, uniform in inverse depth).
    points : ndarray, shape (M, 3), mm
        The sample points on the ray, model frame.
    status : ndarray of uint8, shape (M,)
        Projection status of each sample (``Status.OUTSIDE_HALF`` where the point lands
        outside the other half).
    origin, direction : ndarray, shape (3,)
        The pixel's ray (mm, unit); NaN if the pixel has no ray.
    ray_status : int
        Status of the backward trace of the pixel (``Status.OK`` when it has a ray).
    """

    pixels: np.ndarray
    depths_mm: np.ndarray
    points: np.ndarray
    status: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    ray_status: int

    @property
    def inside(self) -> np.ndarray:
        """Samples that land inside the other half, shape (M,) bool."""
        return self.status == Status.OK


def other_half(half: Half | str) -> Half:
    """The half opposite ``half``."""
    return Half.RIGHT if Half.parse(half) is Half.LEFT else Half.LEFT


def _points_at_depths(origin: np.ndarray, direction: np.ndarray, depths: np.ndarray) -> np.ndarray:
    t = (depths - origin[2]) / direction[2]
    return origin + t[:, None] * direction


def _largest_step(pixels: np.ndarray) -> float:
    """Largest distance between consecutive samples that are both inside, px (0 if none)."""
    steps = np.linalg.norm(np.diff(pixels, axis=0), axis=-1)
    steps = steps[np.isfinite(steps)]
    return float(steps.max()) if steps.size else 0.0


def epipolar_curve(
    model: CameraModel,
    pixel: np.ndarray,
    half: Half | str,
    depth_range_mm: tuple[float, float] = DEPTH_RANGE_MM,
    spacing_px: float = SPACING_PX,
) -> EpipolarCurve:
    """Sample a pixel's ray over a depth range and project it into the other half.

    Parameters
    ----------
    model : CameraModel
    pixel : array_like, shape (2,), px
        Full-image pixel coordinates in ``half``.
    half : Half or {'left', 'right'}
        The half the pixel is in; the curve lies in the other one.
    depth_range_mm : (near, far), mm
        Working depth range, as z coordinates in the model frame (0 < near < far).
    spacing_px : float, px
        Largest allowed distance between consecutive projected samples.

    Returns
    -------
    EpipolarCurve
        Empty (M = 0) if the pixel has no forward ray (outside its half, failed trace).

    Raises
    ------
    ValueError
        For a depth range that is not ``0 < near < far`` or a non-positive spacing.
    """
    near, far = (float(v) for v in depth_range_mm)
    if not (0.0 < near < far and np.isfinite(far)):
        raise ValueError(f"depth range must satisfy 0 < near < far, got {depth_range_mm}")
    if not spacing_px > 0:
        raise ValueError(f"curve spacing must be positive, got {spacing_px}")
    half = Half.parse(half)
    target = other_half(half)
    rays = model.rays(np.asarray(pixel, dtype=np.float64).reshape(2), half)
    origin, direction, ray_status = rays.origins, rays.directions, int(rays.status)
    if ray_status == Status.OK and not direction[2] > 0:
        ray_status = int(Status.BEHIND)  # a ray that never reaches the working range
    if ray_status != Status.OK:
        empty2, empty = np.empty((0, 2)), np.empty(0)
        return EpipolarCurve(
            empty2, empty, np.empty((0, 3)), np.empty(0, np.uint8), origin, direction, ray_status
        )

    n = COARSE_SAMPLES
    for _ in range(_MAX_PASSES + 1):
        inverse = np.linspace(1.0 / far, 1.0 / near, n)
        depths = 1.0 / inverse
        points = _points_at_depths(origin, direction, depths)
        projection = model.project(points, target)
        step = _largest_step(projection.pixels)
        if step == 0.0 and np.count_nonzero(projection.status == Status.OK) == 1:
            step = 4.0 * spacing_px  # a lone sample inside: a short stretch, look closer
        if step <= spacing_px or n >= _MAX_SAMPLES:
            break
        # uniform in inverse depth, the step scales as 1/n: aim 10 % below the target
        n = min(_MAX_SAMPLES, int(np.ceil((n - 1) * step / (0.9 * spacing_px))) + 1)
    return EpipolarCurve(
        projection.pixels, depths, points, projection.status, origin, direction, ray_status
    )
