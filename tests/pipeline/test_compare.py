"""``endomeasure compare`` on sessions of known models (``measure_data``): a session
against a copy whose baseline is scaled, two models of one session, and bad input."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest
from tests.conftest import scaled_world
from tests.pipeline.measure_data import build_session
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.records import model_from_record
from endomeasure.io.session import edit_session

runner = CliRunner()
DEPTHS = "15,25"
GRID = "6,5"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    path = tmp_path_factory.mktemp("compare") / "probe.h5"
    return build_session(path, models=("raytrace", "pinhole"))[0]


def _compare(*args):
    return runner.invoke(cli.app, ["compare", *map(str, args), "--depths", DEPTHS, "--grid", GRID])


def _scaled(session, path, factor):
    shutil.copyfile(session, path)
    with edit_session(path) as w:
        record = w.model("raytrace")
        model = scaled_world(model_from_record(record), factor)
        w.write_model(dataclasses.replace(record, params=model.params))
    return path


def test_a_copy_agrees_and_a_scaled_baseline_disagrees(session, tmp_path):
    same = _compare(session, _scaled(session, tmp_path / "same.h5", 1.0), "--json")
    assert same.exit_code == 0, same.output
    doc = json.loads(same.stdout)
    assert doc["verdict"] == "agree"
    assert all(r["length_diff_max_mm"] == 0 and r["left_max_px"] == 0 for r in doc["per_depth"])
    plot = tmp_path / "maps.png"
    scaled = _compare(session, _scaled(session, tmp_path / "b.h5", 1.01), "--json", "--plot", plot)
    assert scaled.exit_code == 1, scaled.output
    doc = json.loads(scaled.stdout)
    assert doc["verdict"] == "disagree" and doc["exit_code"] == 1
    for r in doc["per_depth"]:
        assert r["length_diff_mean_mm"] == pytest.approx(0.01, rel=1e-6)
        assert r["rms_z"] > doc["rms_z_limit"] and r["outside_band"] > 0.5
    assert plot.stat().st_size > 10_000
    lines = scaled.stderr.strip().splitlines()
    assert lines[-1].startswith("error: disagree: at z = 15 mm")


def test_two_models_of_one_session_of_different_designs_disagree(session):
    result = _compare(session, session, "--model", "raytrace", "--model-b", "pinhole")
    assert result.exit_code == 1, result.output
    assert result.stderr.strip().splitlines()[-1].startswith("error: disagree")


@pytest.mark.parametrize(
    "args, message",
    [
        (("--model", "raytrace"), "the same calibration"),
        (("--model-b", "nothing"), "no calibrated 'nothing' model"),
        (("--model-b", "pinhole", "--depths", "-3"), "positive"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(session, args, message):
    result = runner.invoke(cli.app, ["compare", str(session), str(session), *args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0]
