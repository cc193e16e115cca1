"""Frame picking: the board's edge blur against the renderer's known blur, the pose
distance, and the pick on a clip's evidence."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.frames import (
    BLUR_RATIO_MAX,
    FrameEvidence,
    board_edge_blur_px,
    frame_evidence,
    outline_motion_px,
    pick_frames,
    sharp_envelope,
)
from endomeasure.features.synthetic import render_split_image

from .conftest import IMAGE_SIZE, SPLIT, pose_homographies

BOARD = parse_board_spec("chessboard:9x6:1.0")
CENTRE = (4.0, 2.5)


def _render(blur: float, centre=CENTRE):
    return render_split_image(BOARD, pose_homographies(board_centre_mm=centre), IMAGE_SIZE,
                              SPLIT, blur_sigma_px=blur, exact_float=True)  # fmt: skip


def _grid(rendered, half=Half.LEFT):
    return rendered.true_pixels[half].reshape(BOARD.rows, BOARD.cols, 2)


@pytest.mark.parametrize("blur", [0.7, 1.0, 1.5, 2.5])
def test_edge_blur_is_the_renderers_blur_with_the_pixel_box(blur):
    rendered = _render(blur)
    expected = np.sqrt(blur**2 + 1.0 / 12.0)  # Gaussian blur and the 4x4 sampled pixel box
    assert board_edge_blur_px(rendered.image, _grid(rendered)) == pytest.approx(expected, rel=0.02)


def test_motion_blur_along_one_edge_family_is_seen():
    """Motion along u smears the edges across it only; the worse family shows it."""
    sharp = _render(0.7)
    grid = _grid(sharp)
    spacing = np.linalg.norm(grid[0, 1] - grid[0, 0])  # px per mm along u
    travel_mm = 0.3
    shifts = np.linspace(-travel_mm / 2, travel_mm / 2, 9)
    moving = np.mean([_render(0.7, (CENTRE[0] + s, CENTRE[1])).image for s in shifts], axis=0)
    # a box of length L (9 point samples) adds L^2 (n + 1) / (12 (n - 1)) to the variance;
    # the measure is exact for a Gaussian profile, a box-smeared edge reads about 15 % lower
    length = travel_mm * spacing
    expected = np.sqrt(0.7**2 + 1 / 12 + length**2 * 10 / (12 * 8))
    measured = board_edge_blur_px(moving, grid)
    assert measured == pytest.approx(expected, rel=0.2)
    assert measured > 2 * board_edge_blur_px(sharp.image, grid)


def test_outline_motion_ignores_the_corner_order():
    grid = _grid(_render(0.7))
    assert outline_motion_px(grid, grid[::-1, ::-1]) == pytest.approx(0.0, abs=1e-12)
    assert outline_motion_px(grid, grid + np.array([3.0, 4.0])) == pytest.approx(5.0)


def test_frame_evidence_finds_the_board_in_both_halves():
    rendered = _render(0.7)
    image = np.clip(np.round(rendered.image), 0, 255).astype(np.uint8)
    evidence = frame_evidence(7, image, SPLIT, BOARD)
    assert evidence.board_seen and evidence.index == 7
    for grid, half in zip(evidence.grids, (Half.LEFT, Half.RIGHT), strict=True):
        # the fast check's corners (pixel-level) against the truth, in either order
        assert outline_motion_px(grid, _grid(rendered, half)) < 0.5
    assert evidence.blur_px == pytest.approx(np.sqrt(0.7**2 + 1 / 12), rel=0.05)
    blank = np.full_like(image, 120)
    assert not frame_evidence(8, blank, SPLIT, BOARD).board_seen


def _evidence(index, shift, blur, seen=(True, True)):
    base = np.stack(np.meshgrid(np.arange(4) * 20.0, np.arange(3) * 20.0), axis=-1) + 50
    grids = tuple(base + np.array([shift + 300 * k, 0.0]) if s else None
                  for k, s in enumerate(seen))  # fmt: skip
    return FrameEvidence(index, grids, blur if all(seen) else float("nan"))


def test_pick_keeps_sharp_distinct_frames_and_says_why_not_the_others():
    size = (640, 480)  # diagonal 800 px: the default 2 % is 16 px
    evidence = [
        _evidence(0, 0.0, 0.8),
        _evidence(1, 10.0, 0.8),  # moved 10 px: too close
        _evidence(2, 60.0, 2.0),  # blurred
        _evidence(3, 60.0, 0.85),
        _evidence(4, 120.0, 0.8, seen=(True, False)),
        _evidence(5, 5.0, 0.9),  # back near frame 0
        _evidence(6, 200.0, 0.9),
        FrameEvidence(7, _evidence(7, 300.0, 0.8).grids, 0.85, anisotropy=1.4),  # motion
    ]
    pick = pick_frames(evidence, size)
    assert pick.picked == [0, 3, 6]
    assert pick.reasons == {
        1: "pose too close to a kept frame",
        2: "blurred",
        4: "board not fully seen in the right half",
        5: "pose too close to a kept frame",
        7: "blurred",
    }
    assert pick.count("pose too close") == 2 and pick.count("blurred") == 2
    # the reference is the clip's, not a constant: the same clip blurred twice over
    blurred = [FrameEvidence(e.index, e.grids, 2 * e.blur_px, e.anisotropy) for e in evidence]
    assert pick_frames(blurred, size).picked == [0, 3, 6]


def test_the_sharp_envelope_follows_defocus_over_the_board_scale(rng):
    """Defocus: blur^2 = a + (k (s - s_focus))^2 in the board scale s; frames blurred by
    motion lie above and do not pull the envelope up."""
    scale = rng.uniform(10.0, 40.0, 60)
    defocus = np.sqrt(0.5**2 + (0.02 * (scale - 22.0)) ** 2)
    blur = defocus * (1.0 + rng.normal(0.0, 0.02, 60))  # the measure's scatter
    moving = rng.random(60) < 0.3
    blur[moving] = np.hypot(blur[moving], rng.uniform(0.5, 2.0, moving.sum()))
    envelope = sharp_envelope(scale, blur)
    np.testing.assert_allclose(envelope, defocus, rtol=0.06)  # the lower side of the scatter
    # every frame without motion passes as sharp, every one with this much does not
    assert np.all(blur[~moving] <= BLUR_RATIO_MAX * envelope[~moving])
    assert np.all(blur[moving] > BLUR_RATIO_MAX * envelope[moving])
    # with few frames, the clip's least blur
    np.testing.assert_allclose(sharp_envelope(scale[:3], blur[:3]), blur[:3].min())
