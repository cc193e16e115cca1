"""Both halves of one image: full-image coordinates, quality, and reasons for failure."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half, in_half
from endomeasure.errors import BadInputError
from endomeasure.features.detect import detect_split_image

from .conftest import CHESSBOARD, IMAGE_SIZE, SPLIT, render

# See test_chessboard: noise-free analytic renders.
NOISE_FREE_RMS_PX = 0.06


def test_corners_in_full_image_pixels_of_each_half(chessboard_render):
    detection = detect_split_image(chessboard_render.image, CHESSBOARD, SPLIT)
    assert detection.board == "chessboard:9x6:1"
    assert detection.image_size == IMAGE_SIZE and detection.split == SPLIT
    assert detection.n_ok == 2
    for half in detection.halves:
        assert np.array_equal(half.ids, np.arange(54))
        assert in_half(half.pixels, half.half, SPLIT, IMAGE_SIZE).all()
        errors = np.linalg.norm(half.pixels - chessboard_render.true_pixels[half.half], axis=1)
        assert np.sqrt(np.mean(errors**2)) < NOISE_FREE_RMS_PX
        assert 1.0 < half.quality.edge_width_px < 4.0
        assert half.failure is None


def test_colour_and_16_bit_images_give_the_same_corners(chessboard_render):
    grey = chessboard_render.image
    expected = detect_split_image(grey, CHESSBOARD, SPLIT)
    for image in (np.repeat(grey[:, :, None], 3, axis=2), grey.astype(np.uint16) * 257):
        again = detect_split_image(image, CHESSBOARD, SPLIT)
        for a, b in zip(expected.halves, again.halves, strict=True):
            np.testing.assert_allclose(a.pixels, b.pixels, atol=1e-9)


@pytest.mark.parametrize(
    ("board", "reason"),
    [
        ("chessboard:8x6:1", "does not match the spec: a grid of 9x6"),
        ("chessboard:10x7:1", "does not match the spec: a whole board of 9x6"),
    ],
)
def test_wrong_board_size_is_named(chessboard_render, board, reason):
    detection = detect_split_image(chessboard_render.image, board, SPLIT)
    for half in detection.halves:
        assert not half.ok
        assert reason in half.failure
        assert half.ids.shape == (0,) and half.pixels.shape == (0, 2)


def test_partial_board_in_one_half():
    # the board centre is pushed to the right edge of the right half's view
    scene = render(board_centre_mm=(0.5, 2.5))
    detection = detect_split_image(scene.image, CHESSBOARD, SPLIT)
    assert np.isnan(scene.true_pixels[Half.RIGHT]).any()
    failed = [h for h in detection.halves if not h.ok]
    assert failed, "some half should see only part of the board"
    assert all("partial board" in h.failure for h in failed)


def test_no_board_and_too_dark(rng):
    blank = rng.normal(120, 3, IMAGE_SIZE[::-1]).clip(0, 255).astype(np.uint8)
    blank[:, :40] = 255  # some contrast, no board
    detection = detect_split_image(blank, CHESSBOARD, SPLIT)
    assert detection.left.failure == "no chessboard found"
    assert detection.right.failure.startswith("no contrast")
    dark = (blank // 30).astype(np.uint8)
    assert detect_split_image(dark, CHESSBOARD, SPLIT).left.failure.startswith("too dark")


@pytest.mark.parametrize("split", [0, IMAGE_SIZE[0], -5])
def test_split_outside_the_image_is_bad_input(chessboard_render, split):
    with pytest.raises(BadInputError, match="outside the image"):
        detect_split_image(chessboard_render.image, CHESSBOARD, split)
