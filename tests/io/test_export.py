"""``export`` to ROS, mrcal and ray-table files, read back by those formats' own rules.

The oracles are independent of endomeasure's writer: the YAML library and
``ast.literal_eval`` parse the files, ``cv2.projectPoints`` and ``cv2.stereoRectify``
recompute from the numbers in them, and the model's own ``project`` / ``rays`` are the
truth the files must reproduce.
"""

from __future__ import annotations

import ast
import json

import cv2
import h5py
import numpy as np
import pytest
import yaml
from tests.conftest import make_pinhole_model, make_raytrace_model
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.conventions import Half, Status
from endomeasure.io.export import RAY_TABLE_VERSION, export_files, export_model
from endomeasure.io.session import ModelRecord, edit_session

runner = CliRunner()

PROJECTION_TOL_PX = 1e-6
"""The brief's bar: a file's numbers reproduce the model's pixels to a micro-pixel (the
Brown formula is evaluated in the same float64 order by OpenCV and by the model, so the
real differences are ~1e-12 px)."""
RAY_TOL = 1e-9
"""Origins (mm) and unit directions of the table against the model's rays at the same
pixels, traced in another batch (rounding differs by ~1e-15)."""
RECTIFY_TOL = 1e-9
"""The file's R and P against ``cv2.stereoRectify`` recomputed from the file's K and D
(written with 17 significant digits, so read back exactly)."""
ROS_KEYS = {
    "image_width",
    "image_height",
    "camera_name",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
    "rectification_matrix",
    "projection_matrix",
}


def points_seen_by(model, half: Half, rng, n: int = 200) -> np.ndarray:
    """3D points (n, 3), mm, on the rays of random pixels of ``half``, 5 to 40 mm away."""
    width, height = model.config.image_size
    lo, hi = (0, model.config.split) if half is Half.LEFT else (model.config.split, width)
    pixels = np.column_stack([rng.uniform(lo + 20, hi - 20, n), rng.uniform(20, height - 20, n)])
    rays = model.rays(pixels, half)
    assert np.all(rays.status == Status.OK)
    return rays.origins + rng.uniform(5.0, 40.0, (n, 1)) * rays.directions


def matrix(node: dict) -> np.ndarray:
    """A ROS ``{rows, cols, data}`` node as an array, checking its declared shape."""
    data = np.asarray(node["data"], dtype=np.float64)
    assert data.size == node["rows"] * node["cols"]
    return data.reshape(node["rows"], node["cols"])


@pytest.fixture
def ros_files(tmp_path):
    model = make_pinhole_model()
    files = export_model(model, "ros-yaml", tmp_path / "probe.yaml")
    return model, files, [yaml.safe_load(f.read_text()) for f in files]


def test_ros_yaml_is_one_file_per_half_with_every_camera_info_field(ros_files, tmp_path):
    model, files, docs = ros_files
    assert [f.name for f in files] == ["probe_left.yaml", "probe_right.yaml"]
    width, height = model.config.image_size
    for doc, half, half_width in zip(docs, ("left", "right"), (320, width - 320), strict=True):
        assert set(doc) == ROS_KEYS
        assert (doc["image_width"], doc["image_height"]) == (half_width, height)
        assert doc["camera_name"] == f"probe_{half}"
        assert doc["distortion_model"] == "plumb_bob"
        shapes = [matrix(doc[k]).shape for k in sorted(ROS_KEYS) if isinstance(doc[k], dict)]
        assert shapes == [(3, 3), (1, 5), (3, 4), (3, 3)]  # K, D, P, R by key order


def test_ros_yaml_projects_as_the_model(ros_files, rng):
    model, _, docs = ros_files
    R, t = model.pose_right_left()
    rvec = cv2.Rodrigues(R)[0]
    for half, doc, (rv, tv), shift in (
        (Half.LEFT, docs[0], (np.zeros(3), np.zeros(3)), 0),
        (Half.RIGHT, docs[1], (rvec, t), model.config.split),
    ):
        points = points_seen_by(model, half, rng)
        K, D = matrix(doc["camera_matrix"]), matrix(doc["distortion_coefficients"])
        q = cv2.projectPoints(points, rv, tv, K, D)[0].reshape(-1, 2)
        expected = model.project(points, half).pixels
        assert np.all(np.isfinite(expected))
        np.testing.assert_allclose(q + [shift, 0], expected, atol=PROJECTION_TOL_PX, rtol=0)


