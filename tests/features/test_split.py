"""Finding the split column from the dark prism band."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.errors import BadInputError
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.split import find_split, to_gray_float
from endomeasure.features.synthetic import render_split_image

from .conftest import IMAGE_SIZE, pose_homographies

# The band is ~24 px wide; a board's white margin next to it skews the profile a little.
SPLIT_TOLERANCE_PX = 3


@pytest.mark.parametrize("split", [260, 320, 371])
def test_finds_the_band_centre(split, rng):
    spec = parse_board_spec("chessboard:9x6:1")
    render = render_split_image(
        spec,
        pose_homographies(split=split, board_centre_mm=(4, 2.5)),
        IMAGE_SIZE,
        split,
        noise_sigma=2.0,
        rng=rng,
    )
    estimate = find_split(render.image)
    assert abs(estimate.split - split) <= SPLIT_TOLERANCE_PX
    assert estimate.contrast < 0.6


def test_colour_and_16_bit_give_the_same_split(chessboard_render):
    grey = chessboard_render.image
    colour = np.repeat(grey[:, :, None], 3, axis=2)
    wide = grey.astype(np.uint16) * 257
    expected = find_split(grey).split
    assert find_split(colour).split == expected
    assert find_split(wide).split == expected
    np.testing.assert_allclose(to_gray_float(wide), grey.astype(float))


def test_uniform_image_is_refused_with_the_override_hint():
    with pytest.raises(BadInputError) as info:
        find_split(np.full((120, 300), 128, np.uint8), path="flat.png")
    message = info.value.one_line()
    assert "no dark band" in message and "--split COLUMN" in message and "flat.png" in message


def test_band_outside_the_middle_third_is_refused(rng):
    image = rng.normal(128, 20, (100, 300)).clip(0, 255).astype(np.uint8)
    image[:, 20:40] = 5  # dark band near the left edge, middle third is busy texture
    with pytest.raises(BadInputError, match="--split"):
        find_split(image)


def test_tiny_image_is_refused():
    with pytest.raises(BadInputError, match="too small"):
        find_split(np.zeros((4, 8), np.uint8))
