"""The ChArUco target and the ``charuco`` set: OpenCV's pattern, exact corners, truth."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError
from endomeasure.features.boards import CharucoSpec, parse_board_spec
from endomeasure.features.charuco import opencv_charuco_board
from endomeasure.pipeline.simulate import MANIFEST_NAME, simulate
from endomeasure.simulate.optics import Region
from endomeasure.simulate.oracle import symmetric_corners
from endomeasure.simulate.preset import Preset, data_digest
from endomeasure.simulate.render import render
from endomeasure.simulate.scenes import BORDER_CLEARANCE_PX, plan_set, visibility
from endomeasure.simulate.targets import CharucoBoard, target_from_preset
from endomeasure.simulate.truth import CHARUCO_CORNER_ID_RULE, image_truth, true_pixels

from .conftest import small_preset_data

SEED = 0
RAY_POINT_TOL_MM = 1e-6
"""As for the chessboards (issue 4): a true pixel traced back passes this close to its point."""
ORACLE_RMS_PX = 0.06
"""The point-symmetry locator on rendered chessboards (tests/simulate/test_render.py)."""
ORACLE_RADIUS_SQUARES = 0.2
"""Near a ChArUco corner the image is point-symmetric out to the markers' inner bits,
gap + one border cell = 0.25 squares for this board; the disc keeps inside with room
for the blur."""
SAMPLE_SESSIONS = Path(__file__).resolve().parents[2] / "sample_sessions"


@pytest.fixture(scope="module")
def charuco_plan(default_preset):
    return plan_set(default_preset, "charuco", SEED)


@pytest.fixture(scope="module")
def board(default_preset) -> CharucoBoard:
    return target_from_preset("charuco", default_preset.targets["charuco"])


def test_pattern_is_opencvs_board_with_whole_texel_edges(board):
    """Squares and markers sit on whole texels, top-left square black, markers in white."""
    T = board.texels_per_square
    pattern = board.pattern
    assert pattern.shape == (board.squares_y * T, board.squares_x * T)
    marker = round(board.marker_mm / board.square_mm * T)
    gap = (T - marker) // 2
    cell = marker // 6  # 4 x 4 bits and a one-bit border on each side
    dark, light = True, False
    ids = opencv_charuco_board(board.board_spec).getIds().ravel()
    n_marker = 0
    for j in range(board.squares_y):
        for i in range(board.squares_x):
            square = pattern[j * T : (j + 1) * T, i * T : (i + 1) * T]
            if (i + j) % 2 == 0:
                assert np.all(square == dark), (i, j)
                continue
            ring = np.ones((T, T), dtype=bool)
            ring[gap : T - gap, gap : T - gap] = False
            assert np.all(square[ring] == light), (i, j)
            box = square[gap : T - gap, gap : T - gap]
            border = np.ones_like(box, dtype=bool)
            border[cell:-cell, cell:-cell] = False
            assert np.all(box[border] == dark), (i, j)
            # every bit is a whole cell of one colour
            bits = box[cell:-cell, cell:-cell].reshape(4, cell, 4, cell)
            assert np.all(bits == bits[:, :1, :, :1])
            n_marker += 1
    assert n_marker == len(ids) == board.board_spec.n_markers


def test_corner_ids_and_positions_are_opencvs(board):
    """Corner id i is OpenCV's ChArUco corner i, one square in from the outer corner."""
    opencv = np.asarray(opencv_charuco_board(board.board_spec).getChessboardCorners())
    np.testing.assert_allclose(board.corners_board, opencv - [board.square_mm, board.square_mm, 0])
    spec = parse_board_spec(board.spec)
    assert isinstance(spec, CharucoSpec)
    assert spec.canonical() == board.spec == "charuco:24x20:1.5:1.125:DICT_4X4_250"
    np.testing.assert_allclose(spec.object_points, board.corners_board)


