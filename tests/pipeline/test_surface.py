"""``endomeasure surface``: dense depth of a textured plane through the command line,
stored with its PLY point cloud; bad regions and untextured ones refused with one line,
the session left as it was."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tests.conftest import make_raytrace_model
from tests.measure.dense_data import render_plane
from tests.pipeline.measure_data import model_record
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.records import SURFACE_RECORD
from endomeasure.io.session import ImageRecord, edit_session, open_session

runner = CliRunner()
DEPTH_MM = 18.0
REGION = "250,200,310,260"  # where both halves of the test model see the plane
# (near the overlap's edge: a 15 px window, which stays inside the right half there)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    model = make_raytrace_model()
    plane = render_plane(model, DEPTH_MM, np.random.default_rng(11)).astype(np.uint8)
    blank = np.full_like(plane, 100)
    path = tmp_path_factory.mktemp("surface") / "s.h5"
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=model.config.image_size, split=model.config.split)
        w.write_images([ImageRecord("plane", plane, "plane.png", "0" * 64, "scene"),
                        ImageRecord("blank", blank, "blank.png", "0" * 64, "scene")])  # fmt: skip
        w.write_model(model_record("raytrace", model))
    return path


def test_the_depth_of_a_textured_plane_is_stored_with_its_point_cloud(session, tmp_path):
    ply = tmp_path / "plane.ply"
    args = ["--image", "plane", "--region", REGION, "--window", "15", "--ply", str(ply)]
    result = runner.invoke(cli.app, ["surface", str(session), *args, "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["measured"] >= 0.8 * doc["pixels"]
    assert doc["median_depth_mm"] == pytest.approx(DEPTH_MM, rel=0.01)
    header = ply.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header
    assert f"element vertex {doc['measured']}" in header
    with open_session(session) as s:
        assert s.record_names(SURFACE_RECORD) == [doc["record"]]
        record = s.record(SURFACE_RECORD, doc["record"])
    # each depth says which rung it comes from; a pixel without one has none
    measured = np.isfinite(record.arrays["depth"])
    window, prefilter = record.arrays["window"], record.arrays["prefilter"]
    assert set(np.unique(window[measured])) <= {15, 31, 63}
    assert set(np.unique(prefilter[measured])) <= {0.0, record.attrs["prefilter_px"]}
    assert not window[~measured].any() and not prefilter[~measured].any()


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--image", "plane", "--region", "400,10,500,100"], 2, "region"),  # right half
        (["--image", "plane", "--region", "1,2,3"], 2, "U0,V0,U1,V1"),
        (["--image", "nope"], 2, "nope"),
        (["--image", "plane", "--region", "0,240,40,280"], 2, "outside the overlap"),
        (["--image", "blank", "--region", REGION], 1, "could be measured"),
    ],
    ids=[
        "outside-the-left-half",
        "bad-region",
        "unknown-image",
        "outside-the-overlap",
        "untextured",
    ],
)
def test_bad_or_unmeasurable_regions_are_one_line_and_store_nothing(
    session, tmp_path, args, code, message
):
    before = session.read_bytes()
    ply = tmp_path / "x.ply"
    result = runner.invoke(cli.app, ["surface", str(session), *args, "--ply", str(ply)])
    assert result.exit_code == code, result.output
    assert message in result.stderr and result.stderr.count("error:") == 1
    assert "Traceback" not in result.stderr
    assert session.read_bytes() == before and not ply.exists()
