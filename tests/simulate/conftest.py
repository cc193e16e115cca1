"""Fixtures of the simulator tests: the default preset and a small, fast variant of it."""

from __future__ import annotations

import copy
import json

import pytest

from endomeasure.simulate.preset import Preset, load_preset

SMALL_SCALE = 4
"""The small preset divides the sensor resolution by this (same optics, same field)."""


def small_preset_data() -> dict:
    """The default preset at 1/4 resolution with 2 + 2 + 1 images: for end-to-end runs."""
    data = copy.deepcopy(load_preset("default").data)
    f = SMALL_SCALE
    width, height = data["sensor"]["image_size"]
    data["name"] = "small-test"
    data["sensor"]["image_size"] = [width // f, height // f]
    lens = data["lens"]
    lens["fx"] /= f
    lens["fy"] /= f
    # pixel centres at integers: u' + 0.5 = (u + 0.5) / f
    lens["cx"] = (lens["cx"] + 0.5) / f - 0.5
    lens["cy"] = (lens["cy"] + 0.5) / f - 0.5
    lens["psf_sigma_px"] /= f
    sets = data["sets"]
    for group in sets["calib"]["boards"]:
        group["images"] = 1 if group["target"] != "board_1" else 0
    sets["calib"]["boards"] = [g for g in sets["calib"]["boards"] if g["images"]]
    sets["calib"]["partial_images"] = 0
    sets["test"]["boards"] = [
        {"target": "board_2", "distance_mm": [30.0, 31.0], "step_mm": 1.0},
    ]
    sets["scene"]["images"] = 1
    return data


@pytest.fixture(scope="session")
def default_preset() -> Preset:
    return load_preset("default")


@pytest.fixture(scope="session")
def small_preset() -> Preset:
    return Preset.from_dict(small_preset_data(), source="tests/simulate small preset")


@pytest.fixture
def small_preset_file(tmp_path):
    path = tmp_path / "small.json"
    path.write_text(json.dumps(small_preset_data()))
    return path