def test_albedo_follows_the_pattern_at_board_points(board):
    s, T = board.square_mm, board.texels_per_square
    # texel centres of a few squares and a point just inside each corner of square (0, 0)
    eps = 1e-6
    bx = np.array([-1 + 0.5 / T, -eps, eps, 0.5, (22 + 0.5) + 0.5 / T, 50.0])
    by = np.array([-1 + 0.5 / T, eps, eps, 0.5, 18.5, 0.0])
    albedo = board._albedo(bx, by, np.float64)
    assert albedo[0] == board.black  # outer top-left square
    assert albedo[1] == board.white  # square (0, 1) in squares from the top-left: white
    assert albedo[2] == board.black  # the square diagonal to the top-left one
    assert albedo[3] == board.black  # centre of that square
    tx, ty = int((bx[4] + 1) * T), int((by[4] + 1) * T)
    assert albedo[4] == (board.black if board.pattern[ty, tx] else board.white)
    assert albedo[5] == board.white  # off the pattern (the margin)
    # through the renderer's ray-board intersection: the board 10 mm ahead, a ray
    # through board point (0.5 s, 0.5 s) sees the black square diagonal to the top-left
    posed = board.with_pose(np.eye(3), np.array([0.0, 0.0, 10.0]))
    d = np.array([0.5 * s, 0.5 * s, 10.0]) / np.linalg.norm([0.5 * s, 0.5 * s, 10.0])
    hit = posed.hit(tuple(np.zeros((3, 1))), tuple(d[:, None]))
    assert hit.hit[0] and hit.albedo[0] == board.black


def test_texel_size_that_would_round_the_markers_is_refused(default_preset, tmp_path):
    spec = dict(default_preset.targets["charuco"], texels_per_square=100)  # marker 75 texels
    with pytest.raises(ValueError, match="texels_per_square"):
        target_from_preset("charuco", spec)
    data = small_preset_data()
    data["targets"]["charuco"]["texels_per_square"] = 100
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(BadInputError, match="texels"):
        simulate(tmp_path / "out", path, ["charuco"], seed=0)


def test_set_cuts_a_board_larger_than_the_view_in_both_halves(default_preset, charuco_plan):
    spec = default_preset.sets["charuco"]
    assert len(charuco_plan) == spec["images"]
    distances = []
    for shot in charuco_plan:
        board = shot.target
        assert isinstance(board, CharucoBoard)
        assert visibility(default_preset, board) == {"left": False, "right": False}
        pixels = true_pixels(default_preset, board.corners_camera)
        for half in Half:
            seen = sum(p is not None for p in pixels[half.label])
            assert spec["min_corners_per_half"] <= seen < board.cols * board.rows
        distances.append((board.R @ board.centre_board + board.t)[2])
    lo, hi = spec["distance_mm"]
    assert lo <= min(distances) and max(distances) <= hi
    assert max(distances) - min(distances) > 0.5 * (hi - lo)  # stratified over the range
    again = plan_set(default_preset, "charuco", SEED)
    for a, b in zip(charuco_plan, again, strict=True):
        np.testing.assert_array_equal(a.target.R, b.target.R)


def test_truth_document_pixels_trace_back_and_are_null_outside(default_preset, charuco_plan):
    model = default_preset.truth_optics
    shot = charuco_plan[0]
    doc = image_truth(default_preset, shot, "charuco_000.png", {"noise_free": True})
    board = shot.target
    assert doc["board_spec"] == board.spec
    assert doc["target"]["kind"] == "charuco"
    assert doc["target"]["corner_ids"] == CHARUCO_CORNER_ID_RULE
    assert doc["corners"]["ids"] == list(range(board.cols * board.rows))
    assert doc["board_fully_visible"] == {"left": False, "right": False}
    points = np.array(doc["corners"]["points_mm"])
    width, height = default_preset.image_size
    for half in Half:
        q = doc["corners"]["pixels"][half.label]
        ok = np.array([p is not None for p in q])
        assert 0 < ok.sum() < len(q)
        pix = np.array([p for p in q if p is not None])
        rays = model.rays(pix, half)
        rel = points[ok] - rays.origins
        along = np.sum(rel * rays.directions, axis=-1, keepdims=True)
        assert np.linalg.norm(rel - along * rays.directions, axis=-1).max() < RAY_POINT_TOL_MM
        # inside the image and on the half's side of the split
        assert np.all((pix >= -0.5) & (pix <= [width - 0.5, height - 0.5]))
        if half is Half.LEFT:
            assert pix[:, 0].max() < default_preset.split - 0.5
        else:
            assert pix[:, 0].min() >= default_preset.split - 0.5


