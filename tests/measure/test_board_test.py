"""Board-test evaluation on synthetic triangulated boards with known distortions."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.errors import BadInputError
from endomeasure.measure.board_test import (
    BOARD_KINDS,
    BoardImage,
    board_stencils,
    board_test_table,
    stencil_pixels,
    zone_summary,
)

COLS, ROWS, SQUARE = 7, 5, 1.0
ROUND_OFF = 1e-12  # mm: exact geometry on small numbers


def board_points(z, scale=1.0, square=SQUARE, cols=COLS, rows=ROWS):
    """A board perpendicular to the axis at depth z, uniformly scaled in its plane."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    x = (c - (cols - 1) / 2) * square * scale
    y = (r - (rows - 1) / 2) * square * scale
    return np.stack([x, y, np.full(x.shape, float(z))], axis=-1)


def image(points, ids=None):
    ids = np.arange(points.shape[0]) if ids is None else np.asarray(ids)
    pixels = 100.0 + 10.0 * points[:, :2]
    return BoardImage(ids, points, pixels, pixels + [320.0, 0.0])


def test_stencil_counts_and_true_values():
    st = board_stencils(COLS, ROWS, 2.0)
    counts = {k: int(np.sum(st.kind == k)) for k in BOARD_KINDS}
    assert counts == {
        "x-segment": ROWS * (COLS - 1),
        "y-segment": (ROWS - 1) * COLS,
        "point-plane": (ROWS - 1) * (COLS - 1),
        "area": (ROWS - 1) * (COLS - 1),
    }
    assert set(st.true[st.kind == "x-segment"]) == {2.0}
    assert set(st.true[st.kind == "area"]) == {4.0}
    assert set(st.true[st.kind == "point-plane"]) == {0.0}
    # the first x-segment joins corners 0 and 1; the first point-plane tests corner 0
    # against the other three corners of its square
    assert list(st.corners[st.kind == "x-segment"][0]) == [0, 1, -1, -1]
    assert list(st.corners[st.kind == "point-plane"][0]) == [1, COLS + 1, COLS, 0]


def test_a_perfect_board_has_no_error():
    table = board_test_table(COLS, ROWS, SQUARE, [image(board_points(20.0))])
    assert table.image.size == board_stencils(COLS, ROWS, SQUARE).kind.size
    assert np.abs(table.error).max() < ROUND_OFF
    np.testing.assert_allclose(table.z_mean, 20.0)


def test_a_scaled_board_has_the_closed_form_errors():
    e = 0.004
    table = board_test_table(COLS, ROWS, SQUARE, [image(board_points(20.0, 1 + e))])
    for kind, expected in (
        ("x-segment", SQUARE * e),
        ("y-segment", SQUARE * e),
        ("area", SQUARE**2 * ((1 + e) ** 2 - 1)),
        ("point-plane", 0.0),
    ):
        errors = table.error[table.kind == kind]
        np.testing.assert_allclose(errors, expected, atol=ROUND_OFF)


def test_point_plane_is_signed_towards_the_probe():
    points = board_points(20.0)
    corner = 2 * COLS + 3  # an inner corner
    points[corner, 2] -= 0.1  # 0.1 mm towards the probe
    table = board_test_table(COLS, ROWS, SQUARE, [image(points)])
    pp = table.select(table.kind == "point-plane")
    row = np.flatnonzero(pp.corners[:, 3] == corner)
    assert pp.error[row] == pytest.approx(0.1, abs=ROUND_OFF)
    untouched = ~np.any(pp.corners == corner, axis=1)
    assert np.abs(pp.error[untouched]).max() < ROUND_OFF


def test_missing_and_failed_corners_drop_only_their_measurements():
    points = board_points(15.0)
    keep = np.setdiff1d(np.arange(COLS * ROWS), [0])  # corner 0 not detected
    points[5] = np.nan  # corner 5 not triangulated
    table = board_test_table(COLS, ROWS, SQUARE, [image(points[keep], keep)])
    assert not np.any(np.isin(table.corners, [0, 5]))
    full = board_stencils(COLS, ROWS, SQUARE)
    lost = np.any(np.isin(full.corners, [0, 5]), axis=1)
    assert table.image.size == int(np.sum(~lost))


