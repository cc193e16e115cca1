"""The Brown lens camera both models share: its parameter names and its Jacobians."""

from __future__ import annotations

import numpy as np

from endomeasure.geometry.distortion import distort, distort_coeff_jacobian, distort_jacobian

__all__ = [
    "LENS_NAMES",
    "DISTORTION_NAMES",
    "RATIONAL_NAMES",
    "RATIONAL_LENS_NAMES",
    "IMAGE_TANGENTIAL_NAMES",
    "FULL_LENS_NAMES",
    "lens_units",
    "lens_jacobians",
]

LENS_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
"""The lens camera's parameters in OpenCV order (the columns of ``dq_dlens``)."""
DISTORTION_NAMES = LENS_NAMES[4:]
"""The distortion coefficients in OpenCV order, as :mod:`endomeasure.geometry.distortion`
takes them."""
RATIONAL_NAMES = ("k4", "k5", "k6")
"""The denominator of OpenCV's rational radial factor (``geometry.distortion``)."""
RATIONAL_LENS_NAMES = LENS_NAMES + RATIONAL_NAMES
"""A lens camera with the rational radial factor, in OpenCV order."""
IMAGE_TANGENTIAL_NAMES = ("p1_image", "p2_image")
"""Decentering defined on the image side (``geometry.distortion``)."""
FULL_LENS_NAMES = RATIONAL_LENS_NAMES + IMAGE_TANGENTIAL_NAMES
"""The lens camera with every distortion term ``geometry.distortion`` has."""


def lens_units(prefix: str = "", names: tuple[str, ...] = LENS_NAMES) -> dict[str, str]:
    """Units of the lens parameters ``names`` (focal lengths and principal point px,
    coefficients unitless), keyed by ``prefix + name``."""
    return {prefix + n: "px" if n in LENS_NAMES[:4] else "1" for n in names}


def lens_jacobians(x: np.ndarray, y: np.ndarray, lens) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of the pixels of undistorted normalised lens coordinates.

    Parameters
    ----------
    x, y : ndarray, shape (N,)
    lens : sequence of 9, 12 or 14 floats
        ``fx fy cx cy k1 k2 p1 p2 k3`` (:data:`LENS_NAMES`), optionally followed by
        ``k4 k5 k6`` (:data:`RATIONAL_LENS_NAMES`) and ``p1_image p2_image``
        (:data:`FULL_LENS_NAMES`).

    Returns
    -------
    dq_dxy : ndarray, shape (N, 2, 2), px
    dq_dlens : ndarray, shape (N, 2, len(lens)), px per parameter unit

    Notes
    -----
    ``q = (fx xd + cx, fy yd + cy)`` with ``(xd, yd) = distort(x, y)``.
    """
    fx, fy = lens[0], lens[1]
    coeffs = tuple(lens[4:])
    xd, yd = distort(x, y, coeffs)
    j11, j12, j21, j22 = distort_jacobian(x, y, coeffs)
    f = np.array([fx, fy])[None, :, None]
    dq_dxy = f * np.stack([np.stack([j11, j12], -1), np.stack([j21, j22], -1)], -2)
    dq_dlens = np.zeros(np.shape(x) + (2, len(lens)))
    dq_dlens[:, 0, 0] = xd
    dq_dlens[:, 1, 1] = yd
    dq_dlens[:, 0, 2] = 1.0
    dq_dlens[:, 1, 3] = 1.0
    dq_dlens[:, :, 4:] = f * distort_coeff_jacobian(x, y, coeffs)  # OpenCV order
    return dq_dxy, dq_dlens
