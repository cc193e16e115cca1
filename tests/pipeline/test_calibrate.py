"""``endomeasure calibrate`` and ``export`` on a session of synthetic detections."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from tests.solvers.calibration_data import (
    perturbed_raytrace_truth,
    synthetic_views,
    write_session,
)
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.conventions import Half
from endomeasure.io.export import read_opencv_yaml
from endomeasure.io.records import model_from_record
from endomeasure.io.session import open_session
from endomeasure.models import model_from_dict

runner = CliRunner()
NOISE_PX = 0.1


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(21), n_images=12, noise_px=NOISE_PX)
    return write_session(tmp_path_factory.mktemp("cal") / "probe.h5", data)


@pytest.fixture(scope="module")
def calibrated(session, tmp_path_factory):
    plots = tmp_path_factory.mktemp("plots")
    result = runner.invoke(
        cli.app, ["calibrate", str(session), "--model", "all", "--json", "--plot", str(plots)]
    )
    return result, plots


def test_calibrate_all_prints_one_json_document(calibrated):
    result, _ = calibrated
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert set(doc["models"]) == {"pinhole", "raytrace"}
    ray = doc["models"]["raytrace"]
    # the raytrace fit reaches the detection noise (per-axis sigma) within 10 %
    assert ray["residual_sigma_px"] == pytest.approx(NOISE_PX, rel=0.10)
    assert doc["models"]["pinhole"]["rms_px"] > ray["rms_px"]
    assert doc["refused"] == {}


def test_results_are_stored_with_everything_needed_later(calibrated, session):
    with open_session(session) as s:
        assert {"pinhole", "raytrace"} <= set(s.model_names())
        rec = s.model("raytrace")
    free = [str(n) for n in rec.arrays["free_names"]]
    cov = rec.arrays["covariance"]
    assert cov.shape == (len(free), len(free))
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), rec.arrays["std"])
    assert rec.units["rms"] == "px"
    units = dict(zip(free, (str(u) for u in rec.arrays["free_units"]), strict=True))
    assert (units["fx"], units["rear_d"], units["left_a"], units["k1"]) == ("px", "mm", "rad", "1")
    # the stored residuals are reproduced by the stored model and poses
    model = model_from_record(rec)
    from endomeasure.geometry.rotations import rotation_matrix

    img = rec.arrays["obs_image"]
    R = rotation_matrix(rec.arrays["rvecs"])[img]
    P = np.einsum("nij,nj->ni", R, rec.arrays["obs_board_points"]) + rec.arrays["tvecs"][img]
    for h in Half:
        sel = rec.arrays["obs_half"] == h
        q = model.project(P[sel], h).pixels
        ok = np.all(np.isfinite(q), axis=-1)
        assert ok.mean() > 0.99
        np.testing.assert_allclose(
            q[ok] - rec.arrays["obs_pixels"][sel][ok], rec.arrays["residuals"][sel][ok], atol=1e-6
        )


def test_residual_plots_are_written(calibrated):
    _, plots = calibrated
    names = sorted(p.name for p in plots.iterdir())
    assert names == [
        "pinhole-residual-vectors.png",
        "pinhole-residual-vs-distance.png",
        "raytrace-residual-vectors.png",
        "raytrace-residual-vs-distance.png",
    ]
    assert all((plots / n).stat().st_size > 10_000 for n in names)


@pytest.mark.parametrize("name", ["pinhole", "raytrace"])
def test_export_json_round_trip(calibrated, session, tmp_path, name):
    out = tmp_path / f"{name}.json"
    result = runner.invoke(cli.app, ["export", str(session), str(out), "--model", name])
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    back = model_from_dict(doc)
    with open_session(session) as s:
        rec = s.model(name)
    np.testing.assert_array_equal(back.params, rec.params)
    assert back.config.to_dict() == rec.config
    assert doc["calibration"]["free_names"] == [str(n) for n in rec.arrays["free_names"]]
    if "uncertainty_covariance" in rec.arrays:
        assert doc["calibration"]["uncertain"] == [str(n) for n in rec.attrs["uncertain"]]
        np.testing.assert_array_equal(doc["calibration"]["uncertainty_covariance"],
                                      rec.arrays["uncertainty_covariance"])  # fmt: skip


def test_the_covariance_measurements_use_holds_the_held_pupil(calibrated, session):
    """The raytrace fit holds the moving pupil (its data do not call for it); the model a
    measurement varies counts it as free and the stored covariance holds it, widening the
    absolute depth but not the fitted parameters' own covariance."""
    from endomeasure.io.records import calibrated_from_record

    with open_session(session) as s:
        rec = s.model("raytrace")
    cm = calibrated_from_record(rec, session)
    free = [cm.model.PARAM_NAMES[i] for i in np.flatnonzero(cm.model.free_mask)]
    held = [str(n) for n in rec.attrs["uncertain"]]
    assert held == ["e1", "e2"] and set(held) <= set(free)
    assert not set(held) & {str(n) for n in rec.arrays["free_names"]}
    assert cm.param_cov.shape == (len(free), len(free))
    fitted = [str(n) for n in rec.arrays["free_names"]]
    rear = rec.arrays["std"][fitted.index("rear_d")]
    assert np.sqrt(cm.param_cov[free.index("rear_d"), free.index("rear_d")]) > rear


