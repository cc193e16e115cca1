"""``endomeasure measure`` with operator points in one half only (issue 9): the matches
are found automatically, refused points stop the measurement.

Ground truth: the committed simulator ``scene`` images (a textured metal cylinder with
six marks; ``sample_sessions/scene/*.json`` give every mark's 3D point, its true pixels
in both halves and every mark-to-mark distance). The session holds the simulator's
truth optics as the "calibrated" raytrace model, so the only errors left are the
search's. Planted refusal: the texture around a point painted flat.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from tests.pipeline.measure_data import model_record
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.session import ImageRecord, edit_session, open_session
from endomeasure.models import model_from_dict
from endomeasure.pipeline.measure import MatchRefusedError, measure_points
from endomeasure.solvers.triangulate import triangulate

runner = CliRunner()

SAMPLES = Path(__file__).parents[2] / "sample_sessions"
SCENE = "scene_001"
MATCH_TOL_PX = 0.15
"""Largest distance of one automatic match from the true pixel: issue 9 asks for 0.2 px
RMS; the committed marks are found to 0.02-0.08 px."""
LENGTH_TOL_MM = 0.03
"""Distance of two marks at ~21 mm from the true one with the truth optics: 0.1 px of
match error moves a mark's depth by ~0.06 mm along a ray that is nearly parallel to
the other mark's, changing the length by 0.01-0.02 mm."""
LINEAR_REL_TOL = 0.05
"""UT against first-order propagation for a length at 0.03 px: they agree to ~1 %
(Monte Carlo in tests/solvers); 5 % leaves room for the finite differences."""
FD_STEP_PX = 1e-3
FLAT_HALF_PX = 20
"""Half-width of the painted flat square: a 15 px patch and the noise window fit in."""

pytestmark = pytest.mark.skipif(
    not (SAMPLES / "simulation.json").exists(), reason="no committed samples"
)


def _truth_model():
    return model_from_dict(json.loads((SAMPLES / "simulation.json").read_text())["truth_model"])


def _scene_truth(name=SCENE) -> dict:
    return json.loads((SAMPLES / "scene" / f"{name}.json").read_text())


def _flat_image(image: np.ndarray, centre, rng) -> np.ndarray:
    """``image`` with a square around ``centre`` replaced by its mean plus sensor-like noise."""
    out = image.astype(np.float64)
    u, v = (int(round(c)) for c in centre)
    block = (
        slice(v - FLAT_HALF_PX, v + FLAT_HALF_PX + 1),
        slice(u - FLAT_HALF_PX, u + FLAT_HALF_PX + 1),
    )
    out[block] = out[block].mean() + rng.normal(0.0, 1.5, out[block].shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def scene_session(tmp_path_factory):
    """A session with the truth optics as its raytrace model, the scene image and a copy
    with the texture around mark 0's left pixel painted flat."""
    path = tmp_path_factory.mktemp("operator") / "scene.h5"
    model = _truth_model()
    image = cv2.imread(str(SAMPLES / "scene" / f"{SCENE}.png"), cv2.IMREAD_UNCHANGED)
    mark0 = _scene_truth()["marks"]["pixels"]["left"][0]
    flat = _flat_image(image, mark0, np.random.default_rng(5))
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=tuple(model.config.image_size), split=model.config.split)
        w.write_images(
            [
                ImageRecord(SCENE, image, f"{SCENE}.png", "0" * 64, "scene"),
                ImageRecord("flat", flat, "flat.png", "1" * 64, "scene"),
            ]
        )
        w.write_model(model_record("raytrace", model))
    return path


def _measurements(session) -> list[str]:
    with open_session(session) as s:
        return list(s.record_names("measurement"))


def _pixel_args(option: str, pixels) -> list[str]:
    out = []
    for q in pixels:
        out += [option, f"{q[0]:.17g},{q[1]:.17g}"]
    return out


def test_left_points_are_matched_and_measured(scene_session):
    truth = _scene_truth()
    left = np.asarray(truth["marks"]["pixels"]["left"])[[0, 1]]
    right = np.asarray(truth["marks"]["pixels"]["right"])[[0, 1]]
    known = next(d for d in truth["distances"] if (d["a"], d["b"]) == (0, 1))["distance_mm"]
    before = _measurements(scene_session)
    result = runner.invoke(
        cli.app,
        ["measure", str(scene_session), "--image", SCENE, "--kind", "length", "--json",
         *_pixel_args("--left", left)],
    )  # fmt: skip
    assert result.exit_code == 0, result.stderr
    doc = json.loads(result.stdout)
    assert doc["measured"] and doc["matched"]
    found = np.array([p["right_px"] for p in doc["points"]])
    assert np.linalg.norm(found - right, axis=1).max() < MATCH_TOL_PX
    assert [p["match"]["status"] for p in doc["points"]] == ["ok", "ok"]
    assert all(p["match"]["score"] > 0.9 for p in doc["points"])
    np.testing.assert_allclose([p["left_px"] for p in doc["points"]], left, atol=1e-12)
    assert doc["value"] == pytest.approx(known, abs=LENGTH_TOL_MM)
    assert doc["sigma_source"].startswith("match precision")
    after = _measurements(scene_session)
    assert len(after) == len(before) + 1 and doc["record"] in after
    with open_session(scene_session) as s:
        rec = s.record("measurement", doc["record"])
    np.testing.assert_allclose(rec.arrays["pixels_right"], found)
    assert rec.arrays["pixel_std"].shape == (2, 2)


