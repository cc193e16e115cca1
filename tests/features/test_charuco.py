"""ChArUco: the board's own ids in both halves at any roll, also when the board exceeds the view."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.features.boards import parse_board_spec
from endomeasure.features.charuco import detect_charuco
from endomeasure.features.detect import detect_split_image

from .conftest import SPLIT, render

BOARD = "charuco:14x10:1.0:0.7:DICT_4X4_100"
# Corners interpolated from markers and refined to the centre of point symmetry with a
# window kept off the markers' bits: measured 0.044 px RMS with noise (cornerSubPix in the
# white gap 0.096); an id error would be a whole square (>= 15 px) off.
CHARUCO_RMS_PX = 0.15
# Markers of about 3 px per bit under blur and noise: 75-100 % of a whole board's corners
# come back at any roll (rolls 0-270 measured; the rest lack a decoded marker, no id is
# wrong).
MIN_FOUND_FRACTION = 0.7


@pytest.mark.parametrize("roll", [0.0, 25.0, 135.0, 180.0, 235.0, 320.0])
def test_partial_view_gives_board_ids_in_both_halves(roll, rng):
    spec = parse_board_spec(BOARD)
    # 13x9 inner corners at ~26 px per square: about 17 squares wide, more than a half
    scene = render(
        board=BOARD,
        noise=2.0,
        rng=rng,
        roll_deg=roll,
        distance_mm=16.0,
        tilt_deg=(8.0, -10.0),
        focal_px=420.0,
    )
    detection = detect_split_image(scene.image, spec, SPLIT)
    for half_detection in detection.halves:
        assert half_detection.ok, half_detection.failure
        truth = scene.true_pixels[half_detection.half]
        # the view is partial: some corners fall outside this half
        assert np.isnan(truth).any()
        assert len(half_detection.ids) >= 20
        errors = np.linalg.norm(half_detection.pixels - truth[half_detection.ids], axis=1)
        assert not np.isnan(errors).any()  # no id names a corner that is not in view
        assert np.sqrt(np.mean(errors**2)) < CHARUCO_RMS_PX
    common = np.intersect1d(detection.left.ids, detection.right.ids)
    assert len(common) >= 10


@pytest.mark.parametrize("roll", [90.0, 270.0])
def test_portrait_board_gets_its_own_ids_in_both_halves(roll, rng):
    """Turned a quarter, the 14x10-square board fits each half whole: most corners, each
    at the true pixel of its id."""
    spec = parse_board_spec(BOARD)
    scene = render(board=BOARD, noise=2.0, rng=rng, roll_deg=roll, tilt_deg=(8.0, -10.0))
    detection = detect_split_image(scene.image, spec, SPLIT)
    for half_detection in detection.halves:
        assert half_detection.ok, half_detection.failure
        truth = scene.true_pixels[half_detection.half]
        assert not np.isnan(truth).any()
        assert len(half_detection.ids) >= MIN_FOUND_FRACTION * spec.n_corners
        errors = np.linalg.norm(half_detection.pixels - truth[half_detection.ids], axis=1)
        assert np.sqrt(np.mean(errors**2)) < CHARUCO_RMS_PX


def test_no_markers_is_a_reason(chessboard_render):
    spec = parse_board_spec(BOARD)
    result = detect_charuco(np.ascontiguousarray(chessboard_render.image[:, :SPLIT]), spec)
    assert not result.ok
    assert "markers" in result.failure


def test_wrong_dictionary_finds_nothing(rng):
    scene = render(board=BOARD, rng=rng)
    other = parse_board_spec("charuco:14x10:1.0:0.7:DICT_5X5_100")
    result = detect_charuco(np.ascontiguousarray(scene.image[:, :SPLIT]), other)
    assert not result.ok
