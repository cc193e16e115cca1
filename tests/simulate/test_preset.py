"""Simulator presets: the ground-truth optics and its deliberate imperfections."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from endomeasure.errors import BadInputError
from endomeasure.simulate.optics import apex_columns
from endomeasure.simulate.preset import Preset, builtin_presets, load_preset

NOMINAL_FACE_DEG = 37.0
"""The nominal biprism face tilt of the default design (docs/simulator.md)."""


def test_default_is_builtin_and_round_trips_through_its_data(default_preset):
    assert "default" in builtin_presets()
    again = Preset.from_dict(default_preset.to_dict())
    np.testing.assert_array_equal(again.truth_model.params, default_preset.truth_model.params)
    assert again.digest == default_preset.digest


def test_truth_has_the_effects_the_calibrated_models_lack(default_preset):
    truth = default_preset.truth_model.named_params()
    # terms the raytrace model holds at zero by default (the paper's lens lacks them)
    for name in ("k3", "p1", "p2"):
        assert truth[name] != 0.0, name
    # faces tilted off nominal about both axes
    assert abs(np.degrees(truth["left_a"])) != NOMINAL_FACE_DEG
    assert abs(np.degrees(truth["right_a"])) != NOMINAL_FACE_DEG
    assert abs(truth["left_a"]) != abs(truth["right_a"])
    for face in ("rear", "left", "right"):
        assert truth[f"{face}_b"] != 0.0
    # the apex (where the front faces meet) is off the optical axis
    assert default_preset.apex_point[0] != 0.0


def test_front_faces_meet_at_the_apex_point(default_preset):
    model = default_preset.truth_model
    for face in ("left", "right"):
        normal, d = model.face(face)
        assert normal @ default_preset.apex_point == pytest.approx(d, abs=1e-12)


def test_split_is_the_column_boundary_nearest_the_apex_image(default_preset):
    height = default_preset.image_size[1]
    u_apex = apex_columns(default_preset.truth_optics, np.array([(height - 1) / 2.0]))[0]
    assert abs((default_preset.split - 0.5) - u_apex) <= 0.5
    # the apex is off axis, so the halves are not equal
    assert default_preset.split != default_preset.image_size[0] // 2


def test_blur_is_smallest_at_best_focus_and_grows_both_ways(default_preset):
    focus = default_preset.lens["best_focus_mm"]
    z = np.array([10.0, 13.0, focus, 25.0, 45.0])
    sigma = default_preset.blur_sigma_px(z)
    assert sigma[2] == pytest.approx(default_preset.lens["psf_sigma_px"])
    assert sigma[0] > sigma[1] > sigma[2] < sigma[3] < sigma[4]
    # closed form: A f |1/z - 1/z_f| / 4 in quadrature with the in-focus PSF
    c = default_preset.aperture_mm * default_preset.lens["fx"] * abs(1 / 10.0 - 1 / focus)
    assert sigma[0] == pytest.approx(np.hypot(default_preset.lens["psf_sigma_px"], c / 4))


def test_unknown_preset_name_is_a_domain_error():
    with pytest.raises(BadInputError, match="unknown simulator preset"):
        load_preset("no-such-preset")


def test_malformed_preset_files_are_domain_errors(tmp_path, default_preset):
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    with pytest.raises(BadInputError, match="not valid JSON"):
        load_preset(bad_json)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(BadInputError, match="not a simulator preset"):
        load_preset(other)
    data = copy.deepcopy(default_preset.data)
    data["prism"]["n_glass"] = 0.9
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps(data))
    with pytest.raises(BadInputError, match="invalid optics"):
        load_preset(broken)
    with pytest.raises(BadInputError, match="not found"):
        load_preset(tmp_path / "missing.json")
