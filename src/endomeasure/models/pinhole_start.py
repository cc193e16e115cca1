"""The ``pinhole`` pair's calibration start, from the detections alone.

Each half is calibrated on its own with OpenCV (``cv2.calibrateCamera``, Zhang's
method), giving two virtual cameras and a board pose per image and half; the right
camera's pose relative to the left is the rotation average and the translation median
over the images seen in both halves.

Zhang's closed form can fail on one half and not the other (small boards in a wide
field: the homographies hardly constrain the focal length, and the fit wanders off to a
local minimum). Each half is therefore also fitted in stages from either half's focal
length: first with the principal point on the lens axis (the prism's apex images on
the lens axis, so the split column), square pixels and no tangential terms, then with
everything free. Each half keeps the calibration of least reprojection RMS on its own
corners.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from endomeasure.conventions import Half
from endomeasure.errors import CalibrationError
from endomeasure.geometry.distortion import max_monotonic_radius2
from endomeasure.geometry.rotations import rotation_matrix, rotation_vector
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.start import Observations, Start, StartContext

__all__ = ["initial_pinhole", "mean_rotation"]

_HINT = "check that the boards are tilted and at several distances"


class _HalfCalibration(NamedTuple):
    intrinsics: np.ndarray  # (9,) fx fy cx cy k1 k2 p1 p2 k3, full-image pixels
    poses: dict  # image index -> (rvec, tvec) of the board in the half's camera
    rms: float  # OpenCV's reprojection RMS on the half's corners, px


def _calibrate_half(obs: Observations, half: Half, image_size, split, focal=None):
    """OpenCV calibration of one half (a :class:`_HalfCalibration`).

    ``focal`` (px) starts a staged fit instead of Zhang's closed form: first the
    principal point on the lens axis (the split column, the middle row), square pixels,
    no tangential terms; then everything free from there.
    """
    import cv2

    width, height = image_size
    offset = 0.0 if half is Half.LEFT else float(split)
    size = (split, height) if half is Half.LEFT else (width - split, height)
    images, objp, imgp = [], [], []
    for i in range(obs.n_images):
        sel = obs.subset(i, int(half))
        if sel.size == 0:
            continue
        images.append(i)
        objp.append(obs.board_points[sel].astype(np.float32).reshape(-1, 1, 3))
        q = obs.pixels[sel] - np.array([offset, 0.0])
        imgp.append(q.astype(np.float32).reshape(-1, 1, 2))
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # its parallel reductions differ in the last bits from run to run
    K, dist, guessed = None, None, 0
    try:
        if focal is not None:
            axis = min(max(split - 0.5 - offset, 0.0), size[0] - 1.0)  # OpenCV: inside
            K = np.array([[focal, 0.0, axis], [0.0, focal, (height - 1) / 2], [0, 0, 1]])
            guessed = cv2.CALIB_USE_INTRINSIC_GUESS
            _, K, dist, _, _ = cv2.calibrateCamera(
                objp, imgp, size, K, np.zeros(5), flags=guessed | cv2.CALIB_FIX_PRINCIPAL_POINT
                | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
            )  # fmt: skip
        # radial k1 k2 (stable for ordinary fields), then k3 as well when that polynomial
        # folds back inside the observed field (strong wide-angle distortion)
        for flags in (cv2.CALIB_FIX_K3, 0):
            rms, K1, dist1, rvecs, tvecs = cv2.calibrateCamera(
                objp, imgp, size, None if K is None else K.copy(),
                None if dist is None else dist.copy(), flags=flags | guessed,
            )  # fmt: skip
            if _folded_corners(objp, rvecs, tvecs, dist1) == 0:
                break
        K, dist = K1, dist1
    except cv2.error as exc:
        raise CalibrationError(
            f"the initial calibration of the {half.label} half failed "
            f"({str(exc).strip().splitlines()[-1]})",
            hint=_HINT,
        ) from None
    finally:
        cv2.setNumThreads(threads)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    k1, k2, p1, p2, k3 = (list(dist[:5]) + [0.0] * 5)[:5]
    intr = np.array([K[0, 0], K[1, 1], K[0, 2] + offset, K[1, 2], k1, k2, p1, p2, k3])
    if not (np.all(np.isfinite(intr)) and intr[0] > 0 and intr[1] > 0 and np.isfinite(rms)):
        raise CalibrationError(
            f"the initial calibration of the {half.label} half failed (no valid focal length)",
            hint=_HINT,
        )
    rv = [np.asarray(r, dtype=np.float64).reshape(3) for r in rvecs]
    tv = [np.asarray(t, dtype=np.float64).reshape(3) for t in tvecs]
    return _HalfCalibration(intr, dict(zip(images, zip(rv, tv, strict=True), strict=True)),
                            float(rms))  # fmt: skip


def _calibrate_halves(obs: Observations, image_size, split):
    """Both halves, each the calibration of least reprojection RMS on its own corners
    among Zhang's closed form and staged fits from either half's focal length (module
    docstring)."""
    own = {half: _calibrate_half(obs, half, image_size, split) for half in Half}
    focals = sorted({float(c.intrinsics[0]) for c in own.values()})
    out = []
    for half in Half:
        best = own[half]
        for focal in focals:
            try:
                staged = _calibrate_half(obs, half, image_size, split, focal)
            except CalibrationError:
                continue
            if staged.rms < best.rms:
                best = staged
        out.append(best)
    return out


def _folded_corners(objp, rvecs, tvecs, dist) -> int:
    """How many corners lie beyond the radius where the fitted radial polynomial folds
    back: the model refuses to project them (``max_monotonic_radius2``), so such a fit
    cannot start the joint one."""
    d = (list(np.asarray(dist, dtype=np.float64).reshape(-1)) + [0.0] * 5)[:5]
    r2_max = max_monotonic_radius2(d[0], d[1], d[4])
    count = 0
    for X, rv, tv in zip(objp, rvecs, tvecs, strict=True):
        P = X.reshape(-1, 3) @ rotation_matrix(np.ravel(rv)).T + np.ravel(tv)
        r2 = (P[:, 0] ** 2 + P[:, 1] ** 2) / P[:, 2] ** 2
        count += int(np.sum(r2 > r2_max))
    return count


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotation matrices: the rotation nearest to their average."""
    U, _, Vt = np.linalg.svd(Rs.mean(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def initial_pinhole(ctx: StartContext, base: None = None) -> Start:
    """Per-half OpenCV calibration combined into a ``pinhole`` pair (a start from the
    detections alone: ``base`` is None).

    Returns
    -------
    Start
        The pair (configuration ``ctx.config``) and ``T_left_board`` per image.
    """
    obs, config = ctx.obs, ctx.config
    (intr_l, poses_l, _), (intr_r, poses_r, _) = _calibrate_halves(
        obs, config.image_size, config.split
    )
    both = sorted(set(poses_l) & set(poses_r))
    if not both:
        raise CalibrationError("no image shows the board in both halves")
    Rl = rotation_matrix(np.array([poses_l[i][0] for i in both]))
    Rr = rotation_matrix(np.array([poses_r[i][0] for i in both]))
    tl = np.array([poses_l[i][1] for i in both])
    tr = np.array([poses_r[i][1] for i in both])
    R_rl = mean_rotation(Rr @ np.swapaxes(Rl, -1, -2))
    t_rl = np.median(tr - tl @ R_rl.T, axis=0)
    rvecs = np.zeros((obs.n_images, 3))
    tvecs = np.zeros((obs.n_images, 3))
    for i in range(obs.n_images):
        if i in poses_l:
            rvecs[i], tvecs[i] = poses_l[i]
        else:
            rv, tv = poses_r[i]
            rvecs[i] = rotation_vector(R_rl.T @ rotation_matrix(rv))
            tvecs[i] = R_rl.T @ (tv - t_rl)
    params = np.concatenate([intr_l, intr_r, rotation_vector(R_rl), t_rl])
    return Start(PinholeModel(params, config), rvecs, tvecs, "per-half OpenCV calibration")