def test_export_opencv_yaml_reads_back_with_the_same_numbers(calibrated, session, tmp_path):
    out = tmp_path / "pinhole.yml"
    result = runner.invoke(
        cli.app, ["export", str(session), str(out), "--model", "pinhole", "--format", "opencv-yaml"]
    )
    assert result.exit_code == 0, result.output
    with open_session(session) as s:
        model = model_from_record(s.model("pinhole"))
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)  # plain OpenCV, no endomeasure
    M1, D2, R, T = (fs.getNode(k).mat() for k in ("M1", "D2", "R", "T"))
    fs.release()
    assert M1[0, 0] == model.left_fx and M1[0, 2] == model.left_cx
    np.testing.assert_array_equal(D2.ravel(), model.right[[4, 5, 6, 7, 8]])
    Rm, t = model.pose_right_left()
    np.testing.assert_array_equal(R, Rm)
    np.testing.assert_array_equal(T.ravel(), t)
    back = read_opencv_yaml(out)
    assert back["split"] == 320 and back["image_width"] == 640


def test_export_yaml_of_raytrace_is_refused(calibrated, session, tmp_path):
    result = runner.invoke(
        cli.app,
        ["export", str(session), str(tmp_path / "r.yml"), "--model", "raytrace",
         "--format", "opencv-yaml"],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "no OpenCV stereo equivalent" in result.stderr


def test_refusal_exits_1_and_stores_nothing(tmp_path):
    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(22), n_images=3)
    path = write_session(tmp_path / "few.h5", data)
    result = runner.invoke(cli.app, ["calibrate", str(path), "--model", "pinhole"])
    assert result.exit_code == 1
    assert "too few usable calibration images" in result.stderr
    with open_session(path) as s:
        assert s.model_names() == []


def test_a_seed_seeds_only_the_model_of_its_kind(session, tmp_path):
    from tests.conftest import make_raytrace_model

    copy = tmp_path / "seeded.h5"
    copy.write_bytes(session.read_bytes())
    seed = tmp_path / "design.json"
    seed.write_text(json.dumps(make_raytrace_model().to_dict()))
    result = runner.invoke(cli.app, ["calibrate", str(copy), "--seed", str(seed), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["models"]["raytrace"]["start"].startswith("the seed model")
    assert doc["models"]["pinhole"]["start"] == "per-half OpenCV calibration"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--model", "pinhole", "--glass-index", "1.6"], "has the parameter(s) ['n_glass']"),
        (["--model", "pinhole", "--free-index"], "has the parameter(s) ['n_glass']"),
        (["--model", "pinhole", "--seed", "{seed}"], "which is not being calibrated"),
        (["--glass-index", "0.9"], "must exceed 1"),
    ],
)
def test_options_no_model_to_calibrate_can_take_are_refused(session, tmp_path, args, message):
    from tests.conftest import make_raytrace_model

    seed = tmp_path / "design.json"
    seed.write_text(json.dumps(make_raytrace_model().to_dict()))
    args = [a.format(seed=seed) for a in args]
    before = session.read_bytes()
    result = runner.invoke(cli.app, ["calibrate", str(session), *args])
    assert result.exit_code == 2, result.output
    assert message in result.stderr
    assert session.read_bytes() == before


MAP_DEPTH_TOL_MM = 0.2  # rounding to 0.1 mm plus the fitted poses' error


def test_a_map_spans_the_depths_the_calibration_saw(calibrated, session, tmp_path):
    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(21), n_images=12, noise_px=NOISE_PX)
    z = np.concatenate(
        [
            (data.boards[v.board] @ R.T + t)[np.concatenate(v.ids)][:, 2]
            for v, (R, t) in zip(data.views, data.poses, strict=True)
        ]
    )
    copy = tmp_path / "map.h5"
    copy.write_bytes(session.read_bytes())
    result = runner.invoke(
        cli.app, ["predict-error", str(copy), "--map", "--model", "raytrace", "--json"]
    )
    assert result.exit_code == 0, result.output
    depths = json.loads(result.stdout)["depths"]
    assert len(depths) == 8
    assert depths[0] == pytest.approx(z.min(), abs=MAP_DEPTH_TOL_MM)
    assert depths[-1] == pytest.approx(z.max(), abs=MAP_DEPTH_TOL_MM)


@pytest.mark.parametrize("uncertain", [["e1", "not_a_parameter"], ["e1"]])
def test_a_crafted_measurement_covariance_is_refused_in_one_line(calibrated, session, uncertain):
    """Unknown held names, or a covariance that does not fit the model with them free."""
    import dataclasses

    from endomeasure.errors import BadInputError
    from endomeasure.io.records import calibrated_from_record

    with open_session(session) as s:
        rec = s.model("raytrace")
    crafted = dataclasses.replace(rec, attrs={**rec.attrs, "uncertain": uncertain})
    with pytest.raises(BadInputError) as err:
        calibrated_from_record(crafted, session)
    assert "\n" not in str(err.value)
