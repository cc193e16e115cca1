"""The model contract holds: a third model, defined and registered here and nowhere else,
is projected, traced, calibrated, board-tested and error-predicted through the public API
(the solver, then the command line on a session).

The model is the pinhole pair with OpenCV's rational distortion (``k4 k5 k6`` in the
denominator, ``cv2.CALIB_RATIONAL_MODEL``). It implements only the contract's required
hooks; its Jacobians, projector and validity come from the generic defaults, and its
calibration start is its own (seeded from the ``pinhole`` pair). Truth: its projections
agree with ``cv2.projectPoints``; synthetic detections come from a known rational model.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest
from tests.conftest import make_pinhole_model
from tests.solvers.calibration_data import synthetic_views

from endomeasure.conventions import STATUS_DTYPE, Half, Status
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.models import MODELS, CameraModel, register_model, unregister_model
from endomeasure.models.start import Start
from endomeasure.solvers.calibrate import calibrate

_INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
UNDISTORT_TOL = 1e-13  # normalised units: ~1e-10 px
UNDISTORT_MAX_ITER = 50
OPENCV_TOL_PX = 1e-6  # cv2.projectPoints works in double precision
EXACT_RMS_PX = 1e-6  # exact detections: only the convergence tolerances remain
EXACT_PARAM_REL = 1e-5


def _rational(x, y, c):
    """OpenCV's rational + tangential distortion of normalised coordinates."""
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


