"""``pinhole``: the paper's Model 1, two virtual pinhole cameras with Brown distortion.

Each half of the sensor is treated as its own camera (``fx fy cx cy k1 k2 p1 p2 k3``,
OpenCV order, principal point in full-image pixels). The left virtual camera's frame is
the model frame; the right camera's pose is ``T_right_left`` (rotation vector ``rx ry
rz``, translation ``tx ty tz`` in mm), the convention of OpenCV's ``stereoCalibrate``
``R, T``.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Half, Status
from endomeasure.geometry.distortion import (
    distort,
    distort_jacobian,
    max_monotonic_radius2,
    undistort,
)
from endomeasure.geometry.rotations import rotation_jacobian, rotation_matrix, skew
from endomeasure.models.base import CameraModel, OpenCVStereo, ParamBatch
from endomeasure.models.lens import LENS_NAMES, lens_jacobians, lens_units

__all__ = ["PinholeModel", "project_pinhole", "UNDISTORT_TOL_PX"]

UNDISTORT_TOL_PX = 1e-9  # px; well below the 1e-6 px the spec requires of the inverse


def project_pinhole(points: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points through a Brown pinhole camera.

    Parameters
    ----------
    points : ndarray, shape (N, 3), mm
    intrinsics : ndarray, shape (9,)
        ``fx fy cx cy k1 k2 p1 p2 k3``.

    Returns
    -------
    pixels : ndarray, shape (N, 2), px
    status : ndarray, shape (N,), uint8
        ``BEHIND`` for z <= 0, ``OUTSIDE_HALF`` beyond the radius where the radial
        polynomial folds back (there the formula gives a plausible but wrong pixel).

    Notes
    -----
    Equal to ``cv2.projectPoints`` with five distortion coefficients
    ``(k1, k2, p1, p2, k3)``.
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intrinsics
    z = points[:, 2]
    front = z > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        x = points[:, 0] / z
        y = points[:, 1] / z
    xd, yd = distort(x, y, (k1, k2, p1, p2, k3))
    pixels = np.stack([fx * xd + cx, fy * yd + cy], axis=-1)
    status = np.full(z.shape, Status.OK, dtype=STATUS_DTYPE)
    status[(x * x + y * y) > max_monotonic_radius2(k1, k2, k3)] = Status.OUTSIDE_HALF
    status[~front] = Status.BEHIND
    return pixels, status


class PinholeModel(CameraModel):
    """Two virtual Brown pinhole cameras and their relative pose (24 parameters)."""

    NAME: ClassVar[str] = "pinhole"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = (
        tuple(f"left_{n}" for n in LENS_NAMES)
        + tuple(f"right_{n}" for n in LENS_NAMES)
        + ("rx", "ry", "rz", "tx", "ty", "tz")
    )
    PARAM_UNITS: ClassVar[dict[str, str]] = {
        **lens_units("left_"),
        **lens_units("right_"),
        **dict.fromkeys(("rx", "ry", "rz"), "rad"),
        **dict.fromkeys(("tx", "ty", "tz"), "mm"),
    }
    GROUPS: ClassVar[dict[str, slice]] = {
        "left": slice(0, 9),
        "right": slice(9, 18),
        "rvec_right_left": slice(18, 21),
        "t_right_left": slice(21, 24),
    }

    @classmethod
    def _constraints(cls, params):
        f = params[..., [cls.index(f"{h}_{n}") for h in ("left", "right") for n in ("fx", "fy")]]
        return [(np.all(f > 0, axis=-1), "focal lengths must be positive")]

    def intrinsics(self, half: Half) -> np.ndarray:
        return self.left if Half.parse(half) is Half.LEFT else self.right

    def pose_right_left(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` of ``T_right_left``: ``p_right = R p_left + t``."""
        return rotation_matrix(self.rvec_right_left), np.array(self.t_right_left)

    def opencv_stereo(self) -> OpenCVStereo:
        """The pair as ``cv2.stereoCalibrate`` gives it (the same conventions)."""

        def matrix(half):
            fx, fy, cx, cy = self.intrinsics(half)[:4]
            return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

        R, t = self.pose_right_left()
        return OpenCVStereo(
            matrix(Half.LEFT), self.left[4:].copy(), matrix(Half.RIGHT), self.right[4:].copy(), R, t
        )

    def _to_camera(self, points: np.ndarray, half: Half) -> np.ndarray:
        if half is Half.LEFT:
            return points
        R, t = self.pose_right_left()
        return points @ R.T + t

    def _project(self, points, half):
        return project_pinhole(self._to_camera(points, half), self.intrinsics(half))

    def _project_jacobian(self, points, half):
        cam = self._to_camera(points, half)
        pixels, status = project_pinhole(cam, self.intrinsics(half))
        dq_dp = self._camera_jacobian(cam, half)
        if half is Half.RIGHT:
            dq_dp = dq_dp @ self.pose_right_left()[0]
        return pixels, status, dq_dp

    def _camera_jacobian(self, cam: np.ndarray, half: Half) -> np.ndarray:
        """d pixel / d camera-frame point (N, 2, 3) of points ``cam`` (N, 3)."""
        fx, fy, _, _, k1, k2, p1, p2, k3 = self.intrinsics(half)
        inv_z = 1.0 / cam[:, 2]
        x, y = cam[:, 0] * inv_z, cam[:, 1] * inv_z
        j11, j12, j21, j22 = distort_jacobian(x, y, (k1, k2, p1, p2, k3))
        # d(x, y)/d cam = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
        zero = np.zeros_like(x)
        dn = np.stack([np.stack([inv_z, zero, -x * inv_z], -1),
                       np.stack([zero, inv_z, -y * inv_z], -1)], -2)  # fmt: skip
        D = np.stack([np.stack([j11, j12], -1), np.stack([j21, j22], -1)], -2)
        return np.array([fx, fy])[:, None] * (D @ dn)

    def _project_jacobians(self, points, half, free):
        """Closed form: the half's intrinsics through :func:`lens_jacobians`, the right
        camera's pose by ``d(R X + t) = -[R X]_x J(rvec) d rvec + d t``."""
        cam = self._to_camera(points, half)
        pixels, status = project_pinhole(cam, self.intrinsics(half))
        dq_dcam = self._camera_jacobian(cam, half)
        zs = np.where(cam[:, 2] > 0, cam[:, 2], 1.0)
        _, dq_dintr = lens_jacobians(cam[:, 0] / zs, cam[:, 1] / zs, self.intrinsics(half))
        dq_dall = np.zeros((points.shape[0], 2, self.params.size))
        dq_dall[:, :, self.GROUPS[half.label]] = dq_dintr
        dq_dp = dq_dcam
        if half is Half.RIGHT:
            R = self.pose_right_left()[0]
            dq_dp = dq_dcam @ R
            dcam_drvec = -skew(points @ R.T) @ rotation_jacobian(np.array(self.rvec_right_left))
            dq_dall[:, :, self.GROUPS["rvec_right_left"]] = dq_dcam @ dcam_drvec
            dq_dall[:, :, self.GROUPS["t_right_left"]] = dq_dcam
        return pixels, status, dq_dp, dq_dall[:, :, free]

    def _rays(self, pixels, half):
        return self._rays_rows(pixels, half, ParamBatch(self.params[None], None))

    def _rays_rows(self, pixels, half, batch):
        """Rays with a parameter vector per pixel (``batch``; index None: its only vector)."""
        group = self.GROUPS[half.label]
        intrinsics = (batch.per_item(j) for j in range(group.start, group.stop))
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = intrinsics
        radial = (self.column(batch.table, f"{half.label}_{k}") for k in ("k1", "k2", "k3"))
        r2 = max_monotonic_radius2(*radial)
        one = batch.table.shape[0] == 1
        und = undistort(
            (pixels[:, 0] - cx) / fx,
            (pixels[:, 1] - cy) / fy,
            (k1, k2, p1, p2, k3),
            UNDISTORT_TOL_PX / np.maximum(fx, fy),
            r2_max=float(r2[0]) if one else r2[batch.index],
        )
        d = np.stack([und.x, und.y, np.ones_like(und.x)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        status = np.where(und.converged, Status.OK, Status.NOT_CONVERGED).astype(STATUS_DTYPE)
        origins = np.zeros_like(d)
        if half is Half.RIGHT:
            R = rotation_matrix(batch.table[:, self.GROUPS["rvec_right_left"]])  # (K, 3, 3)
            t = batch.table[:, self.GROUPS["t_right_left"]]
            centre = -np.einsum("kji,kj->ki", R, t)  # right camera centre in the left frame
            if one:
                origins[:] = centre[0]
                d = d @ R[0]  # R^T d for each row
            else:
                origins[:] = centre[batch.index]
                d = np.einsum("nj,nji->ni", d, R[batch.index])
        return origins, d, status
