"""The ``pinhole`` pair's calibration start, from the detections alone.

Each half is calibrated on its own with OpenCV (``cv2.calibrateCamera``, Zhang's
method), giving two virtual cameras and a board pose per image and half; the right
camera's pose relative to the left is the rotation average and the translation median
over the images seen in both halves.
"""

from __future__ import annotations

import numpy as np

from endomeasure.conventions import Half
from endomeasure.errors import CalibrationError
from endomeasure.geometry.distortion import max_monotonic_radius2
from endomeasure.geometry.rotations import rotation_matrix, rotation_vector
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.start import Observations, Start, StartContext

__all__ = ["initial_pinhole", "mean_rotation"]

_HINT = "check that the boards are tilted and at several distances"


def _calibrate_half(obs: Observations, half: Half, image_size, split):
    """OpenCV calibration of one half: intrinsics (9,) in full-image pixels and the
    board pose ``(rvec, tvec)`` of each image seen in the half, by image index."""
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
    try:
        # radial k1 k2 (stable for ordinary fields), then k3 as well when that polynomial
        # folds back inside the observed field (strong wide-angle distortion)
        for flags in (cv2.CALIB_FIX_K3, 0):
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
                objp, imgp, size, None, None, flags=flags
            )
            if _folded_corners(objp, rvecs, tvecs, dist) == 0:
                break
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
    return intr, dict(zip(images, zip(rv, tv, strict=True), strict=True))


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
    intr_l, poses_l = _calibrate_half(obs, Half.LEFT, config.image_size, config.split)
    intr_r, poses_r = _calibrate_half(obs, Half.RIGHT, config.image_size, config.split)
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
