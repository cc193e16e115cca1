"""``endomeasure measure --plane`` (issue 20): points placed where their left ray meets
the plane through three triangulated points.

Ground truth: a committed simulator board test image (``sample_sessions/test``; its
JSON gives every corner's 3D point and true pixels) with one corner painted over, the
session's raytrace model the simulator's truth optics; and, for the closed forms and
the refusals, sessions of a known model's exact projections
(``tests/pipeline/measure_data.py``).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from tests.conftest import make_pinhole_model, make_raytrace_model
from tests.pipeline.measure_data import (
    build_session,
    masked_corners,
    model_record,
    placed_position_std,
)
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.session import ImageRecord, edit_session, open_session
from endomeasure.measure.kinds import PLANE_POINTS
from endomeasure.models import model_from_dict
from endomeasure.pipeline.measure import measure_points
from endomeasure.pipeline.predict import predict_stored_measurement

runner = CliRunner()

SAMPLES = Path(__file__).parents[2] / "sample_sessions"
TEST_IMAGE = "test_000"
"""The first committed test image (the 1 mm board at 12 mm): the rule that picks it is
"the first", not its result (``bench/accuracy_plane.py`` runs all 35)."""
Z_BAND = 2.0
"""Errors against the predicted std: inside 2 sigma (issue 20: "within its +-")."""
EXACT_TOL_MM = 1e-6
"""Noise-free pixels: ML triangulation and the ray-plane cut are exact to ~1e-9 mm."""

pytestmark = pytest.mark.skipif(
    not (SAMPLES / "simulation.json").exists(), reason="no committed samples"
)


def _pixel_args(option: str, pixels) -> list[str]:
    out = []
    for q in pixels:
        out += [option, f"{q[0]:.17g},{q[1]:.17g}"]
    return out


def _invoke(session, *args):
    return runner.invoke(cli.app, ["measure", str(session), *map(str, args)])


# ----- the acceptance test: a masked corner on a board test image --------------------------------


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A session holding the test image with its last corner painted over in both halves,
    the truth optics as its raytrace model, and the image's truth."""
    truth = json.loads((SAMPLES / "test" / f"{TEST_IMAGE}.json").read_text())
    model = model_from_dict(json.loads((SAMPLES / "simulation.json").read_text())["truth_model"])
    image = cv2.imread(str(SAMPLES / "test" / f"{TEST_IMAGE}.png"), cv2.IMREAD_UNCHANGED)
    cols, rows = truth["target"]["cols"], truth["target"]["rows"]
    left = np.array(truth["corners"]["pixels"]["left"])
    right = np.array(truth["corners"]["pixels"]["right"])
    corner = cols * rows - 1
    painted = masked_corners(image, (left[corner], right[corner]))
    path = tmp_path_factory.mktemp("plane") / "board.h5"
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=tuple(model.config.image_size), split=model.config.split)
        w.write_images([ImageRecord(TEST_IMAGE, painted, "t.png", "0" * 64, "test")])
        w.write_model(model_record("raytrace", model))
    return {
        "path": path,
        "left": left,
        "right": right,
        "xyz": np.array(truth["corners"]["points_mm"]),
        "square": float(truth["target"]["square_mm"]),
        "corner": corner,
        "neighbour": corner - 1,
        "plane": [0, cols - 1, (rows - 1) * cols],  # the other three outer corners
    }


def test_a_masked_corner_is_recovered_on_the_plane_within_its_std(board):
    b = board
    corner, neighbour = b["left"][b["corner"]], b["left"][b["neighbour"]]
    before = b["path"].read_bytes()
    result = _invoke(b["path"], "--image", TEST_IMAGE, "--kind", "length", "--json",
                     *_pixel_args("--left", [corner, neighbour]),
                     *_pixel_args("--plane", b["left"][b["plane"]]))  # fmt: skip
    assert result.exit_code == 0, result.stderr
    doc = json.loads(result.stdout)
    assert doc["modifier"] == "plane" and doc["matched"]
    assert [p["projected"] for p in doc["points"]] == [True, True]
    assert all(p["right_px"] is None for p in doc["points"])
    assert [p["match"]["status"] for p in doc["plane"]] == ["ok"] * 3
    # the length to the neighbour corner against the square size
    assert abs(doc["value"] - b["square"]) <= Z_BAND * doc["std"]
    # the corner itself, per coordinate, against the UT of that coordinate
    report = measure_points(b["path"], "raytrace", TEST_IMAGE, [tuple(corner), tuple(neighbour)],
                            None, "length", plane=[tuple(q) for q in b["left"][b["plane"]]],
                            store=False)  # fmt: skip
    assert report.error.value == pytest.approx(doc["value"], abs=1e-12)
    error = np.array(report.points[0].xyz) - b["xyz"][b["corner"]]
    std = placed_position_std(b["path"], report)
    assert np.all(np.abs(error) <= Z_BAND * std), (error, std)
    # stored, with the plane and what was placed on it
    assert b["path"].read_bytes() != before
    with open_session(b["path"]) as s:
        rec = s.record("measurement", doc["record"])
    assert rec.attrs["modifier"] == "plane"
    assert rec.arrays["projected"].tolist() == [1, 1]
    np.testing.assert_allclose(rec.arrays["plane_pixels_left"], b["left"][b["plane"]])
    np.testing.assert_allclose(rec.arrays["plane_points"], [p["xyz_mm"] for p in doc["plane"]])
    assert np.isnan(rec.arrays["pixels_right"]).all()
    assert rec.arrays["pixel_std"].shape == (PLANE_POINTS + 2, 4)


