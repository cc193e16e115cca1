"""Rotation vectors against OpenCV's Rodrigues (an independent implementation)."""

from __future__ import annotations

import cv2
import numpy as np

from endomeasure.geometry.rotations import rotation_matrix, rotation_vector

ROT_TOL = 1e-12


def test_rotation_matrix_matches_cv2_rodrigues(rng):
    rvecs = rng.normal(size=(200, 3)) * rng.uniform(0, 3.0, (200, 1))
    rvecs = np.concatenate([rvecs, [[0, 0, 0], [1e-10, 0, 0], [0, np.pi - 1e-7, 0]]])
    R = rotation_matrix(rvecs)
    for r, m in zip(rvecs, R, strict=True):
        np.testing.assert_allclose(m, cv2.Rodrigues(r)[0], atol=ROT_TOL)


def test_rotation_vector_inverts_rotation_matrix(rng):
    axes = rng.normal(size=(300, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 297), [0.0, 1e-9, np.pi - 1e-6]])
    rvecs = axes * angles[:, None]
    back = rotation_vector(rotation_matrix(rvecs))
    np.testing.assert_allclose(rotation_matrix(back), rotation_matrix(rvecs), atol=1e-9)
    np.testing.assert_allclose(back[:-1], rvecs[:-1], atol=1e-7)
    assert rotation_matrix(rng.normal(size=(4, 5, 3))).shape == (4, 5, 3, 3)
