"""The renderer: corners where the truth says, sensor noise as modelled, the apex band."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm

from endomeasure.features.subpixel import local_quadratic
from endomeasure.features.subpixel import symmetric_corners as refine_symmetric
from endomeasure.simulate.optics import Region, sample_offsets
from endomeasure.simulate.oracle import symmetric_corners
from endomeasure.simulate.render import _blur_half, apex_profile, pixel_kernel, render
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
KERNEL_TOL = 2e-8
"""Pixel kernel vs numerical quadrature of the PSF over the pixel: the renormalisation of the
tails cut at 4 sigma + 1 px (worst here: 1e-8 of the flux at sigma 0.9 px, the point near a
pixel edge, 5.6 sigma from the nearer cut)."""
EDGE_TOL = 3e-4
"""Blurred straight edge vs the closed form, fraction of the edge contrast: the samples
integrate the pixel kernel by the midpoint rule over strata 1/16 px wide (measured
1e-4 at sigma 0.55 px). Blurring the pixels' sample means with a sampled Gaussian (the
renderer before) errs by 0.9-3.4e-2."""
MIDDLE_ROW_RMS_PX = 0.012
"""Noise-free 2 mm board corners within 12 px of the image's middle row, whose edges run
along the pixel grid, against the truth: measured 0.0075 px RMS (the 16-sample floor),
0.021 px with the PSF applied to pixel means instead of the samples."""
ALL_CORNERS_RMS_PX = 0.009
"""The same boards, all corners: measured 0.0058 px RMS (0.0136 before)."""


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


@pytest.mark.parametrize("sigma", [0.0, 0.3, 0.55, 0.9])
@pytest.mark.parametrize("offset", [-0.4375, -0.1, 0.0, 0.3125])
def test_pixel_kernel_is_the_psf_integrated_over_each_pixel(sigma, offset):
    kernel = pixel_kernel(sigma, offset)
    reach = kernel.size // 2
    for m, value in zip(range(-reach, reach + 1), kernel, strict=True):
        if sigma == 0:
            expected = float(m - 0.5 <= offset < m + 0.5)
        else:
            expected = quad(norm(offset, sigma).pdf, m - 0.5, m + 0.5, epsabs=1e-13)[0]
        assert value == pytest.approx(expected, abs=KERNEL_TOL)


@pytest.mark.parametrize("sigma", [0.55, 0.7, 0.9])
@pytest.mark.parametrize("edge_phase", [-0.1875, 0.0, 0.0625, 0.3125])
def test_blurred_straight_edge_matches_the_closed_form(sigma, edge_phase):
    """A step from 0 to 1 at ``u = e`` blurred by a Gaussian and integrated over each pixel
    is ``sigma (psi((k + 0.5 - e) / sigma) - psi((k - 0.5 - e) / sigma))``, ``psi(t) = t
    Phi(t) + phi(t)``; the edge lies on a sample stratum boundary, so the samples see it
    exactly and only the integration of the pixel kernel is tested."""
    offsets = sample_offsets(4)
    width = 24
    k = np.arange(width)
    edge = 11 + edge_phase
    samples = (k[:, None] + offsets[None, :, 0] >= edge).astype(float)  # (W, S)
    image = _blur_half(np.repeat(samples[None], 3, axis=0), offsets, np.full((3, width), sigma))

    def psi(t):
        return t * norm.cdf(t) + norm.pdf(t)

    expected = sigma * (psi((k + 0.5 - edge) / sigma) - psi((k - 0.5 - edge) / sigma))
    inner = slice(5, width - 5)  # away from the 'nearest' border extension
    for row in image:
        np.testing.assert_allclose(row[inner], expected[inner], rtol=0, atol=EDGE_TOL)


def test_corners_along_the_pixel_grid_are_at_the_true_pixels(default_preset):
    """Near the image's middle row the board's edges run along pixel rows and columns, so an
    error of the pixel integration that depends on the edge's sub-pixel phase does not
    average out along the edge (it did: 0.021 px RMS with the PSF applied to pixel means)."""
    middle_errors, all_errors = [], []
    for index in (16, 17):  # the 2 mm board at 22 and 23 mm, centred on the middle row
        board = plan_set(default_preset, "test", 0)[index].target
        assert board.square_mm == 2.0
        pixels = true_pixels(default_preset, board.corners_camera)
        for half in ("left", "right"):
            truth = np.array(pixels[half])
            square = np.median(np.linalg.norm(np.diff(truth, axis=0), axis=-1))
            region = _crop_around(truth, int(1.5 * square), default_preset.image_size)
            rendering = render(default_preset, board, noise_free=True, region=region)
            local = truth - [region.u0, region.v0]
            steps, curvature = local_quadratic(local.reshape(board.rows, board.cols, 2))
            fit = refine_symmetric(
                rendering.radiance, None, local + [0.2, -0.15], steps=steps, curvature=curvature
            )
            assert fit.converged.all()
            err = fit.pixels - local
            middle = np.abs(truth[:, 1] - (default_preset.image_size[1] - 1) / 2.0) < 12
            middle_errors.append(err[middle])
            all_errors.append(err)
    middle_errors, all_errors = np.concatenate(middle_errors), np.concatenate(all_errors)
    assert len(middle_errors) >= 20
    assert np.sqrt(np.mean(middle_errors**2)) < MIDDLE_ROW_RMS_PX
    assert np.sqrt(np.mean(all_errors**2)) < ALL_CORNERS_RMS_PX
