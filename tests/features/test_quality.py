"""The edge-width quality figure against blur of known size and OpenCV's own estimate."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.features.boards import parse_board_spec
from endomeasure.features.detect import detect_split_image
from endomeasure.features.synthetic import render_split_image

from .conftest import IMAGE_SIZE, SPLIT, pose_homographies

# 10-90 % width of a Gaussian edge is 2.563 sigma; pixel box filter adds 1/12 px^2 of
# variance, profiles are sampled every 0.25 px: allow 20 %.
WIDTH_REL_TOL = 0.2
# OpenCV's estimateChessboardSharpness walks between square centres with its own
# sampling; agreement within 30 % shows both measure the same thing.
OPENCV_REL_TOL = 0.3


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_edge_width_matches_gaussian_blur_and_opencv(sigma):
    cv2 = pytest.importorskip("cv2")
    spec = parse_board_spec("chessboard:9x6:1")
    scene = render_split_image(
        spec,
        pose_homographies(tilt_deg=(0, 0), roll_deg=0, board_centre_mm=(4, 2.5)),
        IMAGE_SIZE,
        SPLIT,
        blur_sigma_px=sigma,
    )
    detection = detect_split_image(scene.image, spec, SPLIT)
    measured = detection.left.quality.edge_width_px
    expected = 2.563 * np.sqrt(sigma**2 + 1 / 12)
    assert measured == pytest.approx(expected, rel=WIDTH_REL_TOL)
    crop = np.ascontiguousarray(scene.image[:, :SPLIT])
    corners = detection.left.pixels.astype(np.float32).reshape(-1, 1, 2)
    opencv = cv2.estimateChessboardSharpness(crop, spec.pattern_size, corners)[0][0]
    assert measured == pytest.approx(opencv, rel=OPENCV_REL_TOL)
    assert 0 < detection.left.quality.brightness < 255
    assert detection.left.quality.contrast > 150