def test_zone_summary_groups_by_mean_depth():
    e1, e2, e3 = 0.002, 0.006, -0.01
    images = [
        image(board_points(11.0, 1 + e1)),  # zone [10, 15)
        image(board_points(13.5, 1 + e2)),  # zone [10, 15)
        image(board_points(17.0, 1 + e3)),  # zone [15, 20)
    ]
    tables = {
        "raytrace": board_test_table(COLS, ROWS, SQUARE, images),
        "pinhole": board_test_table(COLS, ROWS, SQUARE, images[:1]),
    }
    summary = zone_summary(tables, zone_mm=5.0)
    rows = {(m, k, s): i for i, (m, k, s) in enumerate(
        zip(summary.model, summary.kind, summary.zone_start, strict=True))}  # fmt: skip
    i = rows[("raytrace", "x-segment", 10.0)]
    n = ROWS * (COLS - 1)
    assert summary.n[i] == 2 * n
    assert summary.zone_end[i] == 15.0
    assert summary.mean_error[i] == pytest.approx((e1 + e2) / 2 * SQUARE, abs=ROUND_OFF)
    # n errors e1 and n errors e2: sample std = |e2 - e1| / 2 * sqrt(2n / (2n - 1))
    expected_std = abs(e2 - e1) / 2 * np.sqrt(2 * n / (2 * n - 1)) * SQUARE
    assert summary.std_error[i] == pytest.approx(expected_std, rel=1e-9)
    i = rows[("raytrace", "x-segment", 15.0)]
    assert summary.mean_error[i] == pytest.approx(e3 * SQUARE, abs=ROUND_OFF)
    assert summary.std_error[i] == pytest.approx(0.0, abs=ROUND_OFF)
    assert ("pinhole", "area", 15.0) not in rows
    assert summary.true[rows[("pinhole", "area", 10.0)]] == SQUARE**2
    records = summary.as_records()
    assert records[0]["model"] == "raytrace" and isinstance(records[0]["n"], int)


def test_stencil_pixels_follow_the_table():
    points = board_points(20.0)
    keep = np.arange(COLS * ROWS)[::-1]  # ids in any order
    img = image(points[keep], keep)
    table = board_test_table(COLS, ROWS, SQUARE, [img])
    left, right = stencil_pixels(table, [img], "area")
    areas = table.select(table.kind == "area")
    assert left.shape == (areas.image.size, 4, 2)
    expected = 100.0 + 10.0 * points[areas.corners, :2]
    np.testing.assert_allclose(left, expected)
    np.testing.assert_allclose(right, expected + [320.0, 0.0])
    np.testing.assert_allclose(areas.pixel_mean, expected.mean(axis=1))


def test_records_are_json_ready():
    import json

    table = board_test_table(COLS, ROWS, SQUARE, [image(board_points(20.0))])
    records = table.as_records()
    assert records[0]["corners"] == [0, 1]
    json.dumps(records)


@pytest.mark.parametrize(
    ("ids", "message"),
    [
        (np.arange(COLS * ROWS) + 1, "corner ids must lie in"),
        (np.r_[np.arange(COLS * ROWS - 1), 0], "occurs twice"),
    ],
)
def test_bad_ids_are_refused(ids, message):
    with pytest.raises(BadInputError, match=message):
        board_test_table(COLS, ROWS, SQUARE, [image(board_points(20.0), ids)])


def test_bad_board_and_zone_are_refused():
    with pytest.raises(BadInputError, match="2x2"):
        board_stencils(1, 5, 1.0)
    with pytest.raises(BadInputError, match="square size"):
        board_stencils(4, 4, -1.0)
    with pytest.raises(BadInputError, match="span"):
        board_stencils(4, 4, 1.0, span=4)
    with pytest.raises(BadInputError, match="zone width"):
        zone_summary({}, zone_mm=0.0)
