"""Finding the split column from the dark prism band."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.errors import BadInputError
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.split import (
    find_split,
    find_split_in_set,
    split_evidence,
    to_gray_float,
)
from endomeasure.features.synthetic import render_split_image

from .conftest import IMAGE_SIZE, pose_homographies

# The boards' white margins run up to the band in these renders and skew it a little.
SPLIT_TOLERANCE_PX = 2
# Sub-pixel on these clean sets (issue 16 asks for 2 px on real scenes).
CENTRE_TOLERANCE_PX = 1.0
# The band's width is measured from a fitted profile with knots X/8 apart.
WIDTH_TOLERANCE = 0.25


def band_images(
    rng: np.random.Generator,
    centre: float,
    *,
    size: tuple[int, int] = (400, 300),
    slope: float = 0.0,
    half_width: float = 6.0,
    depth: float = 0.9,
    levels: tuple[float, float] = (60.0, 140.0),
    images: int = 4,
    stripe: bool = False,
) -> list[np.ndarray]:
    """Images of one probe: a raised-cosine band (not the simulator's Gaussian) about the
    line ``u = centre + slope (v - v_mid)``, support ``+-half_width``; each half its own
    level (a step at the apex), slow shading and a bright board that move between images;
    optionally a dark scene stripe at a random column; dark level 4, noise 2 grey levels.
    """
    width, height = size
    u = np.arange(width, dtype=float)[None, :]
    v = np.arange(height, dtype=float)[:, None]
    x = u - (centre + slope * (v - (height - 1) / 2.0))
    dip = np.where(np.abs(x) < half_width, 0.5 * (1.0 + np.cos(np.pi * x / half_width)), 0.0)
    out = []
    for _ in range(images):
        shading = np.sin(2 * np.pi * (u / rng.uniform(150, 300) + rng.uniform()))
        shading = shading * np.cos(2 * np.pi * (v / rng.uniform(100, 300) + rng.uniform()))
        scene = np.where(x < 0, levels[0], levels[1]) * (1.0 + 0.15 * shading)
        for lo, hi in ((0.0, centre - 3 * half_width), (centre + 3 * half_width, width)):
            if hi - lo > 40:
                board = rng.uniform(20, min(80, hi - lo - 10))
                left = int(rng.uniform(lo, hi - board))
                top = int(rng.uniform(0, height - 60))
                scene[top : top + 60, left : left + int(board)] = 230.0
        if stripe:
            column = int(rng.uniform(20, width - 20))
            if abs(column - centre) > 6 * half_width:
                scene[:, column : column + 4] *= 0.1
        image = 4.0 + scene * (1.0 - depth * dip) + rng.normal(0.0, 2.0, scene.shape)
        out.append(np.clip(np.round(image), 0, 255).astype(np.uint8))
    return out


def estimate_of(images: list[np.ndarray]):
    return find_split_in_set([split_evidence(image) for image in images])


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
    assert estimate.images == 1


@pytest.mark.parametrize(
    "case",
    [
        {"centre": 200.3},
        {"centre": 45.7},  # the split anywhere: near the left border
        {"centre": 352.2},  # ... and near the right one
        {"centre": 180.5, "slope": 0.03},  # a tilted apex line
        {"centre": 210.2, "levels": (15.0, 200.0)},  # halves of very unequal light
        {"centre": 190.6, "half_width": 14.0},  # a wide band
        {"centre": 205.4, "depth": 0.5},  # a shallow band
    ],
)
def test_a_set_finds_the_band_of_any_probe(case, rng):
    estimate = estimate_of(band_images(rng, **case))
    assert abs(estimate.centre_px - case["centre"]) <= CENTRE_TOLERANCE_PX
    assert estimate.split == int(np.floor(estimate.centre_px + 1.0))
    assert estimate.images == 4


def test_width_depth_and_tilt_are_measured(rng):
    estimate = estimate_of(band_images(rng, 190.3, slope=-0.02, half_width=8.0))
    # a raised cosine of support +-w is at half its depth at |x| = w / 2
    assert estimate.width_px == pytest.approx(8.0, rel=WIDTH_TOLERANCE)
    assert estimate.contrast == pytest.approx(0.1, abs=0.1)
    assert estimate.slope == pytest.approx(-0.02, abs=0.005)


def test_a_dark_stripe_that_moves_is_outvoted(rng):
    images = band_images(rng, 230.4, stripe=True, images=6)
    assert abs(estimate_of(images).centre_px - 230.4) <= CENTRE_TOLERANCE_PX


def test_the_band_not_the_vignetted_border(rng):
    width, height = 400, 300
    u = np.arange(width)[None, :] - (width - 1) / 2
    v = np.arange(height)[:, None] - (height - 1) / 2
    falloff = np.cos(np.arctan(np.hypot(u, v) / 150.0)) ** 4
    images = [
        np.clip(
            4 + 200 * falloff * image.astype(float) / 255 + rng.normal(0, 1, falloff.shape), 0, 255
        ).astype(np.uint8)  # fmt: skip
        for image in band_images(rng, 140.2, levels=(200.0, 200.0))
    ]
    assert abs(estimate_of(images).centre_px - 140.2) <= CENTRE_TOLERANCE_PX


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


def test_noise_is_no_band(rng):
    images = [rng.normal(128, 10, (240, 320)).clip(0, 255).astype(np.uint8) for _ in range(3)]
    with pytest.raises(BadInputError, match="no dark band"):
        estimate_of(images)


def test_smooth_vignetting_is_no_band(rng):
    u = np.arange(320)[None, :] - 159.5
    v = np.arange(240)[:, None] - 119.5
    falloff = np.cos(np.arctan(np.hypot(u, v) / 150.0)) ** 4
    image = (200 * falloff + rng.normal(0, 2, falloff.shape)).clip(0, 255).astype(np.uint8)
    with pytest.raises(BadInputError, match="--split"):
        find_split(image)


def test_images_of_different_sizes_are_refused(rng):
    evidence = [split_evidence(image) for image in band_images(rng, 200.0, images=1)]
    evidence += [split_evidence(image) for image in band_images(rng, 150.0, size=(300, 300))]
    with pytest.raises(BadInputError, match="differ in size"):
        find_split_in_set(evidence)


def test_tiny_image_is_refused():
    with pytest.raises(BadInputError, match="too small"):
        find_split(np.zeros((4, 8), np.uint8))


def board_edge_images(
    rng: np.random.Generator,
    centre: float,
    *,
    size: tuple[int, int] = (400, 300),
    half_width: float = 14.0,
    images: int = 12,
) -> list[np.ndarray]:
    """Small bright boards on a black background (design 32's first board group): the
    background one grey level above the dark level, hardly any noise (so no dither), the
    raised-cosine band of :func:`band_images`; in five images of six a blurred board edge
    0.8-1.6 band half-widths from the apex on one side, black on the other."""
    from scipy.ndimage import gaussian_filter

    width, height = size
    x = np.arange(width, dtype=float)[None, :] - centre
    dip = np.where(np.abs(x) < half_width, 0.5 * (1.0 + np.cos(np.pi * x / half_width)), 0.0)
    out = []
    for i in range(images):
        scene = np.full((height, width), 1.0)
        if i % 6 != 5:
            gap = rng.uniform(0.8, 1.6) * half_width
            top = int(rng.uniform(0, height - 120))
            lo = centre + gap if i % 2 else centre - gap - 60
            scene[top : top + 120, int(lo) : int(lo + 60)] = 150.0
            scene = gaussian_filter(scene, 3.0)
        image = 3.0 + scene * (1.0 - 0.93 * dip) + rng.normal(0.0, 0.05, scene.shape)
        out.append(np.clip(np.round(image), 0, 255).astype(np.uint8))
    return out


def test_board_edges_next_to_the_band_on_black_are_not_its_flanks(rng):
    # Without light on the dark side, a blurred edge on the bright side fits a flank of
    # the band wherever it is: the fit refused (design 32) or went 6-7 px off.
    centre = 200.3 + rng.uniform(-20.0, 20.0)
    estimate = estimate_of(board_edge_images(rng, centre))
    assert abs(estimate.centre_px - centre) <= CENTRE_TOLERANCE_PX