def test_the_plane_length_of_visible_corners_agrees_with_the_triangulated_one(board):
    b = board
    pair = [tuple(b["left"][j]) for j in (7, 9)]  # two visible inner corners of one row
    plane = [tuple(q) for q in b["left"][b["plane"]]]
    on_plane = measure_points(b["path"], "raytrace", TEST_IMAGE, pair, None, "length",
                              plane=plane, store=False)  # fmt: skip
    ordinary = measure_points(b["path"], "raytrace", TEST_IMAGE, pair, None, "length",
                              store=False)  # fmt: skip
    both = np.hypot(on_plane.error.std, ordinary.error.std)
    assert abs(on_plane.error.value - ordinary.error.value) <= Z_BAND * both
    assert abs(on_plane.error.value - 2 * b["square"]) <= Z_BAND * on_plane.error.std


def test_a_plane_point_the_search_refuses_stops_it_with_exit_1(board):
    b = board
    before = b["path"].read_bytes()
    plane = b["left"][[b["plane"][0], b["plane"][1], b["corner"]]]  # the painted corner
    result = _invoke(b["path"], "--image", TEST_IMAGE, "--kind", "length",
                     *_pixel_args("--left", b["left"][[7, 9]]),
                     *_pixel_args("--plane", plane))  # fmt: skip
    assert result.exit_code == 1
    assert "plane point 3" in result.stderr and "Traceback" not in result.stderr
    assert b["path"].read_bytes() == before


# ----- closed forms on exact projections ----------------------------------------------------------


@pytest.fixture(scope="module")
def exact(tmp_path_factory):
    path = tmp_path_factory.mktemp("plane-exact") / "probe.h5"
    session, _ = build_session(path, models=("raytrace", "pinhole"))
    return session


FACTORIES = {"raytrace": make_raytrace_model, "pinhole": make_pinhole_model}
TILTED = np.array([[-1.5, -1.0, 19.0], [1.5, -1.0, 20.5], [-1.5, 1.2, 19.4]])
"""Three points of a plane tilted about both axes, in front of both halves."""


def _on_tilted(xy) -> np.ndarray:
    """Points of the TILTED plane at the given x, y (closed form)."""
    n = np.cross(TILTED[1] - TILTED[0], TILTED[2] - TILTED[0])
    xy = np.asarray(xy, dtype=np.float64)
    z = (n @ TILTED[0] - xy @ n[:2]) / n[2]
    return np.column_stack([xy, z])


@pytest.mark.parametrize("name", ["raytrace", "pinhole"])
def test_points_land_on_the_plane_and_a_depth_projects_only_its_fourth(exact, name):
    model = FACTORIES[name]()
    target = _on_tilted([[0.3, 0.2], [-0.4, 0.6]])
    pl, pr = (model.project(TILTED, h).pixels for h in ("left", "right"))
    ql = model.project(target, "left").pixels
    plane = {"plane": [tuple(q) for q in pl], "plane_right": [tuple(q) for q in pr]}
    r = measure_points(exact, name, "scene", [tuple(q) for q in ql], None, "length", **plane)
    np.testing.assert_allclose([p.xyz for p in r.points], target, atol=EXACT_TOL_MM)
    assert r.error.value == pytest.approx(np.linalg.norm(target[1] - target[0]), abs=1e-6)
    assert r.noise.pixel_std.shape == (PLANE_POINTS + 2, 4)
    assert np.all(r.noise.pixel_std[PLANE_POINTS:, 2:] == 0)  # no right pixel
    # predict-error of the stored record propagates the same inputs, so the same +-
    again = predict_stored_measurement(exact, r.record, store=False)
    assert again.error.std == pytest.approx(r.error.std, rel=1e-9)
    # depth: the first three triangulated (a plane at z = 21), the fourth on TILTED
    reference = np.array([[-1.0, -1.0, 21.0], [1.0, -1.0, 21.0], [0.0, 1.0, 21.0]])
    point = _on_tilted([[0.1, -0.2]])
    rl, rr = (model.project(reference, h).pixels for h in ("left", "right"))
    q4 = model.project(point, "left").pixels
    d = measure_points(exact, name, "scene", [tuple(q) for q in np.vstack([rl, q4])],
                       [tuple(q) for q in rr], "depth", plane=[tuple(q) for q in pl],
                       plane_right=[tuple(q) for q in pr], store=False)  # fmt: skip
    assert [p.projected for p in d.points] == [False, False, False, True]
    np.testing.assert_allclose(d.points[3].xyz, point[0], atol=EXACT_TOL_MM)
    # the probe is on the z < 21 side: a point in front of the reference plane is positive
    assert d.error.value == pytest.approx(21.0 - point[0, 2], abs=1e-6)


