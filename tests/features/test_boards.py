"""Board specs: parsing, canonical strings, board-frame geometry, and refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from endomeasure.errors import BadInputError
from endomeasure.features.boards import (
    CharucoSpec,
    ChessboardSpec,
    parse_board_spec,
)


def test_chessboard_fields_and_corner_layout():
    spec = parse_board_spec("chessboard:9x6:1.5")
    assert spec == ChessboardSpec(cols=9, rows=6, square_mm=1.5)
    assert spec.pattern_size == (9, 6)
    points = spec.object_points
    assert points.shape == (54, 3)
    # id = row * cols + col at (col * square, row * square, 0)
    assert np.array_equal(points[9 * 4 + 7], [7 * 1.5, 4 * 1.5, 0.0])
    assert np.array_equal(points[:, 2], np.zeros(54))


def test_charuco_corners_match_opencv_board_ids():
    cv2 = pytest.importorskip("cv2")
    spec = parse_board_spec("charuco:8x6:2:1.4:4x4_50")
    assert isinstance(spec, CharucoSpec)
    assert spec.dictionary == "DICT_4X4_50"
    assert (spec.cols, spec.rows) == (7, 5)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    board = cv2.aruco.CharucoBoard((8, 6), 2.0, 1.4, dictionary)
    opencv = board.getChessboardCorners()
    # Same ids, origin moved from the outer corner to inner corner 0.
    np.testing.assert_allclose(spec.object_points, opencv - opencv[0], atol=1e-6)


@pytest.mark.parametrize(
    "text",
    ["chessboard:9x6:1", " Chessboard : 9X6 : 1.0 ", "charuco:12x9:1:0.7:DICT_4X4_100"],
)
def test_canonical_string_round_trips(text):
    spec = parse_board_spec(text)
    assert parse_board_spec(spec.canonical()) == spec
    assert parse_board_spec(spec) is spec


@given(
    cols=st.integers(2, 40),
    rows=st.integers(2, 40),
    square=st.floats(0.01, 100, allow_nan=False),
)
def test_chessboard_round_trip_property(cols, rows, square):
    spec = parse_board_spec(f"chessboard:{cols}x{rows}:{square!r}")
    again = parse_board_spec(spec.canonical())
    assert (again.cols, again.rows) == (cols, rows)
    # %g keeps six significant digits
    assert again.square_mm == pytest.approx(square, rel=1e-5)


@pytest.mark.parametrize(
    ("text", "complaint"),
    [
        ("", "unknown board kind"),
        ("circles:4x11:1", "unknown board kind"),
        ("chessboard:9x6", "3 fields"),
        ("chessboard:9by6:1", "must look like 9x6"),
        ("chessboard:1x6:1", "at least 2x2"),
        ("chessboard:9x6:-1", "positive"),
        ("chessboard:9x6:nan", "positive"),
        ("chessboard:9x6:one", "number of millimetres"),
        ("charuco:12x9:1:0.7", "5 fields"),
        ("charuco:12x9:1:1.2:DICT_4X4_100", "smaller than the square"),
        ("charuco:12x9:1:0.7:DICT_9X9_5", "unknown ArUco dictionary"),
        ("charuco:12x9:1:0.7:DICT_4X4_50", "holds only 50"),
    ],
)
def test_malformed_specs_say_what_and_show_an_example(text, complaint):
    with pytest.raises(BadInputError) as info:
        parse_board_spec(text)
    message = info.value.one_line()
    assert complaint in message
    assert "write it like '" in message
    # the example offered is itself valid
    example = message.split("write it like '")[1].rstrip("'")
    parse_board_spec(example)