def test_ros_rectification_is_stereo_rectify_of_the_files_in_ros_convention(ros_files, rng):
    model, _, (left, right) = ros_files
    R, t = model.pose_right_left()
    size = (left["image_width"], left["image_height"])
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        matrix(left["camera_matrix"]), matrix(left["distortion_coefficients"]),
        matrix(right["camera_matrix"]), matrix(right["distortion_coefficients"]),
        size, R, t.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0,
    )  # fmt: skip
    for got, want in ((left, (R1, P1)), (right, (R2, P2))):
        np.testing.assert_allclose(matrix(got["rectification_matrix"]), want[0], atol=RECTIFY_TOL)
        np.testing.assert_allclose(matrix(got["projection_matrix"]), want[1], atol=RECTIFY_TOL)
    P_right = matrix(right["projection_matrix"])
    # ROS: the right camera's P[0, 3] is -fx' * baseline; the left one's 0
    assert P_right[0, 3] == pytest.approx(-P_right[0, 0] * np.linalg.norm(t), rel=1e-12)
    assert matrix(left["projection_matrix"])[0, 3] == 0.0
    # rectified, a point lands on the same row in both halves (P applies to the
    # rectified left frame, where R1 takes left-camera points)
    p = points_seen_by(model, Half.LEFT, rng, 20)
    rect = np.column_stack([p @ matrix(left["rectification_matrix"]).T, np.ones(len(p))])
    rows = [(rect @ matrix(doc["projection_matrix"]).T) for doc in (left, right)]
    rows = [h[:, 1] / h[:, 2] for h in rows]
    np.testing.assert_allclose(rows[0], rows[1], atol=1e-9)


def test_mrcal_cameramodel_parses_and_projects_as_the_model(tmp_path, rng):
    model = make_pinhole_model()
    files = export_model(model, "mrcal", tmp_path / "probe.cameramodel")
    assert [f.name for f in files] == ["probe_left.cameramodel", "probe_right.cameramodel"]
    width, height = model.config.image_size
    split = model.config.split
    for path, half, size, shift in (
        (files[0], Half.LEFT, [split, height], 0),
        (files[1], Half.RIGHT, [width - split, height], split),
    ):
        text = path.read_text()
        assert "mm" in text.splitlines()[1]  # the units comment
        doc = ast.literal_eval(text)
        assert set(doc) == {"lensmodel", "intrinsics", "extrinsics", "imagersize"}
        assert doc["lensmodel"] == "LENSMODEL_OPENCV5"
        assert (len(doc["intrinsics"]), len(doc["extrinsics"])) == (9, 6)
        assert doc["imagersize"] == size
        fx, fy, cx, cy, *distortion = doc["intrinsics"]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        r, t = np.array(doc["extrinsics"][:3]), np.array(doc["extrinsics"][3:])
        points = points_seen_by(model, half, rng)
        q = cv2.projectPoints(points, r, t, K, np.array(distortion))[0].reshape(-1, 2)
        np.testing.assert_allclose(
            q + [shift, 0], model.project(points, half).pixels, atol=PROJECTION_TOL_PX, rtol=0
        )
    assert ast.literal_eval(files[0].read_text())["extrinsics"] == [0.0] * 6