def _parallel_plane(model, slope: float = 0.0) -> np.ndarray:
    """Three points of a plane 0.3 mm beside the left ray of the pixel that sees the
    axis at 20 mm, and parallel to it (with ``slope``, moving away from it by that
    much per mm forward, so meeting it behind); and that pixel."""
    pixel = model.project(np.array([0.0, 0.0, 20.0]), "left").pixels
    ray = model.rays(pixel[None], "left")
    o, d = ray.origins[0], ray.directions[0]
    side = np.cross(d, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(side, d)  # in the plane, across the ray
    offset = [0.3 + slope * (t - 18) for t in (18, 22, 20)]
    return np.array([o + 18 * d + offset[0] * side, o + 22 * d + offset[1] * side,
                     o + 20 * d + offset[2] * side + up]), tuple(pixel)  # fmt: skip


def _bad(session, *args):
    before = Path(session).read_bytes()
    result = _invoke(session, "--image", "scene", "--model", "raytrace", *args)
    assert result.exit_code == 2, result.stdout + result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert Path(session).read_bytes() == before
    return result.stderr


def test_bad_plane_input_is_one_line_exit_2_and_nothing_stored(exact):
    model = make_raytrace_model()
    pl, pr = (model.project(TILTED, h).pixels for h in ("left", "right"))
    ql = model.project(_on_tilted([[0.3, 0.2], [-0.4, 0.6]]), "left").pixels
    points = _pixel_args("--left", ql)
    # collinear plane points
    line = np.array([[-1.0, 0.0, 20.0], [0.0, 0.0, 20.0], [1.0, 0.0, 20.0]])
    ll, lr = (model.project(line, h).pixels for h in ("left", "right"))
    assert "collinear" in _bad(exact, *points, *_pixel_args("--plane", ll),
                               *_pixel_args("--plane-right", lr))  # fmt: skip
    # the wrong number of plane points (2, or 3 with 2 right pixels)
    assert "exactly 3" in _bad(exact, *points, *_pixel_args("--plane", pl[:2]))
    assert "--plane-right" in _bad(exact, *points, *_pixel_args("--plane", pl),
                                   *_pixel_args("--plane-right", pr[:2]))  # fmt: skip
    # --right of a length with --plane has no use
    plane_args = [*_pixel_args("--plane", pl), *_pixel_args("--plane-right", pr)]
    assert "--right" in _bad(exact, *points, *_pixel_args("--right", ql), *plane_args)
    # a ray parallel to the plane
    plane, pixel = _parallel_plane(model)
    vl, vr = (model.project(plane, h).pixels for h in ("left", "right"))
    assert np.all(np.isfinite(vl)) and np.all(np.isfinite(vr))
    message = _bad(exact, *_pixel_args("--left", [pixel, ql[0]]), *_pixel_args("--plane", vl),
                   *_pixel_args("--plane-right", vr))  # fmt: skip
    assert "parallel" in message and "point 1" in message
    # a plane that the ray meets behind the probe (0.3 mm beside it at 18 mm, 0.32 at 22)
    plane, pixel = _parallel_plane(model, slope=0.005)
    vl, vr = (model.project(plane, h).pixels for h in ("left", "right"))
    message = _bad(exact, *_pixel_args("--left", [pixel, ql[0]]), *_pixel_args("--plane", vl),
                   *_pixel_args("--plane-right", vr))  # fmt: skip
    assert "behind the probe" in message and "point 1" in message
    # --plane with --board-test
    assert "--plane" in _bad(exact, "--board-test", *_pixel_args("--plane", pl))
