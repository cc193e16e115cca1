"""The ChArUco point-symmetry refinement's pieces: symmetric zone, local maps, steps input."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.features.boards import parse_board_spec
from endomeasure.features.charuco import (
    charuco_local_steps,
    detect_charuco,
    symmetric_radius_squares,
)
from endomeasure.features.subpixel import local_steps, symmetric_corners

from .conftest import SPLIT, render


def test_symmetric_zone_is_the_gap_plus_the_marker_border():
    # 1.5 mm squares, 1.125 mm 4x4 markers: gap 0.1875 mm, border cell 1.125 / 6 mm
    spec = parse_board_spec("charuco:24x20:1.5:1.125:DICT_4X4_250")
    assert symmetric_radius_squares(spec) == pytest.approx((0.1875 + 0.1875) / 1.5)
    # 5x5 bits: cells of marker / 7
    spec = parse_board_spec("charuco:10x8:1:0.7:DICT_5X5_100")
    assert symmetric_radius_squares(spec) == pytest.approx(0.15 + 0.1)


def test_local_steps_recover_an_affine_grid_with_gaps():
    cols, rows = 7, 5
    A = np.array([[21.0, -4.0], [3.0, 18.0]])  # columns: col step, row step
    row, col = np.divmod(np.arange(cols * rows), cols)
    pixels = np.stack([col, row], axis=1) @ A.T + [40.0, 30.0]
    keep = np.ones(cols * rows, dtype=bool)
    keep[[8, 9, 15, 22]] = False  # missing corners, as when markers are not decoded
    ids = np.flatnonzero(keep)
    steps = charuco_local_steps(ids, pixels[keep], cols)
    np.testing.assert_allclose(steps, np.broadcast_to(A, steps.shape), atol=1e-9)
    # a corner whose neighbours all lie on one board row cannot give a row step
    lonely = charuco_local_steps(np.array([0, 1, 2]), pixels[:3], cols)
    assert np.isnan(lonely).all()


def test_steps_input_matches_the_grid_input():
    cols, rows = 6, 5
    scene = render(board=f"chessboard:{cols}x{rows}:1.0", noise=0.0)
    true = scene.true_pixels[list(scene.true_pixels)[0]]
    gray = scene.image
    grid = (true + 0.4).reshape(rows, cols, 2)
    by_grid = symmetric_corners(gray, grid)
    by_steps = symmetric_corners(gray, None, grid.reshape(-1, 2), steps=local_steps(grid))
    np.testing.assert_array_equal(by_grid.pixels, by_steps.pixels)
    with pytest.raises(ValueError, match="start"):
        symmetric_corners(gray, None, steps=local_steps(grid))
    with pytest.raises(ValueError, match="shape"):
        symmetric_corners(gray, None, grid.reshape(-1, 2)[:3], steps=local_steps(grid))


def test_unknown_refinement_is_refused():
    scene = render(board="charuco:14x10:1.0:0.7:DICT_4X4_100")
    spec = parse_board_spec("charuco:14x10:1.0:0.7:DICT_4X4_100")
    with pytest.raises(ValueError, match="refinement"):
        detect_charuco(np.ascontiguousarray(scene.image[:, :SPLIT]), spec, "bilinear")
