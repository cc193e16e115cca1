"""``endomeasure verify`` on the bundled sample renders, with the raytrace model
calibrated from the sample calibration set (as ``make demo`` does)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import pytest
from tests.conftest import scaled_world
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.records import model_from_record
from endomeasure.io.session import edit_session, open_session

runner = CliRunner()
SAMPLES = Path(__file__).parents[2] / "sample_sessions"
MODEL = "raytrace"  # the sample probe's pinhole calibration fails its verdict (a prism)
BASELINE_SCALE = 1.005
SCALE_TOL = 0.1
"""Relative tolerance of the measured length bias against the 0.5 % put in: the sample
calibration's own length error is about 0.04 % (its predicted +-)."""

pytestmark = pytest.mark.skipif(
    not (SAMPLES / "simulation.json").exists(), reason="no committed samples"
)


def _groups(set_name):
    from endomeasure.simulate.manifest import board_groups

    return dict(board_groups(SAMPLES, set_name))


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The sample calibration set detected and calibrated with the raytrace model."""
    from endomeasure.pipeline.calibrate import calibrate_session
    from endomeasure.pipeline.detect import detect_images

    session = tmp_path_factory.mktemp("verify") / "sample.h5"
    for spec, files in _groups("calib").items():
        detect_images(session, files, spec, image_set="calib")
    report = calibrate_session(session, MODEL)
    assert report.ok, report.failed
    return session


def _test_images(spec, count=4):
    files = _groups("test")[spec]
    step = max(len(files) // count, 1)
    return [str(f) for f in files[::step][:count]]


def _verify(session, images, board, *extra):
    return runner.invoke(cli.app, ["verify", str(session), *images, "--board", board, *extra])


def _digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.mark.parametrize("board", ["chessboard:6x5:1", "chessboard:6x5:2"])
def test_the_sample_calibration_passes_on_the_sample_test_images(calibrated, board):
    before = _digest(calibrated)
    result = _verify(calibrated, _test_images(board), board, "--model", MODEL, "--json")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)  # strict JSON: NaN would not parse back as a number
    assert doc["verdict"] == "pass" and doc["reasons"] == []
    assert doc["bias_test"]["passed"] and doc["dispersion_test"]["passed"]
    assert {k["kind"] for k in doc["per_kind"]} == {"x-segment", "y-segment", "area"}
    assert doc["n"] > 100
    assert _digest(calibrated) == before  # read-only


def _scaled_copy(session, path, factor):
    shutil.copyfile(session, path)
    with edit_session(path) as w:
        record = w.model(MODEL)
        model = scaled_world(model_from_record(record), factor)
        w.write_model(dataclasses.replace(record, params=model.params))
    return path


def test_a_baseline_scaled_by_half_a_percent_asks_for_recalibration(calibrated, tmp_path):
    board = "chessboard:6x5:1"
    scaled = _scaled_copy(calibrated, tmp_path / "scaled.h5", BASELINE_SCALE)
    result = _verify(scaled, _test_images(board), board, "--json")
    assert result.exit_code == 1, result.output
    doc = json.loads(result.stdout)
    assert doc["verdict"] == "recalibrate" and doc["exit_code"] == 1
    bias = doc["bias_test"]
    assert not bias["passed"]
    assert bias["mean_relative"] == pytest.approx(BASELINE_SCALE - 1, rel=SCALE_TOL)
    assert "length bias" in doc["error"]
    assert result.stderr.strip().splitlines()[-1] == "error: " + doc["error"]
    text = _verify(scaled, _test_images(board), board)
    assert text.exit_code == 1
    assert text.stderr.strip().splitlines()[-1].startswith("error: recalibrate: lengths are +0.")


@pytest.mark.parametrize(
    "case, message",
    [
        ("scene", "no chessboard:6x5:1 board found"),
        ("pitch", "the squares measure 1 mm"),
        ("grid", "does not match the spec"),
        ("model", "no calibrated 'pinhole' model"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(calibrated, case, message):
    images, board, extra = _test_images("chessboard:6x5:1", 1), "chessboard:6x5:1", []
    if case == "scene":
        images = [str(sorted((SAMPLES / "scene").glob("*.png"))[0])]
    elif case == "pitch":
        board = "chessboard:6x5:2"
    elif case == "grid":
        board = "chessboard:7x5:1"
    else:
        extra = ["--model", "pinhole"]
    result = _verify(calibrated, images, board, *extra)
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]
    with open_session(calibrated) as s:
        assert s.model_names() == [MODEL]
