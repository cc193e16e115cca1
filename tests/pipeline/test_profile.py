"""``endomeasure measure --kind profile | area-profile`` on the simulator's metal cylinder.

Ground truth: the committed ``scene`` image (``sample_sessions/scene``: the cylinder of
radius 25 mm at its exact pose ``T_camera_surface``, its marks' exact 3D points); the
session holds the simulator's truth optics as the raytrace model. The true profile is
where each sample pixel's ray meets the analytic cylinder, against the plane through
the three reference marks' true points. Bad input: one line, exit 2, the session byte
for byte unchanged.
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
from endomeasure.conventions import Half
from endomeasure.io.records import PROFILE_RECORD
from endomeasure.io.session import ImageRecord, edit_session, open_session
from endomeasure.models import model_from_dict

runner = CliRunner()
SAMPLES = Path(__file__).parents[2] / "sample_sessions"
SCENE = "scene_001"
REF_MARKS = (0, 1, 3)
"""Marks 0, 1 and 3 span a triangle; the operator search matches marks reliably."""
PATH = ((110.0, 236.0), (300.0, 236.0))
"""Across the cylinder's axis (about vertical), through the area both halves see."""

pytestmark = pytest.mark.skipif(
    not (SAMPLES / "simulation.json").exists(), reason="no committed samples"
)


def _truth() -> dict:
    return json.loads((SAMPLES / "scene" / f"{SCENE}.json").read_text())


def _model():
    return model_from_dict(json.loads((SAMPLES / "simulation.json").read_text())["truth_model"])


def _cylinder_points(model, pixels: np.ndarray) -> np.ndarray:
    """Where the left rays of ``pixels`` meet the cylinder (camera frame, mm)."""
    truth = _truth()
    T = np.asarray(truth["T_camera_surface"]["matrix"])
    R, t = T[:3, :3], T[:3, 3]
    r = truth["target"]["radius_mm"]
    rays = model.rays(pixels, Half.LEFT)
    o = (rays.origins - t) @ R  # to the surface frame
    d = rays.directions @ R
    oz = o[:, 2] - r
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[:, 0] * d[:, 0] + oz * d[:, 2])
    c = o[:, 0] ** 2 + oz**2 - r * r
    s = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    return (o + s[:, None] * d) @ R.T + t


def _true_heights(model, pixels) -> np.ndarray:
    marks = np.asarray(_truth()["marks"]["points_mm"])[list(REF_MARKS)]
    n = np.cross(marks[1] - marks[0], marks[2] - marks[0])
    n /= np.linalg.norm(n)
    n = n if n @ (-marks[0]) > 0 else -n  # towards the probe
    return (_cylinder_points(model, pixels) - marks[0]) @ n


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    model = _model()
    image = cv2.imread(str(SAMPLES / "scene" / f"{SCENE}.png"), cv2.IMREAD_UNCHANGED)
    blank = np.full_like(image, 110)
    path = tmp_path_factory.mktemp("profile") / "scene.h5"
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=tuple(model.config.image_size), split=model.config.split)
        w.write_images([ImageRecord(SCENE, image, f"{SCENE}.png", "0" * 64, "scene"),
                        ImageRecord("blank", blank, "blank.png", "1" * 64, "scene")])  # fmt: skip
        w.write_model(model_record("raytrace", model))
    return path


def _args(option: str, pixels) -> list[str]:
    return [a for q in pixels for a in (option, f"{q[0]:.17g},{q[1]:.17g}")]


def _refs() -> list:
    return [_truth()["marks"]["pixels"]["left"][i] for i in REF_MARKS]