def test_rendered_corners_are_at_the_true_pixels(default_preset, charuco_plan):
    """A crop of the near board (large squares): the symmetry centres are the truth."""
    board = charuco_plan[0].target
    truth = true_pixels(default_preset, board.corners_camera)["left"]
    pix = np.array([p if p is not None else [np.nan, np.nan] for p in truth])
    centre = np.nanmedian(pix, axis=0)
    near = np.argsort(np.nan_to_num(np.linalg.norm(pix - centre, axis=1), nan=np.inf))[:6]
    lo = np.floor(pix[near].min(axis=0)).astype(int) - 12
    hi = np.ceil(pix[near].max(axis=0)).astype(int) + 12
    region = Region(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
    rendering = render(default_preset, board, noise_free=True, region=region)
    local = pix[near] - [region.u0, region.v0]
    step = pix[np.minimum(near + 1, len(pix) - 1)] - pix[near]  # to the next column
    square_px = np.nanmedian(np.linalg.norm(step, axis=1))
    radius = ORACLE_RADIUS_SQUARES * square_px
    found = symmetric_corners(rendering.image, local + 0.3, radius_px=radius)
    err = np.linalg.norm(found - local, axis=1)
    assert np.sqrt(np.mean(err**2)) < ORACLE_RMS_PX
    assert region.u0 >= BORDER_CLEARANCE_PX  # the crop is inside the left half


def test_simulate_writes_the_set_and_keeps_the_manifest_of_other_sets(tmp_path):
    data = small_preset_data()
    path = tmp_path / "small.json"
    path.write_text(json.dumps(data))
    out = tmp_path / "run"
    report = simulate(out, path, ["charuco"], seed=1)
    assert report.sets["charuco"]["images"] == data["sets"]["charuco"]["images"]
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    recorded = manifest["preset_data"]
    assert list(recorded["sets"]) == ["charuco"] and list(recorded["targets"]) == ["charuco"]
    assert manifest["preset"]["sha256"] == data_digest(recorded)
    entry = manifest["sets"]["charuco"]["images"][0]
    assert entry["board_spec"].startswith("charuco:24x20:")
    truth = json.loads((out / entry["truth"]).read_text())
    assert truth["target"]["kind"] == "charuco"
    # another set into the same folder: both in the manifest, the preset data of both
    simulate(out, path, ["scene"], seed=1)
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    assert sorted(manifest["sets"]) == ["charuco", "scene"]
    assert list(manifest["preset_data"]["sets"]) == ["scene", "charuco"]  # preset order
    assert manifest["preset"]["sha256"] == data_digest(
        Preset.from_dict(data).for_sets(["charuco", "scene"])
    )


def test_adding_the_set_left_the_sample_manifests_preset_unchanged(default_preset):
    """``make samples`` (calib, test, scene) records exactly the preset data it did before."""
    manifest = json.loads((SAMPLE_SESSIONS / MANIFEST_NAME).read_text())
    recorded = default_preset.for_sets(["calib", "test", "scene"])
    assert json.dumps(recorded, indent=1) == json.dumps(manifest["preset_data"], indent=1)
    assert data_digest(recorded) == manifest["preset"]["sha256"]
    assert "charuco" not in recorded["targets"]
    assert cv2.imread(str(SAMPLE_SESSIONS / "calib" / "calib_000.png")) is not None
