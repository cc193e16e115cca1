"""Fixtures for the session tests: a session holding one item of every stored kind."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from endomeasure.conventions import Half
from endomeasure.io.session import (
    Detection,
    ImageRecord,
    ModelRecord,
    Record,
    edit_session,
)


def image_record(name: str, pixels: np.ndarray, image_set: str = "calib") -> ImageRecord:
    """An image record whose hash is the hash of its pixel bytes (stands in for a file)."""
    return ImageRecord(
        name=name,
        pixels=pixels,
        original_path=f"/data/{name}.png",
        sha256=hashlib.sha256(pixels.tobytes()).hexdigest(),
        image_set=image_set,
    )


@pytest.fixture
def contents(rng: np.random.Generator) -> dict:
    """One item of every kind the session stores, with random payloads."""
    cov = rng.normal(size=(5, 5))
    return {
        "metadata": {"image_size": (64, 48), "split": 31, "split_method": "auto"},
        "images": [
            image_record("grey8", rng.integers(0, 256, (48, 64), dtype=np.uint8)),
            image_record("colour16", rng.integers(0, 65536, (48, 64, 3), dtype=np.uint16), "test"),
            image_record("scene0", rng.integers(0, 256, (48, 64), dtype=np.uint8), "scene"),
        ],
        "boards": {
            "cb1": (
                "chessboard:9x6:1.0",
                {"kind": "chessboard", "cols": 9, "rows": 6, "square_mm": 1.0},
            ),
            "ch2": (
                "charuco:8x6:2.0:1.5:DICT_4X4_50",
                {
                    "kind": "charuco",
                    "dictionary": "DICT_4X4_50",
                    "marker_mm": 1.5,
                    "layout": {"squares": [8, 6]},
                },
            ),
        },
        "detections": [
            Detection(
                "grey8",
                "cb1",
                Half.LEFT,
                rng.permutation(54)[:20].astype(np.int32),
                rng.uniform(0, 31, (20, 2)),
                0.83,
                "",
            ),
            Detection(
                "grey8",
                "cb1",
                Half.RIGHT,
                np.zeros(0, np.int32),
                np.zeros((0, 2)),
                math.nan,
                "no corners found",
                {"threshold": 12},
            ),
            Detection(
                "colour16",
                "ch2",
                Half.RIGHT,
                np.arange(7, dtype=np.int32),
                rng.uniform(32, 63, (7, 2)),
                0.5,
                "",
            ),
        ],
        "models": [
            ModelRecord(
                name="pinhole",
                registry_name="pinhole",
                params=rng.normal(size=5),
                param_names=("fx", "fy", "cx", "cy", "k1"),
                config={"image_size": [64, 48], "split": 31, "fixed": {"k3": 0.0}},
                arrays={
                    "covariance": cov @ cov.T,
                    "per_image_rms": rng.uniform(0, 1, 4),
                    "image_names": np.array(["a", "b", "c", "d"]),
                },
                attrs={"rms": 0.137, "status": "converged", "n_iterations": 17},
                units={"rms": "px", "per_image_rms": "px"},
            ),
        ],
        "records": [
            Record(
                "measurement",
                "m001",
                attrs={
                    "measurement_kind": "length",
                    "value": 3.25,
                    "sigma": 0.02,
                    "warning": False,
                    "pixels_left": [1.5, 2.5],
                },
                arrays={
                    "points": rng.normal(size=(2, 3)),
                    "status": np.array([0, 1], dtype=np.uint8),
                },
                units={"value": "mm", "sigma": "mm", "points": "mm"},
            ),
            Record(
                "prediction",
                "zone-12",
                attrs={"method": "unscented", "alpha": 1e-3},
                arrays={"mean": rng.normal(size=4)},
            ),
        ],
    }


def write_contents(path, contents: dict) -> None:
    """Write every item of ``contents`` in one edit, creating the session."""
    with edit_session(path, create=True) as w:
        w.set_metadata(**contents["metadata"])
        w.write_images(contents["images"])
        for name, (spec, attrs) in contents["boards"].items():
            w.write_board(name, spec, attrs)
        w.write_detections(contents["detections"])
        for model in contents["models"]:
            w.write_model(model)
        w.write_records(contents["records"])


@pytest.fixture
def session_path(tmp_path, contents):
    path = tmp_path / "probe.h5"
    write_contents(path, contents)
    return path


@pytest.fixture
def write_session():
    """The function that writes a contents dict to a new session."""
    return write_contents
