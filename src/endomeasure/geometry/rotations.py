"""Rotation vectors (Rodrigues) and rotation matrices, vectorised over leading dimensions."""

from __future__ import annotations

import numpy as np

__all__ = ["rotation_matrix", "rotation_vector", "rotation_jacobian", "skew"]

_SMALL_ANGLE = 1e-8  # rad; below this the series form is exact to float64 precision


def rotation_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle).

    Parameters
    ----------
    rvec : ndarray, shape (..., 3), rad

    Returns
    -------
    ndarray, shape (..., 3, 3)

    Notes
    -----
    Rodrigues' formula ``R = I + sin(t) K + (1 - cos(t)) K^2`` with ``K`` the cross
    product matrix of the unit axis; for tiny angles the first-order series
    ``I + [r]_x`` is used, which is exact to rounding there.
    """
    rvec = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(rvec, axis=-1)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    # sin(t)/t and (1-cos(t))/t^2, with their limits 1 and 1/2 at t -> 0
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    K = skew(rvec)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]_x``, shape (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def rotation_jacobian(rvec: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l`` of SO(3) at a rotation vector.

    ``R(r + e) = Exp(J_l(r) e) R(r)`` to first order, so for a point ``X``
    ``d(R(r) X)/dr = -[R(r) X]_x J_l(r)``.

    Parameters
    ----------
    rvec : ndarray, shape (..., 3), rad

    Returns
    -------
    ndarray, shape (..., 3, 3)

    Notes
    -----
    ``J_l = I + (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2`` with ``K = [r]_x`` and
    ``t = |r|``; the series ``I + K/2 + K^2/6`` below 1e-4 rad.
    """
    rvec = np.asarray(rvec, dtype=np.float64)
    t = np.linalg.norm(rvec, axis=-1)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t**2 / 120.0, (ts - np.sin(ts)) / ts**3)
    K = skew(rvec)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix, the inverse of :func:`rotation_matrix`.

    Parameters
    ----------
    R : ndarray, shape (..., 3, 3)

    Returns
    -------
    ndarray, shape (..., 3), rad, angle in [0, pi]
    """
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R, axis1=-2, axis2=-1)
    cos_t = np.clip((trace - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos_t)
    axis_sin = (
        np.stack(
            [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
            axis=-1,
        )
        / 2.0
    )  # = sin(t) * axis
    sin_t = np.sin(theta)
    near_pi = cos_t < -0.99
    small = theta < _SMALL_ANGLE
    scale = np.where(small, 1.0, theta / np.where(sin_t == 0, 1.0, sin_t))
    rvec = axis_sin * scale[..., None]
    if np.any(near_pi):
        # Near pi, sin(t) loses precision; take the axis from the symmetric part
        # (R + I) / 2 = a a^T (1 - cos) / 2 + cos I ... use its largest column.
        B = (R[near_pi] + np.swapaxes(R[near_pi], -1, -2)) / 2.0
        c = cos_t[near_pi][..., None, None]
        A = (B - c * np.eye(3)) / (1.0 - c)  # = a a^T
        col = np.argmax(np.diagonal(A, axis1=-2, axis2=-1), axis=-1)
        axis = np.take_along_axis(A, col[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        # choose the sign that agrees with the antisymmetric part
        sign = np.sign(np.sum(axis * axis_sin[near_pi], axis=-1))
        sign = np.where(sign == 0, 1.0, sign)
        rvec[near_pi] = axis * (sign * theta[near_pi])[..., None]
    return rvec
