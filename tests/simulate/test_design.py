"""The design space: drawn probes are deterministic, physical, within the documented
ranges, and their boards are seen and detected (checked with the truth optics and the
detector, not with the draw's own bookkeeping)."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from endomeasure.conventions import Half, Status
from endomeasure.simulate.design import (
    DESIGN_RANGES_VERSION,
    RANGES,
    SENSOR_FORMATS,
    draw_design,
)
from endomeasure.simulate.preset import Preset
from endomeasure.simulate.scenes import plan_set, visibility
from endomeasure.simulate.targets import target_from_preset

FAST_SEEDS = (1, 2, 5)
ALL_SEEDS = tuple(range(1, 41))
MIN_SQUARE_PX = 8.5
"""Squares at a board's far distance, px: the draw asks 9 on the common field's scale."""
DETECTION_TOL_PX = 0.25
"""Detected corners against the truth on a noise-free render (the detector's floor is
about 0.03 px; this only asserts that the right corners were found)."""


@functools.cache
def _design(seed: int) -> Preset:
    return Preset.from_dict(draw_design(seed), source=f"design {seed}")


def test_draw_design_is_a_pure_function_of_the_seed():
    a, b = draw_design(5), draw_design(5)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert a["design"]["seed"] == 5 and a["design"]["ranges_version"] == DESIGN_RANGES_VERSION
    assert json.dumps(draw_design(6), sort_keys=True) != json.dumps(a, sort_keys=True)
    with pytest.raises(ValueError):
        draw_design(-1)


def _field_checks(preset: Preset) -> None:
    optics = preset.truth_optics
    width, height = preset.image_size
    assert (width, height) in {f for formats in SENSOR_FORMATS.values() for f in formats}
    lens = optics.lens
    # the lens's field across the width, through the principal point's row
    x, _, ok = lens.pixel_to_ideal(np.array([-0.5, width - 0.5]), np.array([lens.cy, lens.cy]))
    assert ok.all()
    field = np.degrees(np.arctan(abs(x[0])) + np.arctan(abs(x[1])))
    lo, hi = RANGES["full_field_deg"]
    assert lo - 3.0 <= field <= hi + 3.0  # the principal point's offset shifts the edges
    # barrel distortion at the corners, within the range (measured, not read back)
    corners = np.array(
        [[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]]
    )
    xi, yi, ok = lens.pixel_to_ideal(corners[:, 0], corners[:, 1])
    assert ok.all()
    rd = np.hypot((corners[:, 0] - lens.cx) / lens.fx, (corners[:, 1] - lens.cy) / lens.fy)
    distortion = rd / np.hypot(xi, yi) - 1.0
    assert np.all(distortion < 0.01) and np.all(distortion > -RANGES["corner_distortion"][1] - 0.05)
    assert abs(lens.cx - (width - 1) / 2) <= RANGES["principal_offset_max_px"]
    assert 0.0 <= lens.pupil_shift_mm <= RANGES["pupil_shift_mm"][1]
    assert 1.45 <= optics.n_glass <= 1.95
    for half in Half:
        wedge = np.degrees(np.arccos(optics.rear.normal @ optics.front(half).normal))
        assert RANGES["wedge_deg"][0] - 1.5 <= wedge <= RANGES["wedge_deg"][1] + 1.5
    # physical: rays of the whole image, TIR or missed faces only at the fringes
    uu, vv = np.meshgrid(np.linspace(0, width - 1, 80), np.linspace(0, height - 1, 60))
    q = np.stack([uu.ravel(), vv.ravel()], -1)
    status = np.zeros(q.shape[0], dtype=int)
    for half in Half:
        st = optics.rays(q, half).status
        status = np.where(st != Status.OUTSIDE_HALF, st, status)
    dark = status != Status.OK
    assert dark.mean() <= 0.02
    assert not np.any(
        dark
        & (np.abs(q[:, 1] - height / 2) < height / 4)
        & (np.abs(q[:, 0] - width / 2) < 0.3 * width)
    )
    assert 0.2 * width <= preset.split <= 0.8 * width


def _board_checks(preset: Preset) -> None:
    """Each calibration board fits both halves at its near distance and keeps squares of
    MIN_SQUARE_PX at its far one, placed square-on at the set's aim direction."""
    optics = preset.truth_optics
    for group in preset.sets["calib"]["boards"]:
        board = target_from_preset(group["target"], preset.targets[group["target"]])
        lo, hi = group["distance_mm"]
        ax, ay = np.radians(group.get("centre_deg", (0.0, 0.0)))
        for z in (lo, hi):
            centre = np.array([z * np.tan(ax), z * np.tan(ay), z])
            posed = board.with_pose(np.eye(3), centre - board.centre_board)
            corners = posed.corners_camera
            for half in Half:
                proj = optics.project(corners, half)
                assert np.all(proj.status == Status.OK), (group["target"], z, half)
                grid = proj.pixels.reshape(board.rows, board.cols, 2)
                step = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
                if z == hi:
                    assert step.min() >= MIN_SQUARE_PX, (group["target"], step.min())
            if z == lo:
                assert all(visibility(preset, posed).values()), (group["target"], z)