def test_the_cylinder_profile_against_three_marks_matches_the_analytic_one(session, tmp_path):
    plot = tmp_path / "profile.png"
    result = runner.invoke(cli.app, ["measure", str(session), "--image", SCENE, "--kind",
                                     "profile", *_args("--left", PATH), *_args("--ref", _refs()),
                                     "--plot", str(plot), "--json"])  # fmt: skip
    assert result.exit_code == 0, result.stderr
    doc = json.loads(result.stdout)
    prof = doc["profiles"][0]
    samples = prof["samples"]
    pixels = np.asarray(samples["pixel"])
    truth = _true_heights(_model(), np.rint(pixels))
    h, s = np.asarray(samples["height_mm"], float), np.asarray(samples["sigma_mm"], float)
    ok = np.isfinite(h)
    assert ok.sum() >= 0.9 * h.size
    # the convex cylinder bulges towards the probe between the marks and falls behind
    # the plane outside them: the deepest sample is at an end, well beyond its sigma
    deepest = prof["deepest"]
    assert deepest["height_mm"] < -3 * deepest["sigma_mm"]
    for e in (prof["deepest"], prof["highest"]):
        true = truth[e["index"]]
        assert abs(e["height_mm"] - true) <= 2 * e["sigma_mm"], (e, true)
    # and it is the deepest of the true profile where the surface has a depth
    assert abs(deepest["height_mm"] - truth[ok].min()) <= 2 * deepest["sigma_mm"]
    assert np.mean(np.abs(h[ok] - truth[ok]) <= 2 * s[ok]) >= 0.9
    assert plot.stat().st_size > 0 and doc["plot"] == str(plot)
    with open_session(session) as reader:
        rec = reader.record(PROFILE_RECORD, doc["record"])
    assert rec.attrs["extreme_height"] == pytest.approx(doc["extreme"]["height_mm"])
    np.testing.assert_allclose(rec.arrays["sample_height"], h, equal_nan=True)


def test_area_profile_reports_every_slice_and_the_extreme_one(session):
    lines = [(120.0, 200.0), (120.0, 270.0), (290.0, 200.0), (290.0, 270.0)]
    result = runner.invoke(cli.app, ["measure", str(session), "--image", SCENE, "--kind",
                                     "area-profile", *_args("--left", lines), "--slices", "3",
                                     "--json"])  # fmt: skip
    assert result.exit_code == 0, result.stderr
    doc = json.loads(result.stdout)
    assert len(doc["profiles"]) == 3
    assert doc["plane"]["source"] == "best fit"
    # the best-fit plane to two lines across the cylinder's axis: the surface between
    # them bulges towards the probe, in every slice
    tops = [p["highest"]["height_mm"] for p in doc["profiles"]]
    assert all(t > 2 * p["highest"]["sigma_mm"] for t, p in zip(tops, doc["profiles"], strict=True))
    k = doc["extreme_slice"]
    assert (
        doc["extreme"] == doc["profiles"][k]["highest"]
        or doc["extreme"] == (doc["profiles"][k]["deepest"])
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--image", "blank", "--kind", "profile", *_args("--left", PATH)], "depth"),
        (["--image", SCENE, "--kind", "profile", "--left", "400,236", "--left", "500,236"],
         "left half"),
        (["--image", SCENE, "--kind", "profile", "--left", "2,20", "--left", "40,20"],
         "depth"),
        (["--image", SCENE, "--kind", "profile", *_args("--left", [*PATH, (200, 200)])],
         "exactly 2"),
        (["--image", SCENE, "--kind", "area-profile", *_args("--left", PATH)], "exactly 4"),
        (["--image", SCENE, "--kind", "profile", *_args("--left", PATH), "--ref", "158,191",
          "--ref", "238,191"], "exactly 3"),
        (["--image", SCENE, "--kind", "length", *_args("--left", PATH), "--slices", "3"],
         "--slices"),
    ],
    ids=["untextured", "right-half", "outside-the-overlap", "three-points", "two-points",
         "two-refs", "slices-on-a-length"],
)  # fmt: skip
def test_bad_input_is_one_line_exit_2_and_stores_nothing(session, args, message):
    before = session.read_bytes()
    result = runner.invoke(cli.app, ["measure", str(session), *args])
    assert result.exit_code == 2, result.output
    assert message in result.stderr and result.stderr.count("error:") == 1
    assert "Traceback" not in result.stderr
    assert session.read_bytes() == before


def test_collinear_reference_points_are_refused(session):
    # a point repeated: the three reference points span no triangle
    refs = _refs()
    before = session.read_bytes()
    result = runner.invoke(cli.app, ["measure", str(session), "--image", SCENE, "--kind",
                                     "profile", *_args("--left", PATH),
                                     *_args("--ref", [refs[0], refs[1], refs[0]])])  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "collinear" in result.stderr and result.stderr.count("error:") == 1
    assert session.read_bytes() == before