@pytest.mark.parametrize(
    ("model", "rays_fail"),
    [
        (make_pinhole_model(), False),
        (make_raytrace_model(), False),
        (make_raytrace_model(left_a=-0.9), True),  # a steep left face: TIR at the edge
    ],
    ids=["pinhole", "raytrace", "raytrace-with-total-internal-reflection"],
)
def test_ray_table_reproduces_the_model_rays_at_every_pixel_centre(model, rays_fail, tmp_path, rng):
    (path,) = export_model(model, "ray-table", tmp_path / "rays.h5")
    width, height = model.config.image_size
    split = model.config.split
    checked = failed = 0
    with h5py.File(path, "r") as f:
        assert f.attrs["model"] == model.NAME and f.attrs["units"] == "mm"
        assert f.attrs["format_version"] == RAY_TABLE_VERSION
        assert "model frame" in f.attrs["frame"] and "origin" in f.attrs["description"]
        assert json.loads(f.attrs["model_document"])["params"] == model.params.tolist()
        for half, columns in ((Half.LEFT, np.arange(split)), (Half.RIGHT, np.arange(split, width))):
            g = f[half.label]
            np.testing.assert_array_equal(g["pixel_x"][()], columns)
            np.testing.assert_array_equal(g["pixel_y"][()], np.arange(height))
            origin, direction = g["origin"][()], g["direction"][()]
            valid, status = g["valid"][()], g["status"][()]
            assert origin.shape == direction.shape == (height, columns.size, 3)
            np.testing.assert_array_equal(valid, status == Status.OK)
            # every pixel: a ray exactly where valid, NaN elsewhere
            assert np.all(np.isfinite(direction[valid == 1]))
            assert np.all(np.isnan(origin[valid == 0])) and np.all(np.isnan(direction[valid == 0]))
            np.testing.assert_allclose(np.linalg.norm(direction[valid == 1], axis=-1), 1.0)
            # a sample against the model at those pixel centres, traced on their own
            i = rng.integers(0, height, 300)
            j = rng.integers(0, columns.size, 300)
            pixels = np.column_stack([g["pixel_x"][()][j], g["pixel_y"][()][i]])
            rays = model.rays(pixels, half)
            np.testing.assert_array_equal(status[i, j], rays.status)
            ok = rays.status == Status.OK
            np.testing.assert_allclose(origin[i, j][ok], rays.origins[ok], atol=RAY_TOL, rtol=0)
            np.testing.assert_allclose(direction[i, j][ok], rays.directions[ok], atol=RAY_TOL,
                                       rtol=0)  # fmt: skip
            checked += int(ok.sum())
            failed += int((valid == 0).sum())
    assert checked > 300
    assert (failed > 1000) is rays_fail and (failed == 0) is not rays_fail


def test_per_half_names_and_suffixes(tmp_path):
    assert [p.name for p in export_files("mrcal", tmp_path / "a.b.cameramodel")] == [
        "a.b_left.cameramodel",
        "a.b_right.cameramodel",
    ]
    assert export_files("ray-table", tmp_path / "t.h5") == (tmp_path / "t.h5",)
    for fmt, name in (("ros-yaml", "p.json"), ("mrcal", "p.yaml"), ("ray-table", "p.npz")):
        with pytest.raises(Exception, match="must end in"):
            export_files(fmt, tmp_path / name)


# ----- through the command ---------------------------------------------------------------


@pytest.fixture
def session(tmp_path):
    """A session holding the test designs as stored models (no images needed to export)."""
    path = tmp_path / "probe.h5"
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(640, 480), split=320, split_method="auto")
        for model in (make_pinhole_model(), make_raytrace_model()):
            w.write_model(
                ModelRecord(
                    model.NAME,
                    model.NAME,
                    model.params.copy(),
                    model.PARAM_NAMES,
                    model.config.to_dict(),
                )  # fmt: skip
            )
    return path


@pytest.mark.parametrize("fmt", ["ros-yaml", "mrcal"])
def test_a_per_half_format_of_the_raytrace_model_is_one_line_exit_2(session, tmp_path, fmt):
    out = tmp_path / ("r.yaml" if fmt == "ros-yaml" else "r.cameramodel")
    result = runner.invoke(
        cli.app, ["export", str(session), str(out), "--model", "raytrace", "--format", fmt]
    )
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert result.stderr.startswith("error: ") and "no OpenCV stereo equivalent" in result.stderr
    assert not any(p.name.startswith("r_") for p in tmp_path.iterdir())


def test_export_ros_yaml_through_the_command(session, tmp_path):
    out = tmp_path / "cam.yaml"
    result = runner.invoke(
        cli.app, ["export", str(session), str(out), "--format", "ros-yaml", "--json"]
    )
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["files"] == [str(tmp_path / "cam_left.yaml"), str(tmp_path / "cam_right.yaml")]
    assert yaml.safe_load((tmp_path / "cam_right.yaml").read_text())["camera_name"] == "cam_right"


def test_a_per_half_file_goes_through_the_output_checks(session, tmp_path):
    (tmp_path / "cam_right.cameramodel").mkdir()
    result = runner.invoke(
        cli.app, ["export", str(session), str(tmp_path / "cam.cameramodel"), "--format", "mrcal"]
    )
    assert result.exit_code == 2
    assert "right half exists and is a directory" in result.stderr
    assert not (tmp_path / "cam_left.cameramodel").exists()  # refused before writing any