def test_right_points_are_matched_into_the_left_half(scene_session):
    truth = _scene_truth()
    left = np.asarray(truth["marks"]["pixels"]["left"])[[2, 3, 4]]
    right = np.asarray(truth["marks"]["pixels"]["right"])[[2, 3, 4]]
    report = measure_points(scene_session, "raytrace", SCENE, None, right, "area", store=False)
    found = np.array([p.left for p in report.points])
    assert np.linalg.norm(found - left, axis=1).max() < MATCH_TOL_PX
    assert all(p.match.half.label == "right" for p in report.points)
    np.testing.assert_allclose([p.right for p in report.points], right, atol=1e-12)


def test_matched_points_uncertainty_is_the_match_precision(scene_session):
    """The image part of the predicted std equals first-order propagation of the match
    precision through the matched pixels only (the clicked pixels are exact), computed
    here by central differences of triangulate + distance."""
    truth = _scene_truth()
    left = np.asarray(truth["marks"]["pixels"]["left"])[[1, 3]]
    report = measure_points(scene_session, "raytrace", SCENE, left, None, "length", store=False)
    model = _truth_model()
    ql = np.array([p.left for p in report.points])
    qr = np.array([p.right for p in report.points])

    def length(right_pixels):
        x = triangulate(model, ql, right_pixels, "ml").points
        return float(np.linalg.norm(x[0] - x[1]))

    variance = 0.0
    for i, point in enumerate(report.points):
        for axis in range(2):
            step = np.zeros_like(qr)
            step[i, axis] = FD_STEP_PX
            slope = (length(qr + step) - length(qr - step)) / (2 * FD_STEP_PX)
            variance += (slope * point.match.precision_px) ** 2
    assert report.error.std_image == pytest.approx(np.sqrt(variance), rel=LINEAR_REL_TOL)
    assert report.error.value == pytest.approx(length(qr), abs=1e-9)

    given = measure_points(
        scene_session, "raytrace", SCENE, left, None, "length", sigma=0.1, store=False
    )
    assert given.noise.source == "given" and given.noise.sigma == 0.1
    assert given.error.std_image > report.error.std_image  # 0.1 px on all four vs ~0.03 on two


def test_a_refused_point_stops_the_measurement(scene_session, tmp_path):
    truth = _scene_truth()
    left = np.asarray(truth["marks"]["pixels"]["left"])[[0, 1]]  # mark 0 is painted flat
    before = _measurements(scene_session)
    plot = tmp_path / "matches.png"
    args = ["measure", str(scene_session), "--image", "flat", "--kind", "length",
            *_pixel_args("--left", left), "--plot", str(plot)]  # fmt: skip
    result = runner.invoke(cli.app, args)
    assert result.exit_code == 1
    error = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(error) == 1 and "Traceback" not in result.stderr
    assert "point 1: untextured" in error[0] and "point 2" not in error[0]
    assert "nothing measured" in error[0]
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    result = runner.invoke(cli.app, [*args[:-2], "--json"])
    assert result.exit_code == 1
    doc = json.loads(result.stdout)
    assert doc["measured"] is False
    assert [m["status"] for m in doc["matches"]] == ["untextured", "ok"]
    assert doc["matches"][0]["match"] == [None, None]
    assert _measurements(scene_session) == before

    with pytest.raises(MatchRefusedError) as info:
        measure_points(scene_session, "raytrace", "flat", left, None, "length")
    assert [m.ok for m in info.value.matches] == [False, True]
    assert _measurements(scene_session) == before


def test_the_plot_of_matches(scene_session, tmp_path):
    truth = _scene_truth()
    left = np.asarray(truth["marks"]["pixels"]["left"])[[0, 2, 5]]
    plot = tmp_path / "sub" / "m.png"
    plot.parent.mkdir()  # outputs go to existing folders (io.outputs refuses a missing one)
    report = measure_points(
        scene_session, "raytrace", SCENE, left, None, "area", plot=plot, store=False
    )
    assert report.plot == str(plot)
    drawn = cv2.imread(str(plot))
    assert drawn is not None and drawn.shape[0] > 400 and drawn.shape[1] > 600


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--patch", "14"], "patch size"),
        (["--right", "400,200", "--right", "450,200", "--plot", "x.png"], "--plot draws"),
        (["--image", "nope"], "nope"),
    ],
)
def test_bad_operator_input_is_exit_2(scene_session, extra, message):
    truth = _scene_truth()
    left = np.asarray(truth["marks"]["pixels"]["left"])[[0, 1]]
    args = ["measure", str(scene_session), "--kind", "length", *_pixel_args("--left", left)]
    if "--image" not in extra:
        args += ["--image", SCENE]
    result = runner.invoke(cli.app, [*args, *extra])
    assert result.exit_code == 2, result.stderr
    assert message in result.stderr and result.stderr.count("\n") == 1


def test_the_search_spans_the_depths_the_calibration_saw():
    # a probe calibrated at 30-130 mm (a random design's working range) is searched
    # there, not over the default 8-60 mm, where its scene points have no match
    from endomeasure.io.records import CalibratedModel
    from endomeasure.measure.epipolar import DEPTH_RANGE_MM
    from endomeasure.pipeline import SEARCH_DEPTH_MARGINS, search_depths

    seen = CalibratedModel("raytrace", None, None, None, depth_range_mm=(30.0, 130.0))
    near, far = search_depths(seen)
    assert near == 30.0 / SEARCH_DEPTH_MARGINS[0] and far == 130.0 * SEARCH_DEPTH_MARGINS[1]
    assert near < 30.0 and far > 130.0
    assert search_depths(CalibratedModel("raytrace", None, None, None)) == DEPTH_RANGE_MM
