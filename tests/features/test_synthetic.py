"""The analytic renderer itself: pixel-centre rule and exact corner pixels."""

from __future__ import annotations

import numpy as np

from endomeasure.conventions import Half
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.synthetic import (
    BLACK_LEVEL,
    WHITE_LEVEL,
    apply_homography,
    render_split_image,
)


def test_corner_on_a_pixel_centre_splits_that_pixel_evenly():
    spec = parse_board_spec("chessboard:3x3:1")
    # 10 px per mm, board corner 0 at the centre of pixel (column 50, row 40)
    homography = np.array([[10.0, 0, 50], [0, 10.0, 40], [0, 0, 1]])
    render = render_split_image(
        spec,
        {Half.LEFT: homography},
        (200, 100),
        120,
        supersample=8,
        blur_sigma_px=0,
        band_halfwidth_px=0,
        exact_float=True,
    )
    image = render.image / 255
    np.testing.assert_allclose(render.true_pixels[Half.LEFT][0], [50, 40])
    # square (i, j) = (0, 0) (up-left of corner 0) is dark; (1, 0) right of it is white
    assert image[39, 49] == BLACK_LEVEL and image[39, 51] == WHITE_LEVEL
    assert image[41, 51] == BLACK_LEVEL and image[41, 49] == WHITE_LEVEL
    # the pixel whose centre is the corner is half covered by each colour in u and v:
    # two quarters black, two white
    assert abs(image[40, 50] - (BLACK_LEVEL + WHITE_LEVEL) / 2) < 1e-12
    # a pixel whose centre is on the vertical edge x = 0 between rows
    assert abs(image[45, 50] - (BLACK_LEVEL + WHITE_LEVEL) / 2) < 1e-12


def test_true_pixels_follow_the_homography_and_halves():
    spec = parse_board_spec("chessboard:4x3:1")
    left = np.array([[20.0, 0, 30], [0, 20.0, 30], [0, 0, 1]])
    right = np.array([[20.0, 2, 150], [1, 20.0, 30], [0, 0.001, 1]])
    render = render_split_image(spec, {Half.LEFT: left, Half.RIGHT: right}, (240, 120), 120)
    np.testing.assert_allclose(
        render.true_pixels[Half.RIGHT], apply_homography(right, spec.object_points[:, :2])
    )
    assert (render.true_pixels[Half.LEFT][:, 0] < 119.5).all()
    assert (render.true_pixels[Half.RIGHT][:, 0] >= 119.5).all()
    assert render.image.dtype == np.uint8
