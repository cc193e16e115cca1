"""``endomeasure verify``: a quick check of a stored calibration with a few images of a
known board, without changing the session.

Load (the session read-only: its calibrated model, image size and split) -> read and
detect the board in both halves of every image
(:func:`endomeasure.features.detect.detect_split_image`) -> triangulate and measure every
segment and square (:func:`endomeasure.measure.board_runs.run_board_test`) -> predict
each measurement's bias and std at the ideal board's pixels, with each image's own
detection noise, the calibration covariance and the model misfit
(:func:`endomeasure.measure.board_runs.board_predictions`) -> the two tests and the
verdict of :mod:`endomeasure.measure.verify`. Nothing is stored.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure import defaults
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError

__all__ = ["VerifyReport", "verify_calibration"]

METHOD = "ut"
TEST_IMAGE_NOISE = "each image's noise from its neighbouring corners"
MAX_SCALE_ERROR = 0.2
"""Largest median relative length error ``verify`` judges as a calibration's: a probe's
baseline does not drift by a fifth, while a board of another pitch than the spec says
(common pitches differ by factors of 2 or more) is off by that much or more. Beyond it
the input is refused (exit 2) instead of judged."""


@dataclasses.dataclass(frozen=True)
class VerifyReport:
    """What ``verify`` found: the images used, the noise assumed and the statistics."""

    session: str
    model: str
    board: str
    images: list[str]
    corners: list[int]  # per image, corners seen in both halves
    noise: Any  # ImageNoise or ImageNoiseByImage
    statistics: Any  # VerifyStatistics
    calibration: bool  # the calibration covariance was propagated
    model_error: bool  # the calibration's model misfit was propagated

    @property
    def verdict(self) -> str:
        return self.statistics.verdict

    @property
    def passed(self) -> bool:
        return self.statistics.passed

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "model": self.model,
            "board": self.board,
            "images": [
                {"image": i, "corners": c} for i, c in zip(self.images, self.corners, strict=True)
            ],  # fmt: skip
            **self.noise.to_dict(),
            "method": METHOD,
            "calibration": self.calibration,
            "model_error": self.model_error,
            **self.statistics.to_dict(),
        }


def _detected(paths: Sequence[str | Path], spec, split: int, image_size) -> list:
    """The session's Detection of each half of each image; an image without the whole
    board in both halves is a BadInputError naming it and why."""
    from endomeasure.features.detect import detect_split_image
    from endomeasure.io.images import read_image_file
    from endomeasure.io.session import Detection

    detections = []
    for path in paths:
        record = read_image_file(path, "test", expected_size=image_size)
        found = detect_split_image(record.pixels, spec, split)
        for half in (Half.LEFT, Half.RIGHT):
            h = found.halves[half]
            if not h.ok:
                raise BadInputError(
                    f"no {spec.canonical()} board found in the {half.label} half ({h.failure})",
                    path=str(path),
                    hint="give images of the board the --board spec describes, seen whole "
                    "in both halves",
                )
            detections.append(Detection(str(path), spec.canonical(), half, h.ids, h.pixels))
    return detections


def _image_noise(bt, cm, grids):
    """Each image's own detection noise (as the board test's prediction measures it), or
    the calibration's residual sigma where the images have too few corners for it."""
    from endomeasure.measure.board_runs import measured_image_noise
    from endomeasure.measure.predict import image_noise

    measured = measured_image_noise(bt, cm.model, grids, TEST_IMAGE_NOISE)
    if measured is not None:
        return measured
    return image_noise(None, cm.sigma_px, f"model {cm.name!r}", misfit=cm.misfit)


def _check_pitch(table, spec) -> None:
    """Refuse images whose squares measure far from the spec's pitch (MAX_SCALE_ERROR)."""
    sel = np.isin(table.kind, ("x-segment", "y-segment")) & np.isfinite(table.error)
    if not sel.any():
        return
    measured = float(np.median(table.measured[sel]))
    if abs(measured / spec.square_mm - 1) > MAX_SCALE_ERROR:
        raise BadInputError(
            f"the squares measure {measured:.3g} mm, the board spec {spec.canonical()} says "
            f"{spec.square_mm:g} mm: another board, or a calibration of another probe",
            hint="give --board the spec of the board in the images",
        )


def verify_calibration(
    session: str | Path,
    images: Sequence[str | Path],
    board: str,
    model: str = "raytrace",
    *,
    alpha: float | None = None,
) -> VerifyReport:
    """Check the stored calibration ``model`` of ``session`` with images of ``board``.

    Parameters
    ----------
    session : path
        Opened read-only; nothing is written.
    images : sequence of path
        Image files (the session's size) showing the whole board in both halves, or
        directories of them.
    board : str
        Board spec (:func:`endomeasure.features.boards.parse_board_spec`).
    model : str
        A stored, usable calibrated model.
    alpha : float, optional
        Family-wise significance level (default
        :data:`endomeasure.measure.verify.VERIFY_ALPHA`).

    Returns
    -------
    VerifyReport
    """
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.io.images import find_image_files
    from endomeasure.io.records import board_attrs
    from endomeasure.io.session import open_session
    from endomeasure.measure.board_runs import board_predictions, board_sets, run_board_test
    from endomeasure.measure.verify import VERIFY_ALPHA, verify_statistics
    from endomeasure.pipeline import calibrated_model

    spec = parse_board_spec(board)
    images = find_image_files(images)
    if not images:
        raise BadInputError("verify needs at least one image of the board")
    names = [str(p) for p in images]
    if len(set(names)) != len(names):
        raise BadInputError("an image is given twice", hint="give each image once")
    with open_session(session) as reader:
        meta = reader.metadata()
        cm = calibrated_model(reader, model, session)
    detections = _detected(images, spec, meta.split, meta.image_size)
    attrs, _ = board_attrs(spec)
    sets = board_sets({spec.canonical(): attrs}, detections, names, str(session))
    bt = run_board_test(model, cm.model, sets, defaults.ZONE_MM)
    _check_pitch(bt.table, spec)
    grids = {spec.canonical(): np.asarray(spec.object_points)}
    noise = _image_noise(bt, cm, grids)
    pred = board_predictions(bt, cm.model, grids, noise, param_cov=cm.param_cov,
                             misfit=cm.misfit, method=METHOD)  # fmt: skip
    stats = verify_statistics(bt.table, pred, VERIFY_ALPHA if alpha is None else alpha)
    corners = [int(np.sum(bt.corner_image == k)) for k in range(len(bt.images))]
    return VerifyReport(
        str(session), model, spec.canonical(), list(bt.images), corners, noise, stats,
        cm.param_cov is not None, cm.misfit is not None and cm.misfit.present,
    )  # fmt: skip