@pytest.mark.parametrize("seed", FAST_SEEDS)
def test_designs_are_physical_and_within_the_ranges(seed):
    preset = _design(seed)
    _field_checks(preset)
    _board_checks(preset)


@pytest.mark.slow
@pytest.mark.parametrize("seed", ALL_SEEDS)
def test_all_forty_designs_are_physical_within_the_ranges_and_plan(seed):
    preset = _design(seed)
    _field_checks(preset)
    _board_checks(preset)
    for name in ("calib", "test", "scene"):
        assert plan_set(preset, name, 0)


def _board_region(preset: Preset, board, grow_squares: float = 2.0):
    """The rectangle of pixels holding the board (and a margin) in both halves."""
    from endomeasure.simulate.optics import Region

    outline = board.outline_board(grow_squares=grow_squares) @ board.R.T + board.t
    q = np.concatenate([preset.truth_optics.project(outline, h).pixels for h in Half])
    q = q[np.all(np.isfinite(q), axis=1)]
    width, height = preset.image_size
    u0, v0 = np.maximum(np.floor(q.min(axis=0)).astype(int), 0)
    u1, v1 = np.minimum(np.ceil(q.max(axis=0)).astype(int) + 1, [width, height])
    return Region(int(u0), int(v0), int(u1), int(v1))


def test_designs_render_and_their_boards_are_detected():
    """Each board of a design, tilted 17 degrees at the middle of its distances and
    rendered over the region holding it (for test speed) into an otherwise dark frame,
    is detected in both halves at its true corners."""
    from endomeasure.features.detect import detect_split_image
    from endomeasure.simulate.render import render
    from endomeasure.simulate.truth import true_pixels

    data = json.loads(json.dumps(_design(FAST_SEEDS[0]).data))
    data["render"]["supersampling"] = 2  # test speed
    preset = Preset.from_dict(data)
    checked = 0
    for group in preset.sets["calib"]["boards"]:
        board = target_from_preset(group["target"], preset.targets[group["target"]])
        z = float(np.sqrt(np.prod(group["distance_mm"])))
        ax, ay = np.radians(group["centre_deg"])
        tilt = np.array(
            [[1.0, 0.0, 0.0], [0.0, np.cos(0.3), -np.sin(0.3)], [0.0, np.sin(0.3), np.cos(0.3)]]
        )
        centre = np.array([z * np.tan(ax), z * np.tan(ay), z])
        board = board.with_pose(tilt, centre - tilt @ board.centre_board)
        region = _board_region(preset, board)
        frame = np.zeros(preset.image_size[::-1], dtype=np.uint8)
        part = render(preset, board, noise_free=True, region=region).image
        frame[region.v0 : region.v1, region.u0 : region.u1] = part
        found = detect_split_image(frame, board.spec, preset.split)
        truth = true_pixels(preset, board.corners_camera)
        for half in Half:
            det = found.halves[half]
            assert det.ok, (group["target"], half, det.failure)
            assert len(det.ids) == board.rows * board.cols
            true = np.array([truth[half.label][i] for i in det.ids], dtype=float)
            assert np.abs(det.pixels - true).max() < DETECTION_TOL_PX
            checked += len(det.ids)
    assert checked >= 6 * 12  # every corner of boards of at least 4 x 3, in both halves