class RationalPinholeModel(CameraModel):
    """Two virtual pinhole cameras with rational distortion and their relative pose."""

    NAME: ClassVar[str] = "rational-test"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = (
        tuple(f"left_{n}" for n in _INTRINSICS)
        + tuple(f"right_{n}" for n in _INTRINSICS)
        + ("rx", "ry", "rz", "tx", "ty", "tz")
    )
    PARAM_UNITS: ClassVar[dict[str, str]] = {
        **{
            f"{h}_{n}": "px" if n in ("fx", "fy", "cx", "cy") else "1"
            for h in ("left", "right")
            for n in _INTRINSICS
        },
        **dict.fromkeys(("rx", "ry", "rz"), "rad"),
        **dict.fromkeys(("tx", "ty", "tz"), "mm"),
    }
    DEFAULT_FIXED: ClassVar[frozenset[str]] = frozenset(
        f"{h}_{n}" for h in ("left", "right") for n in ("k1", "k2", "k3", "k5", "k6")
    )
    """Only the first denominator term is estimated (with the numerator it would trade
    against k1 to first order)."""
    SEEDED_FROM: ClassVar[str | None] = "pinhole"

    def _intrinsics(self, half: Half) -> np.ndarray:
        first = self.index(f"{half.label}_fx")
        return self.params[first : first + len(_INTRINSICS)]

    def _pose(self):
        return rotation_matrix(self.params[24:27]), self.params[27:30]

    def _project(self, points, half):
        if half is Half.RIGHT:
            R, t = self._pose()
            points = points @ R.T + t
        fx, fy, cx, cy, *dist = self._intrinsics(half)
        z = points[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xd, yd = _rational(points[:, 0] / z, points[:, 1] / z, dist)
        pixels = np.stack([fx * xd + cx, fy * yd + cy], axis=-1)
        status = np.where(z > 0, Status.OK, Status.BEHIND).astype(STATUS_DTYPE)
        return pixels, status

    def _rays(self, pixels, half):
        fx, fy, cx, cy, *dist = self._intrinsics(half)
        xd, yd = (pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy
        x, y = xd.copy(), yd.copy()
        for _ in range(UNDISTORT_MAX_ITER):  # Newton with a central-difference Jacobian
            fx_, fy_ = _rational(x, y, dist)
            ex, ey = fx_ - xd, fy_ - yd
            h = 1e-7
            (xp, yp), (xm, ym) = _rational(x + h, y, dist), _rational(x - h, y, dist)
            a11, a21 = (xp - xm) / (2 * h), (yp - ym) / (2 * h)
            (xp, yp), (xm, ym) = _rational(x, y + h, dist), _rational(x, y - h, dist)
            a12, a22 = (xp - xm) / (2 * h), (yp - ym) / (2 * h)
            det = a11 * a22 - a12 * a21
            sx, sy = (a22 * ex - a12 * ey) / det, (a11 * ey - a21 * ex) / det
            x, y = x - sx, y - sy
            if np.all(np.abs(sx) + np.abs(sy) < UNDISTORT_TOL):
                break
        converged = np.abs(sx) + np.abs(sy) < UNDISTORT_TOL
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        origins = np.zeros_like(d)
        if half is Half.RIGHT:
            R, t = self._pose()
            origins[:] = -R.T @ t
            d = d @ R
        status = np.where(converged, Status.OK, Status.NOT_CONVERGED).astype(STATUS_DTYPE)
        return origins, d, status


def rational_start(ctx, base):
    """The refined pinhole pair, its first radial term moved to the denominator
    (``1 + k1 r^2 ~ 1 / (1 - k1 r^2)``), and its poses."""
    cls = RationalPinholeModel
    values = base.model.named_params()
    for h in ("left", "right"):
        values[f"{h}_k4"] = -values.pop(f"{h}_k1")
    params = [values.get(name, 0.0) if name not in cls.DEFAULT_FIXED else 0.0
              for name in cls.PARAM_NAMES]  # fmt: skip
    model = cls(np.array(params), ctx.config)
    return Start(model, base.rvecs, base.tvecs, "the pinhole pair as a rational lens")


def rational_truth() -> RationalPinholeModel:
    pinhole = make_pinhole_model().named_params()
    values = {**pinhole, "left_k4": 0.08, "right_k4": 0.05}
    values.update({f"{h}_{k}": 0.0 for h in ("left", "right") for k in ("k1", "k2", "k3")})
    params = np.array([values.get(n, 0.0) for n in RationalPinholeModel.PARAM_NAMES])
    return RationalPinholeModel(params, make_pinhole_model().config)


@pytest.fixture(scope="module")
def registered():
    register_model(RationalPinholeModel, rational_start)
    yield RationalPinholeModel
    unregister_model(RationalPinholeModel.NAME)


def test_the_third_model_projects_like_opencv(registered, rng):
    import cv2

    truth = rational_truth()
    P = np.stack([rng.uniform(-4, 4, 200), rng.uniform(-3, 3, 200), rng.uniform(10, 40, 200)], -1)
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = truth._intrinsics(Half.LEFT)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K,
                               np.array([k1, k2, p1, p2, k3, k4, k5, k6]))  # fmt: skip
    got = truth.project(P, "left")
    ok = got.status == Status.OK
    assert ok.sum() > 100
    np.testing.assert_allclose(got.pixels[ok], ref.reshape(-1, 2)[ok], atol=OPENCV_TOL_PX)


def test_the_third_model_is_calibrated_through_its_own_start(registered, rng):
    truth = rational_truth()
    data = synthetic_views(truth, rng, n_images=14)
    res = calibrate(registered.NAME, data.views, data.boards, (640, 480), 320)
    assert res.model.NAME == registered.NAME
    assert res.start.startswith("the pinhole pair as a rational lens, via")
    assert res.rms < EXACT_RMS_PX
    for name in res.free_names:
        expected = getattr(truth, name)
        assert getattr(res.model, name) == pytest.approx(
            expected, rel=EXACT_PARAM_REL, abs=EXACT_PARAM_REL
        ), name
    assert "left_k4" in res.free_names and np.all(np.isfinite(res.std))


def test_registration_is_checked(registered):
    assert MODELS[registered.NAME] is registered
    with pytest.raises(ValueError, match="already registered"):
        register_model(type("Other", (registered,), {}), rational_start)


# ----- the whole pipeline, through the command line ---------------------------------------

TEST_DEPTHS_MM = (12.0, 16.0, 20.0, 24.0)
CALIB_NOISE_PX = 0.05
BOARD_TEST_REL_PERCENT = 1.0  # segments and areas (noisy calibration, exact test corners)


@pytest.fixture(scope="module")
def session(registered, tmp_path_factory):
    from tests.pipeline.measure_data import BOARD, BOARD_COLS, BOARD_ROWS, SQUARE_MM, board_points
    from tests.solvers.calibration_data import BOARD_COLS as CAL_COLS
    from tests.solvers.calibration_data import BOARD_ROWS as CAL_ROWS

    from endomeasure.io.session import Detection, ImageRecord, edit_session

    truth = rational_truth()
    data = synthetic_views(truth, np.random.default_rng(5), n_images=14, noise_px=CALIB_NOISE_PX)
    path = tmp_path_factory.mktemp("third") / "probe.h5"
    blank = np.zeros((480, 640), dtype=np.uint8)
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(640, 480), split=320)
        specs = {k: f"chessboard:{CAL_COLS}x{CAL_ROWS}:{k.removeprefix('sq')}" for k in data.boards}
        for spec in specs.values():
            w.write_board(spec, spec)
        w.write_board(
            BOARD, BOARD, {"cols": BOARD_COLS, "rows": BOARD_ROWS, "square_mm": SQUARE_MM}
        )
        dets = [
            Detection(v.name, specs[v.board], h, v.ids[h].astype(np.int32), v.pixels[h], 1.0, "")
            for v in data.views
            for h in Half
        ]
        records = []
        for depth in TEST_DEPTHS_MM:
            name = f"test_{depth:04.1f}"
            p = board_points(depth)
            records.append(ImageRecord(name, blank, f"{name}.png", "0" * 64, "test"))
            for h in Half:
                q = truth.project(p, h)
                assert np.all(q.status == Status.OK)
                ids = np.arange(p.shape[0], dtype=np.int32)
                dets.append(Detection(name, BOARD, h, ids, q.pixels, 1.0, ""))
        w.write_images(records)
        w.write_detections(dets)
    return path


def _run(*args):
    import json

    from typer.testing import CliRunner

    from endomeasure import cli

    result = CliRunner().invoke(cli.app, [*map(str, args), "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_the_third_model_goes_through_calibrate_board_test_and_predict_error(registered, session):
    name = registered.NAME
    calibration = _run("calibrate", session, "--model", name)
    assert calibration["models"][name]["residual_sigma_px"] == pytest.approx(
        CALIB_NOISE_PX, rel=0.15
    )
    board = _run("measure", session, "--board-test", "--model", name)
    relative = [r["relative_mean_percent"] for r in board["summary"] if r["model"] == name]
    relative = [r for r in relative if r is not None]  # segments and areas
    assert len(relative) >= 6
    assert max(abs(r) for r in relative) < BOARD_TEST_REL_PERCENT
    predicted = _run("predict-error", session, "--board-test", "--model", name)
    assert predicted["model"] == name and predicted["calibration"]
    assert len(predicted["zones"]) >= 6
    for row in predicted["zones"]:
        assert row["predicted_std"] > 0 and row["predicted_std_calibration"] > 0, row
