"""The renderer: corners where the truth says, sensor noise as modelled, the apex band."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from endomeasure.simulate.optics import Region
from endomeasure.simulate.oracle import symmetric_corners
from endomeasure.simulate.render import apex_profile, render
from endomeasure.simulate.scenes import plan_set
from endomeasure.simulate.truth import true_pixels

ORACLE_RMS_PX = 0.06
"""The point-symmetry locator finds rendered corners within this RMS of the truth: its own
floor on ideal analytic boards is 0.01-0.03 px, the rest is the local non-affinity of the
prism image over its 4 px disc."""
ORACLE_BIAS_PX = 0.02
"""A misplaced pixel grid or an asymmetric filter would shift all corners alike."""
SB_MAX_ERROR_PX = 0.5
"""findChessboardCornersSB's own sub-pixel fit errs by up to ~0.3 px on perspective views
(docs/simulator.md); this only checks that it finds the right corner for every id."""
NOISE_STD_TOL = 0.05
"""Relative tolerance of the normalised noise standard deviation over ~10^4 pixels."""


@pytest.fixture(scope="module")
def test_shot(default_preset):
    return plan_set(default_preset, "test", 0)[6]  # the 1 mm board at 18 mm


def _crop_around(points: np.ndarray, margin: int, image_size) -> Region:
    lo = np.floor(points.min(axis=0)).astype(int) - margin
    hi = np.ceil(points.max(axis=0)).astype(int) + margin
    return Region(
        max(lo[0], 0), max(lo[1], 0), min(hi[0], image_size[0]), min(hi[1], image_size[1])
    )


@pytest.fixture(scope="module")
def left_crop(default_preset, test_shot):
    truth = np.array(true_pixels(default_preset, test_shot.target.corners_camera)["left"])
    square_px = np.median(np.linalg.norm(np.diff(truth, axis=0), axis=-1))
    region = _crop_around(truth, int(2.5 * square_px), default_preset.image_size)
    rendering = render(default_preset, test_shot.target, noise_free=True, region=region)
    return rendering, truth - [region.u0, region.v0]


def test_rendered_corners_are_at_the_true_pixels(left_crop):
    rendering, truth = left_crop
    found = symmetric_corners(rendering.image, truth + 0.3, radius_px=4.0)
    err = found - truth
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < ORACLE_RMS_PX
    assert np.all(np.abs(err.mean(axis=0)) < ORACLE_BIAS_PX)


def test_opencv_finds_the_board_with_the_truth_ids(left_crop, test_shot):
    rendering, truth = left_crop
    board = test_shot.target
    found, corners = cv2.findChessboardCornersSB(rendering.image, (board.cols, board.rows))
    assert found
    corners = corners.reshape(-1, 2)
    # SB may start the grid at either end; the canonical start is the top-left corner
    if np.argmin(corners.sum(axis=1)) != 0:
        corners = corners[::-1]
    assert np.abs(corners - truth).max() < SB_MAX_ERROR_PX


def test_noise_follows_shot_and_read_noise(default_preset, test_shot):
    board = test_shot.target
    card = dataclasses.replace(board, margin_squares=30.0)  # mostly white card
    centre = np.array(true_pixels(default_preset, board.corners_camera)["left"]).mean(axis=0)
    u, v = np.round(centre).astype(int)
    region = Region(u - 60, v - 60, u + 60, v + 60)
    clean = render(default_preset, card, noise_free=True, region=region)
    noisy = render(
        default_preset, card, rng=np.random.default_rng(3), region=region, exposure=clean.exposure
    )
    sensor = default_preset.sensor
    full_well = sensor["full_well_e"]
    gain = 255.0 / full_well
    electrons = clean.radiance * full_well
    expected = sensor["black_level_dn"] + electrons * gain
    sigma = np.sqrt((electrons + sensor["read_noise_e"] ** 2) * gain**2 + 1.0 / 12.0)
    usable = (expected > 20) & (expected < 240)
    assert usable.sum() > 5000
    z = (noisy.image.astype(float) - expected)[usable] / sigma[usable]
    assert abs(z.std() - 1.0) < NOISE_STD_TOL
    assert abs(z.mean()) < 0.05


def test_renders_are_deterministic_for_a_generator_seed(default_preset, test_shot):
    region = Region(100, 200, 160, 240)
    a = render(default_preset, test_shot.target, rng=np.random.default_rng(5), region=region)
    b = render(default_preset, test_shot.target, rng=np.random.default_rng(5), region=region)
    c = render(default_preset, test_shot.target, rng=np.random.default_rng(6), region=region)
    np.testing.assert_array_equal(a.image, b.image)
    assert np.any(a.image != c.image)
    with pytest.raises(ValueError, match="rng"):
        render(default_preset, test_shot.target, region=region)


def test_apex_band_is_dark_at_the_apex_and_clear_beyond(default_preset):
    split = default_preset.split
    region = Region(split - 40, 230, split + 40, 250)
    band = apex_profile(default_preset, region)
    depth = default_preset.prism["apex_band_depth"]
    sigma = default_preset.apex_band_sigma_px
    # pixel centres lie within half a pixel of the apex image
    deepest = 1.0 - depth * np.exp(-0.5 * (0.5 / sigma) ** 2)
    assert 1.0 - depth <= band.min() <= deepest
    darkest = region.u0 + np.argmin(band, axis=1)
    assert np.all(np.abs(darkest - (split - 0.5)) <= 1.5)
    far = np.abs(np.arange(region.u0, region.u1) - (split - 0.5)) > 4 * sigma
    assert band[:, far].min() > 0.99
