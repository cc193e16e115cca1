"""The verdict through the CLI: a failed calibration is stored as not usable and says so.

Synthetic detections of the tests' raytrace design with a very good detector (0.004 px,
given as each corner's covariance): the raytrace model fits at the floor, the pinhole
pair cannot (its misfit is ten times the noise), so its calibration fails.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from tests.solvers.calibration_data import (
    perturbed_raytrace_truth,
    synthetic_views,
    write_session,
)
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.session import open_session

runner = CliRunner()
NOISE_PX = 0.004


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(31), n_images=10, noise_px=NOISE_PX)
    return write_session(tmp_path_factory.mktemp("verdict") / "probe.h5", data, NOISE_PX)


@pytest.fixture(scope="module")
def calibrated(session):
    return runner.invoke(cli.app, ["calibrate", str(session), "--model", "all", "--json"])


def test_all_models_exit_0_when_one_is_usable_and_name_the_failed_one(calibrated, session):
    assert calibrated.exit_code == 0, calibrated.output
    doc = json.loads(calibrated.stdout)
    assert doc["models"]["raytrace"]["verdict"] == "ok"
    assert doc["models"]["raytrace"]["rms_ratio"] == pytest.approx(1.0, abs=0.1)
    assert doc["models"]["pinhole"]["verdict"] == "failed"
    assert "pinhole" in doc["failed"] and doc["ok"]
    assert "calibration failed, stored as not usable" in calibrated.stderr
    with open_session(session) as s:
        record = s.model("pinhole")
    assert record.attrs["verdict"] == "failed"
    assert record.attrs["formal_floor_px"] == pytest.approx(NOISE_PX * np.sqrt(2), rel=0.1)
    assert record.attrs["noise_floor_px"] >= record.attrs["formal_floor_px"]
    assert record.arrays["obs_covariance"].shape == (len(record.arrays["obs_pixels"]), 2, 2)


def test_a_named_model_that_fails_exits_1(calibrated, session):
    result = runner.invoke(cli.app, ["calibrate", str(session), "--model", "pinhole"])
    assert result.exit_code == 1
    assert "error: pinhole: calibration failed" in result.stderr


def test_commands_that_measure_refuse_a_failed_model(calibrated, session, tmp_path):
    result = runner.invoke(
        cli.app, ["export", str(session), str(tmp_path / "m.json"), "--model", "pinhole"]
    )
    assert result.exit_code != 0
    assert "calibration failed" in result.stderr and "not usable" in result.stderr
    assert "Traceback" not in result.output
    assert not (tmp_path / "m.json").exists()
    ok = runner.invoke(
        cli.app, ["export", str(session), str(tmp_path / "r.json"), "--model", "raytrace"]
    )
    assert ok.exit_code == 0, ok.output
