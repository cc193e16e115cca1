"""Both halves of one image: full-image coordinates, quality, and reasons for failure."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half, in_half
from endomeasure.errors import BadInputError
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.chessboard import (
    ChessboardResult,
    colour_preserving_turns,
    orient_grid,
    turn_grid,
)
from endomeasure.features.detect import agree_halves, detect_split_image, match_turn
from endomeasure.features.synthetic import render_split_image

from .conftest import CHESSBOARD, IMAGE_SIZE, SPLIT, pose_homographies, render
from .test_chessboard import physical_turn as physical_k

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


# ------------------------------------------------------- left/right id consistency


def grid_of(cols: int, rows: int, angle_deg: float, origin=(150.0, 200.0)) -> np.ndarray:
    """An ideal right-handed grid (rows, cols, 2), columns at ``angle_deg`` from +u."""
    a = np.radians(angle_deg)
    e_col = 18.0 * np.array([np.cos(a), np.sin(a)])
    e_row = 18.0 * np.array([-np.sin(a), np.cos(a)])
    r, c = np.mgrid[0:rows, 0:cols]
    return np.asarray(origin) + c[..., None] * e_col + r[..., None] * e_row


def oriented(grid: np.ndarray, cols: int, rows: int, image=None) -> ChessboardResult:
    """A per-half result as detect_chessboard would give it for this raw grid."""
    image = np.full((600, 600), 128.0) if image is None else image
    ordered, angle, turns = orient_grid(image, grid, cols, rows)
    return ChessboardResult(ordered.reshape(-1, 2), angle_deg=angle, turns=turns)


def pairs(left, right):
    return ((left, "left"), (right, "right"))


@pytest.mark.parametrize(
    ("cols", "rows", "left_deg", "right_deg"),
    [(8, 6, 88.0, 92.0), (8, 6, -91.0, -87.0), (8, 8, 43.0, 47.0), (8, 8, 137.0, 133.0)],
)
@pytest.mark.parametrize("raw", ["same", "reversed", "mirrored"])
def test_halves_astride_the_upright_flip_get_the_same_ids(cols, rows, left_deg, right_deg, raw):
    """The board near where the upright choice flips, a few degrees apart in the two
    halves, the right half's raw detector order reversed or mirrored: each half alone
    picks a different corner 0; agreed, both name every corner alike."""
    grids = {"left": grid_of(cols, rows, left_deg), "right": grid_of(cols, rows, right_deg)}
    given = {
        "same": grids["right"],
        "reversed": grids["right"][::-1, ::-1],
        "mirrored": grids["right"][:, ::-1],
    }[raw]
    truth = {h: g.reshape(-1, 2) for h, g in grids.items()}
    left, right = oriented(grids["left"], cols, rows), oriented(given, cols, rows)
    alone = [physical_k(r.pixels, truth[h], cols, rows) for r, h in pairs(left, right)]
    assert alone[0] != alone[1]  # the case the agreement exists for
    left, right = agree_halves(left, right, cols, rows)
    assert left.ok and right.ok
    ks = [physical_k(r.pixels, truth[h], cols, rows) for r, h in pairs(left, right)]
    assert ks[0] == ks[1] == alone[0]  # the left half is the reference
    assert abs((right.angle_deg - left.angle_deg + 180) % 360 - 180) == pytest.approx(4.0)


def test_the_half_with_the_colours_read_leads():
    """7x7: the left half's colours unread (all four turns open), the right's read (half
    turn open): the left half follows the right."""
    left = ChessboardResult(grid_of(7, 7, 10.0).reshape(-1, 2), angle_deg=10.0, turns=(0, 1, 2, 3))
    right_grid = grid_of(7, 7, 100.0)
    right = ChessboardResult(right_grid.reshape(-1, 2), angle_deg=100.0, turns=(0, 2))
    agreed_left, agreed_right = agree_halves(left, right, 7, 7)
    assert agreed_right is right
    assert agreed_left.angle_deg == pytest.approx(100.0)
    np.testing.assert_allclose(agreed_left.pixels, turn_grid(grid_of(7, 7, 10.0), 1).reshape(-1, 2))


@pytest.mark.parametrize(
    ("cols", "rows", "turns", "right_deg", "reason"),
    [
        (8, 8, (0, 1, 2, 3), 40.0, "board turned 30 degrees from its view in the left half"),
        (8, 6, (0, 2), 70.0, "repeats every 180 degrees; the halves must agree within 45"),
        (9, 6, (0,), 190.0, "squares' colours put corner 0 of the board 180 degrees away"),
    ],
)
def test_halves_that_cannot_agree_are_refused_with_the_reason(cols, rows, turns, right_deg, reason):
    left = ChessboardResult(grid_of(cols, rows, 10.0).reshape(-1, 2), angle_deg=10.0, turns=turns)
    right_grid = grid_of(cols, rows, right_deg)
    right = ChessboardResult(right_grid.reshape(-1, 2), angle_deg=right_deg, turns=turns)
    agreed_left, agreed_right = agree_halves(left, right, cols, rows)
    assert agreed_left is left
    assert not agreed_right.ok
    assert reason in agreed_right.failure
    assert "\n" not in agreed_right.failure


@pytest.mark.parametrize(
    ("reference", "angle", "turns", "expected"),
    [
        (88.0, -88.0, (0, 2), (2, 4.0)),
        (10.0, 12.0, (0, 2), (0, 2.0)),
        (-170.0, 175.0, (0,), (0, 15.0)),
        (45.0, -42.0, (0, 1, 2, 3), (1, 3.0)),
        (0.0, 180.0, (0,), (0, 180.0)),
    ],
)
def test_match_turn_closed_form(reference, angle, turns, expected):
    k, gap = match_turn(reference, angle, turns)
    assert (k, gap) == (expected[0], pytest.approx(expected[1]))


@pytest.mark.parametrize(
    ("board", "left_roll", "right_roll"),
    [
        ("chessboard:8x6:1", 88.0, 92.0),
        ("chessboard:8x8:1", 43.0, 47.0),
        ("chessboard:7x7:1", 268.0, 272.0),
        ("chessboard:9x6:1", 268.0, 272.0),
    ],
)
def test_rendered_halves_rolled_apart_get_the_same_ids(board, left_roll, right_roll, rng):
    """Renders whose two halves see the board rolled 4 degrees apart across the upright
    flip: detect_split_image gives the same id to the same physical corner."""
    spec = parse_board_spec(board)
    centre = ((spec.cols - 1) / 2, (spec.rows - 1) / 2)
    homographies = {
        half: pose_homographies(roll, distance_mm=24.0, board_centre_mm=centre)[half]
        for half, roll in ((Half.LEFT, left_roll), (Half.RIGHT, right_roll))
    }
    scene = render_split_image(
        spec, homographies, IMAGE_SIZE, SPLIT, blur_sigma_px=0.8, noise_sigma=2.0, rng=rng
    )
    detection = detect_split_image(scene.image, spec, SPLIT)
    ks = []
    for half in detection.halves:
        assert half.ok, half.failure
        ks.append(physical_k(half.pixels, scene.true_pixels[half.half], spec.cols, spec.rows))
    assert ks[0] == ks[1]
    assert ks[0] in colour_preserving_turns(spec.cols, spec.rows)


# A board one column or row larger than the spec, in poses where the finders may see the
# spec's size as a part of it (the 7x6 spec on an 8x6 board). Ground truth: the
# rendered board's size, never the detector's.
LARGER_POSES = [
    {"roll_deg": 0.0, "tilt_deg": (0.0, 0.0)},
    {"roll_deg": 5.0, "tilt_deg": (12.0, -15.0)},
    {"roll_deg": -30.0, "tilt_deg": (-20.0, 10.0), "distance_mm": 18.0},
    {"roll_deg": 90.0, "tilt_deg": (5.0, 25.0), "distance_mm": 14.0},
]


@pytest.mark.parametrize("pose", LARGER_POSES, ids=lambda p: f"roll{p['roll_deg']:g}")
@pytest.mark.parametrize("spec", ["chessboard:8x6:1", "chessboard:9x5:1", "chessboard:8x5:1"])
@pytest.mark.parametrize("method", ["sb-classic-symmetry", "classic-subpix", "sb"])
def test_a_part_of_a_larger_board_is_never_stored(pose, spec, method):
    scene = render("chessboard:9x6:1", **pose)
    detection = detect_split_image(scene.image, spec, SPLIT, method=method)
    for half in detection.halves:
        assert not half.ok and half.ids.shape == (0,), (half.half, half.failure)


@pytest.mark.parametrize("pose", LARGER_POSES, ids=lambda p: f"roll{p['roll_deg']:g}")
def test_the_whole_board_shows_its_edge_beyond_every_side(pose):
    from endomeasure.features.chessboard import board_edges

    scene = render("chessboard:9x6:1", **pose)
    for half in Half:
        q = scene.true_pixels[half]
        if np.isnan(q).any():
            continue
        cols = slice(0, SPLIT) if half == Half.LEFT else slice(SPLIT, None)
        offset = 0 if half == Half.LEFT else SPLIT
        grid = (q - [offset, 0]).reshape(6, 9, 2)
        assert set(board_edges(scene.image[:, cols], grid).values()) == {"edge"}
        inner = grid[1:-1, 1:-1]  # a part: the board continues on every side
        assert set(board_edges(scene.image[:, cols], inner).values()) == {"corners"}
    detection = detect_split_image(scene.image, "chessboard:9x6:1", SPLIT)
    assert detection.n_ok == 2
