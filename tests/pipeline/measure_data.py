"""Sessions for the measure / predict-error tests, built from a known model.

The session holds the model as if ``calibrate`` had stored it (parameters, a small
diagonal covariance of its free parameters, a residual variance), one blank scene
image and test images of a flat chessboard facing the probe at several distances whose
corners are the model's exact projections, optionally with seeded Gaussian noise. The
ground truth is the board geometry and the noise that was drawn, never the code under
test.
"""

from __future__ import annotations

import numpy as np
from tests.conftest import make_pinhole_model, make_raytrace_model

from endomeasure.conventions import Half, Status
from endomeasure.io.session import Detection, ImageRecord, ModelRecord, edit_session

BOARD_COLS, BOARD_ROWS, SQUARE_MM = 7, 5, 0.5
BOARD = f"chessboard:{BOARD_COLS}x{BOARD_ROWS}:{SQUARE_MM:g}"
DEPTHS_MM = (12.0, 14.0, 16.0, 18.0, 20.0, 22.0, 24.0, 26.0)
SIGMA_RECORD_PX = 0.05
"""Residual sigma stored with the models (the default image noise of predictions)."""
PARAM_STD_REL = 1e-5
"""Relative standard deviation of each free parameter in the stored covariance."""

FACTORIES = {"raytrace": make_raytrace_model, "pinhole": make_pinhole_model}


def board_points(depth: float, offset=(0.0, 0.0)) -> np.ndarray:
    """Board corners (N, 3), mm, in id order, centred on the axis at ``depth``."""
    row, col = np.divmod(np.arange(BOARD_ROWS * BOARD_COLS), BOARD_COLS)
    x = (col - (BOARD_COLS - 1) / 2) * SQUARE_MM + offset[0]
    y = (row - (BOARD_ROWS - 1) / 2) * SQUARE_MM + offset[1]
    return np.stack([x, y, np.full(x.shape, depth)], axis=-1)


def _misfit_residuals() -> dict[str, np.ndarray]:
    """Calibration residuals with a known misfit field (``tests/solvers/misfit_data.py``)."""
    from tests.solvers.misfit_data import board_residuals

    X, image, half, q, r = board_residuals(np.random.default_rng(0))
    return {
        "obs_board_points": X, "obs_image": image.astype(np.int32),
        "obs_half": half.astype(np.int8), "obs_pixels": q, "residuals": r,
        "inliers": np.ones(image.size, dtype=np.uint8),
    }  # fmt: skip


def model_record(name: str, model, misfit: bool = False) -> ModelRecord:
    """``model`` stored as ``calibrate`` would; with ``misfit``, with calibration
    residuals that hold a known misfit beyond their noise."""
    free = np.flatnonzero(model.free_mask)
    std = PARAM_STD_REL * np.maximum(np.abs(model.params[free]), 1.0)
    return ModelRecord(
        name,
        model.NAME,
        np.array(model.params),
        tuple(model.PARAM_NAMES),
        model.config.to_dict(),
        arrays={
            "free_names": np.array([model.PARAM_NAMES[i] for i in free], dtype=object),
            "covariance": np.diag(std**2),
            **(_misfit_residuals() if misfit else {}),
        },
        attrs={"residual_variance": SIGMA_RECORD_PX**2, "rms": SIGMA_RECORD_PX},
    )


def build_session(
    path, rng=None, noise_px=0.0, models=("raytrace",), offsets=((0.0, 0.0),), misfit=False
):
    """A session with the given models and test images of the board (see module doc);
    with ``misfit``, the models' calibration residuals hold a known misfit.

    ``noise_px``: the noise's sigma (px; a pair for u and v), or a function of the
    image's index and the half (0 left, 1 right) that returns it.

    Returns ``(path, truth)`` with ``truth[image] = points (N, 3)`` (in the frame of the
    first model).
    """
    model = FACTORIES[models[0]]()
    truth = {}
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(640, 480), split=320)
        w.write_board(
            BOARD, BOARD, {"cols": BOARD_COLS, "rows": BOARD_ROWS, "square_mm": SQUARE_MM}
        )
        blank = np.zeros((480, 640), dtype=np.uint8)
        records = [ImageRecord("scene", blank, "scene.png", "0" * 64, "scene")]
        dets = []
        for depth in DEPTHS_MM:
            for k, offset in enumerate(offsets):
                name = f"test_{depth:04.1f}_{k}"
                p = board_points(depth, offset)
                ql = model.project(p, "left")
                qr = model.project(p, "right")
                assert np.all(ql.status == Status.OK) and np.all(qr.status == Status.OK)
                records.append(ImageRecord(name, blank, f"{name}.png", "0" * 64, "test"))
                ids = np.arange(p.shape[0], dtype=np.int32)
                for j, (half, q) in enumerate(((Half.LEFT, ql.pixels), (Half.RIGHT, qr.pixels))):
                    sigma = noise_px(len(records) - 2, j) if callable(noise_px) else noise_px
                    noisy = q + (rng.normal(0.0, sigma, q.shape) if np.any(sigma) else 0.0)
                    dets.append(Detection(name, BOARD, half, ids, noisy, 1.0, ""))
                truth[name] = p
        w.write_images(records)
        w.write_detections(dets)
        for name in models:
            w.write_model(model_record(name, FACTORIES[name](), misfit))
    return path, truth


DISC_RADIUS_PX = 8
"""Radius of the constant-grey disc that masks a board corner (larger than the
corner's correlation patch, so no trace of the corner is left)."""


def masked_corners(image: np.ndarray, pixels) -> np.ndarray:
    """A copy of ``image`` with a disc of its median grey over each pixel (a missing
    corner, burnt-off edge or glare), for the measurement plane's checks."""
    import cv2

    out = image.copy()
    for q in pixels:
        centre = (int(round(q[0])), int(round(q[1])))
        cv2.circle(out, centre, DISC_RADIUS_PX, int(np.median(image)), -1)
    return out


def placed_position_std(session, report) -> np.ndarray:
    """The UT std (3,) mm of a ``--plane`` measurement's first placed point's x, y, z,
    with the image noise and the calibration covariance its +- used."""
    from endomeasure.io.session import open_session
    from endomeasure.measure.kinds import PLANE_POINTS
    from endomeasure.measure.predict import ImageNoise
    from endomeasure.pipeline import calibrated_model
    from endomeasure.solvers.uncertainty import MeasurementFunction, propagate

    with open_session(session) as reader:
        cm = calibrated_model(reader, report.model, session)
    pts = report.plane + report.points[:1]
    ql = np.array([p.left for p in pts])
    qr = np.where(np.isnan([p.right for p in pts]), ql, [p.right for p in pts])
    noise = ImageNoise.per_point(report.noise.pixel_std[: len(pts)], report.noise.source)
    cov, blocks = noise.covariance(len(pts), cm.param_cov)
    on_plane = np.arange(len(pts)) >= PLANE_POINTS
    std = []
    for k in range(3):
        f = MeasurementFunction(cm.model, lambda p, k=k: p[..., PLANE_POINTS, k], len(pts),
                                with_params=True, on_plane=on_plane)  # fmt: skip
        pred = propagate(f, f.inputs(ql[None], qr[None]), cov, "ut", blocks=blocks)
        std.append(float(pred.std[0]))
    return np.array(std)
