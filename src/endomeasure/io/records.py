"""The content of what the commands store: codecs between results and session records.

``docs/session-format.md`` specifies the file; :mod:`endomeasure.io.session` reads and
writes its groups. This module defines what ``calibrate`` stores in ``models/<name>``
(section 3.5) and the record kinds ``measurement``, ``board_test`` and ``prediction``
(section 3.6), in one place. The codecs take results by their attributes and return
plain values (arrays, dicts, camera models), so ``io`` needs no part above ``models``.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.io.session import ModelRecord, Record

__all__ = [
    "BOARD_TEST_RECORD",
    "board_attrs",
    "MEASUREMENT_RECORD",
    "PREDICTION_RECORD",
    "CalibratedModel",
    "StoredMeasurement",
    "board_prediction_record",
    "board_test_fields",
    "board_test_record",
    "calibration_extras",
    "calibration_record",
    "check_usable",
    "stored_verdict",
    "load_calibrated_model",
    "measurement_prediction_record",
    "measurement_record",
    "model_from_record",
    "next_measurement_name",
    "stored_measurement",
    "SURFACE_RECORD",
    "surface_record",
    "surface_record_name",
    "PROFILE_RECORD",
    "next_profile_name",
    "profile_record",
]

MEASUREMENT_RECORD = "measurement"
BOARD_TEST_RECORD = "board_test"
PREDICTION_RECORD = "prediction"
_MEASUREMENT_NAME = re.compile(r"^m(\d+)$")


# ----- models written by `calibrate` ------------------------------------------------------------


def calibration_record(result, name: str | None = None) -> ModelRecord:
    """The ``models/<name>`` entry of a calibration result (``CalibrationResult``)."""
    model = result.model
    arrays = {
        "free_names": np.array(result.free_names, dtype=object),
        "free_units": np.array([model.unit(n) for n in result.free_names], dtype=object),
        "covariance": result.covariance,
        "correlation": result.correlation,
        "std": result.std,
        "rvecs": result.rvecs,
        "tvecs": result.tvecs,
        "image_names": np.array(result.image_names, dtype=object),
        "image_boards": np.array(result.image_boards, dtype=object),
        "obs_image": result.obs_image.astype(np.int32),
        "obs_half": result.obs_half.astype(np.int8),
        "obs_ids": result.obs_ids.astype(np.int32),
        "obs_board_points": result.obs_board_points,
        "obs_pixels": result.obs_pixels,
        "residuals": result.residuals,
        "inliers": result.inliers.astype(np.uint8),
        "rms_image": result.rms_image,
        "rms_image_half": result.rms_image_half,
        "rms_half": result.rms_half,
    }
    if result.obs_covariance is not None:
        arrays["obs_covariance"] = result.obs_covariance
    if result.uncertainty_covariance is not None:
        arrays["uncertainty_covariance"] = result.uncertainty_covariance
    attrs = {
        "kind": "calibration",
        "rms": result.rms,
        "residual_variance": result.residual_variance,
        "status": result.status,
        "message": result.message,
        "nfev": result.nfev,
        "rounds": result.rounds,
        "n_outliers": result.outlier_count,
        "outlier_threshold_px": result.outlier_threshold_px,
        "start": result.start,
        "skipped_images": list(result.skipped_images),
        "extensions": list(result.extensions),
        "selection": list(result.selection),
        "uncertain": list(result.uncertain),
    }
    verdict = result.verdict
    if verdict is not None:
        attrs.update(
            verdict=verdict.level,
            verdict_reasons=list(verdict.reasons),
            noise_floor_px=verdict.floor_px,
            formal_floor_px=verdict.formal_px,
            scatter_floor_px=verdict.scatter_px,
            rms_ratio=verdict.rms_ratio,
        )
    units = {
        "noise_floor_px": "px",
        "formal_floor_px": "px",
        "scatter_floor_px": "px",
        "obs_covariance": "px^2",
        "rms": "px",
        "residual_variance": "px^2",
        "outlier_threshold_px": "px",
        "rvecs": "rad",
        "tvecs": "mm",
        "obs_board_points": "mm",
        "obs_pixels": "px",
        "residuals": "px",
        "rms_image": "px",
        "rms_image_half": "px",
        "rms_half": "px",
        "covariance": "parameter units squared (see free_units)",
    }
    return ModelRecord(
        name=name or model.NAME,
        registry_name=model.NAME,
        params=np.array(model.params),
        param_names=tuple(model.PARAM_NAMES),
        config=model.config.to_dict(),
        arrays=arrays,
        attrs=attrs,
        units=units,
    )


def model_from_record(record: ModelRecord):
    """The camera model of a stored model entry (registry name, parameters, config)."""
    from endomeasure.io.image_header import checked_image_size
    from endomeasure.models import model_from_dict

    try:
        model = model_from_dict(
            {
                "model": record.registry_name,
                "param_names": list(record.param_names),
                "params": np.asarray(record.params).tolist(),
                "config": record.config,
            }
        )
    except (KeyError, ValueError, TypeError) as exc:
        raise BadInputError(f"stored model {record.name!r} cannot be read: {exc}") from None
    size = model.config.image_size
    try:  # a crafted size would make every image-sized grid of the model unbounded
        checked_image_size(size, f"model {record.name!r}")
    except BadInputError:
        raise BadInputError(
            f"stored model {record.name!r} declares an image of {size[0]}x{size[1]} px, "
            "beyond the limits",
            hint="the session is damaged or crafted; recalibrate",
        ) from None
    return model


def _stored_covariance(record: ModelRecord) -> tuple[list[str], np.ndarray] | None:
    if "covariance" not in record.arrays or "free_names" not in record.arrays:
        return None
    names = [str(n) for n in record.arrays["free_names"]]
    return names, np.asarray(record.arrays["covariance"], dtype=np.float64)


def calibration_extras(record: ModelRecord) -> dict[str, Any] | None:
    """The calibration figures an exported model file carries (None without a covariance)."""
    stored = _stored_covariance(record)
    if stored is None:
        return None
    names, cov = stored
    units = record.arrays.get("free_units")
    return {
        "free_names": names,
        **({} if units is None else {"free_units": [str(u) for u in units]}),
        "std": np.sqrt(np.diag(cov)).tolist(),
        "covariance": cov.tolist(),
        "rms_px": float(record.attrs.get("rms", float("nan"))),
        "rms_half_px": np.asarray(record.arrays.get("rms_half", [])).tolist(),
        "residual_variance_px2": float(record.attrs.get("residual_variance", float("nan"))),
        **_uncertainty_extras(record),
    }


def _uncertainty_extras(record: ModelRecord) -> dict[str, Any]:
    """The held extensions a measurement's covariance also varies, and that covariance
    (:attr:`CalibrationResult.uncertain`), where the record has them."""
    if "uncertainty_covariance" not in record.arrays:
        return {}
    names = np.asarray(record.attrs.get("uncertain", []), dtype=object).reshape(-1)
    cov = np.asarray(record.arrays["uncertainty_covariance"], dtype=np.float64)
    return {"uncertain": [str(n) for n in names], "uncertainty_covariance": cov.tolist()}


@dataclasses.dataclass(frozen=True)
class CalibratedModel:
    """A model stored by ``calibrate`` with what the uncertainty of a measurement needs.

    Attributes
    ----------
    name : str
    model : CameraModel
        The fitted model; the extensions the fit held but cannot rule out
        (:attr:`~endomeasure.solvers.calibrate.CalibrationResult.uncertain`) count as
        free, so that ``param_cov`` varies them too.
    param_cov : ndarray, shape (F, F) or None
        Covariance of the free parameters, in the model's ``free_mask`` order.
    sigma_px : float or None
        Image noise estimated from the calibration residuals (``sqrt(SSR / dof)`` per
        coordinate), px.
    depth_range_mm : (float, float) or None
        Nearest and farthest depth of the calibration's inlier corners in the model
        frame, mm: where the calibration has seen the board.
    verdict : str
        The calibration's verdict (``ok``, ``warning``, ``failed``; ``unjudged`` for
        models stored without one, e.g. by an earlier version).
    misfit : ModelMisfit or None
        What the calibration's residuals hold beyond noise
        (:func:`~endomeasure.solvers.misfit.fit_misfit`): None here; the pipeline's
        :func:`~endomeasure.pipeline.calibrated_model` measures it from
        :func:`inlier_residuals`.
    """

    name: str
    model: Any
    param_cov: np.ndarray | None
    sigma_px: float | None
    depth_range_mm: tuple[float, float] | None = None
    verdict: str = "unjudged"
    misfit: Any = None


def stored_verdict(record: ModelRecord) -> tuple[str, list[str]]:
    """The verdict of a stored model and its reasons (``unjudged`` without one)."""
    reasons = record.attrs.get("verdict_reasons", [])
    reasons = [str(r) for r in (reasons if isinstance(reasons, (list, tuple)) else [reasons])]
    return str(record.attrs.get("verdict", "unjudged")), reasons


def check_usable(record: ModelRecord, session: str | Path) -> None:
    """Refuse a model whose calibration failed its verdict (BadInputError)."""
    level, reasons = stored_verdict(record)
    if level == "failed":
        why = reasons[0] if reasons else "see `endomeasure info`"
        raise BadInputError(
            f"the {record.name!r} calibration failed ({why}): it is not usable for measurements",
            path=str(session),
            hint="recalibrate with more or better images, or use another model",
        )


def load_calibrated_model(
    reader, name: str, session: str | Path, *, allow_failed: bool = False
) -> CalibratedModel:
    """The model ``name`` of an open session, with its covariance and residual sigma.

    A model the session does not hold, or whose calibration failed (unless
    ``allow_failed``, for diagnostics such as the board test), is a
    :class:`BadInputError` naming what to do.
    """
    return calibrated_from_record(
        stored_model_record(reader, name, session), session, allow_failed=allow_failed
    )


def stored_model_record(reader, name: str, session: str | Path) -> ModelRecord:
    """The record of model ``name`` of an open session; one the session does not hold is
    a :class:`BadInputError` naming what to do."""
    names = reader.model_names()
    if name not in names:
        from endomeasure.models import MODELS

        held = ", ".join(names) if names else "none"
        if name in MODELS:
            hint = f"run `endomeasure calibrate {session} --model {name}` first"
        elif names:
            hint = f"give --model one of the stored models: {held}"
        else:  # an unknown name: suggest what can be calibrated, not the name itself
            hint = f"calibrate one of the models {', '.join(MODELS)} first"
        raise BadInputError(
            f"the session has no calibrated {name!r} model (it holds: {held})",
            path=str(session),
            hint=hint,
        )
    return reader.model(name)


def calibrated_from_record(
    record: ModelRecord, session: str | Path, *, allow_failed: bool = False
) -> CalibratedModel:
    """:func:`load_calibrated_model` of a record already read."""
    name = record.name
    if not allow_failed:
        check_usable(record, session)
    model = model_from_record(record)
    cov = None
    stored = _stored_covariance(record)
    if stored is not None and "uncertainty_covariance" in record.arrays:
        model = _uncertainty_model(record, model, session)
        free = [model.PARAM_NAMES[i] for i in np.flatnonzero(model.free_mask)]
        stored = free, np.asarray(record.arrays["uncertainty_covariance"], dtype=np.float64)
    if stored is not None:
        stored_names, c = stored
        free = [model.PARAM_NAMES[i] for i in np.flatnonzero(model.free_mask)]
        if sorted(stored_names) != sorted(free) or c.shape != (len(free), len(free)):
            raise BadInputError(
                f"the stored covariance of model {name!r} does not match its free parameters",
                path=str(session),
                hint=f"re-run `endomeasure calibrate {session} --model {name}`",
            )
        order = [stored_names.index(n) for n in free]
        cov = c[np.ix_(order, order)]
    variance = record.attrs.get("residual_variance")
    if variance is not None and not isinstance(variance, (int, float)):
        raise BadInputError(
            f"the stored residual variance of model {name!r} is not a number "
            f"({type(variance).__name__})",
            path=str(session),
            hint=f"the session is damaged or crafted; re-run `endomeasure calibrate {session}`",
        )
    sigma = (
        float(np.sqrt(variance))
        if variance is not None and np.isfinite(variance) and variance > 0
        else None
    )
    return CalibratedModel(
        name, model, cov, sigma, _calibration_depths(record), stored_verdict(record)[0]
    )


def _uncertainty_model(record: ModelRecord, model, session: str | Path):
    """The stored model with the extensions its fit held but its
    ``uncertainty_covariance`` holds (attribute ``uncertain``,
    :attr:`CalibrationResult.uncertain`) counted as free, so that its ``free_mask`` is
    that covariance's order."""
    held = np.asarray(record.attrs.get("uncertain", []), dtype=object)
    names = [str(n) for n in held.reshape(-1)]
    unknown = sorted(set(names) - set(model.PARAM_NAMES))
    if unknown:
        raise BadInputError(
            f"the stored model {record.name!r} names unknown uncertain parameters {unknown}",
            path=str(session),
            hint=f"the session is damaged or crafted; re-run `endomeasure calibrate {session}`",
        )
    return model.with_config(fixed=model.config.fixed - set(names)) if names else model


_RESIDUAL_ARRAYS = ("obs_board_points", "obs_image", "obs_half", "obs_pixels", "residuals")


def inlier_residuals(record: ModelRecord) -> tuple[np.ndarray, ...] | None:
    """``(board_points, image, half, pixels, residuals)`` of a calibration record's inlier
    corners, or None for a record stored without them."""
    a = record.arrays
    if not all(k in a for k in _RESIDUAL_ARRAYS):
        return None
    use = np.asarray(a["inliers"]).astype(bool) if "inliers" in a else slice(None)
    return tuple(np.asarray(a[k])[use] for k in _RESIDUAL_ARRAYS)


def _calibration_depths(record: ModelRecord) -> tuple[float, float] | None:
    """Depth range (mm) of the inlier corners a calibration record holds, if it holds them."""
    from endomeasure.geometry.rotations import rotation_matrix

    a = record.arrays
    if not all(k in a for k in ("rvecs", "tvecs", "obs_image", "obs_board_points")):
        return None
    image = np.asarray(a["obs_image"], dtype=np.int64)
    rvecs, tvecs = np.asarray(a["rvecs"]), np.asarray(a["tvecs"])
    X = np.asarray(a["obs_board_points"], dtype=np.float64)
    z = np.einsum("nj,nj->n", rotation_matrix(rvecs)[image][:, 2], X) + tvecs[image, 2]
    if "inliers" in a:
        z = z[np.asarray(a["inliers"]).astype(bool)]
    z = z[np.isfinite(z)]
    return (float(z.min()), float(z.max())) if z.size else None


# ----- measurement records ----------------------------------------------------------------------


def next_measurement_name(names: Sequence[str]) -> str:
    """The next free measurement id: ``m001``, ``m002``, ..."""
    numbers = [int(m.group(1)) for n in names if (m := _MEASUREMENT_NAME.match(n))]
    return f"m{max(numbers, default=0) + 1:03d}"


def _match_arrays(matches, noise) -> dict[str, np.ndarray]:
    """What a measurement keeps of an automatic search (nothing without one), with the
    per-point image noise (``pixel_std``) of ``noise`` when it has one."""
    if matches is None:
        return {}
    out = {
        "match_query_half": np.array([m.half.label for m in matches], dtype=object),
        "match_score": np.array([m.score for m in matches]),
        "match_precision": np.array([m.precision_px for m in matches]),
    }
    if noise.pixel_std is not None:
        out["pixel_std"] = np.asarray(noise.pixel_std, dtype=np.float64)
    return out


def measurement_record(name: str, report) -> Record:
    """The ``measurement`` record of a ``measure`` report (its points and predicted error;
    for a matched measurement also its per-point input noise, ``pixel_std`` (n, 2), px)."""
    points = report.points
    matches = report.matches or None
    e, unit = report.error, report.unit
    return Record(
        MEASUREMENT_RECORD,
        name,
        attrs={
            "model": report.model,
            "image": report.image,
            "measurement_kind": report.kind,
            "value": e.value,
            "bias": e.bias,
            "std": e.std,
            "std_image": e.std_image,
            "std_calibration": e.std_calibration,
            "std_model": e.std_model,
            "ci95": e.ci95,
            "relative_percent": e.relative_percent,
            "warn_percent": float(report.warn_percent),
            "warning": report.warning,
            **report.noise.to_dict(correlations=False),
            "method": report.method,
            **({} if report.plane is None else {"modifier": "plane"}),
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        },
        arrays={
            "pixels_left": np.array([p.left for p in points], dtype=np.float64),
            "pixels_right": np.array([p.right for p in points], dtype=np.float64),
            "points": np.array([p.xyz for p in points], dtype=np.float64),
            "ray_gap": np.array([p.gap_mm for p in points], dtype=np.float64),
            "reprojection_rms": np.array([p.rms_px for p in points], dtype=np.float64),
            **_match_arrays(matches, report.noise),
            **_plane_arrays(report),
        },
        units={
            **dict.fromkeys(
                ("value", "bias", "std", "std_image", "std_calibration", "std_model", "ci95"), unit
            ),
            "relative_percent": "%",
            "warn_percent": "%",
            "sigma_px": "px",
            "pixels_left": "px",
            "pixels_right": "px",
            "points": "mm",
            "ray_gap": "mm",
            "reprojection_rms": "px",
            **({} if matches is None and report.plane is None else {"pixel_std": "px"}),
            **(
                {}
                if report.plane is None
                else {"plane_pixels_left": "px", "plane_pixels_right": "px", "plane_points": "mm"}
            ),
        },
    )


def _plane_arrays(report) -> dict[str, np.ndarray]:
    """What a ``--plane`` measurement adds (nothing without one): which points were
    placed on the plane, the plane's points, and the per-point image noise (``u_L, v_L,
    u_R, v_R``) of the plane's points followed by the measured ones."""
    if report.plane is None:
        return {}
    plane = report.plane
    return {
        "projected": np.array([p.projected for p in report.points], dtype=np.uint8),
        "plane_pixels_left": np.array([p.left for p in plane], dtype=np.float64),
        "plane_pixels_right": np.array([p.right for p in plane], dtype=np.float64),
        "plane_points": np.array([p.xyz for p in plane], dtype=np.float64),
        "pixel_std": np.asarray(report.noise.pixel_std, dtype=np.float64),
    }


class StoredMeasurement(NamedTuple):
    """What a prediction needs of a stored measurement."""

    model: str
    kind: str
    pixels_left: np.ndarray  # (n, 2) px; with a plane, its 3 points first
    pixels_right: np.ndarray  # (n, 2) px; NaN for the points placed on the plane
    plane: bool = False  # a ``--plane`` measurement


def stored_measurement(record: Record) -> StoredMeasurement:
    """The model, kind and pixels of a ``measurement`` record (for a ``--plane`` one,
    the plane's points first, as :func:`~endomeasure.measure.predict.
    predict_measurement_error` takes them with ``plane=True``)."""
    a = record.arrays
    plane = record.attrs.get("modifier") == "plane"
    left, right = a["pixels_left"], a["pixels_right"]
    if plane:
        left = np.vstack([a["plane_pixels_left"], left])
        right = np.vstack([a["plane_pixels_right"], right])
    return StoredMeasurement(
        str(record.attrs["model"]), str(record.attrs["measurement_kind"]), left, right, plane
    )


# ----- board-test records -----------------------------------------------------------------------

_BOARD_TEST_UNITS = {
    "zone_mm": "mm",
    "image_square_mm": "mm",
    "corner_left": "px",
    "corner_right": "px",
    "corner_xyz": "mm",
    "corner_gap": "mm",
    "corner_rms": "px",
    "row_true": "mm or mm^2 (area)",
    "row_measured": "mm or mm^2 (area)",
    "row_error": "mm or mm^2 (area)",
    "row_z_mean": "mm",
    "row_pixel_mean": "px",
    "zone_start": "mm",
    "zone_end": "mm",
    "zone_mean_error": "mm or mm^2 (area)",
    "zone_std_error": "mm or mm^2 (area)",
    "zone_true": "mm or mm^2 (area)",
}


def board_test_record(bt, zone_mm: float) -> Record:
    """The ``board_test`` record of one model's board test (a ``ModelBoardTest``)."""
    t, s = bt.table, bt.summary
    return Record(
        BOARD_TEST_RECORD,
        bt.model,
        attrs={"model": bt.model, "zone_mm": float(zone_mm), "n_images": len(bt.images)},
        arrays={
            "images": np.array(bt.images, dtype=object),
            "image_board": np.array(bt.board, dtype=object),
            "image_square_mm": np.array(bt.square_mm),
            "corner_image": bt.corner_image.astype(np.int32),
            "corner_id": bt.corner_id.astype(np.int32),
            "corner_left": bt.corner_left,
            "corner_right": bt.corner_right,
            "corner_xyz": bt.corner_xyz,
            "corner_gap": bt.corner_gap,
            "corner_rms": bt.corner_rms,
            "corner_status": bt.corner_status,
            "row_image": t.image.astype(np.int32),
            "row_kind": np.array(t.kind, dtype=object),
            "row_corners": t.corners.astype(np.int32),
            "row_true": t.true,
            "row_measured": t.measured,
            "row_error": t.error,
            "row_z_mean": t.z_mean,
            "row_pixel_mean": t.pixel_mean,
            "zone_board": np.array(bt.summary_board, dtype=object),
            "zone_kind": np.array(s.kind, dtype=object),
            "zone_start": s.zone_start,
            "zone_end": s.zone_end,
            "zone_n": s.n,
            "zone_mean_error": s.mean_error,
            "zone_std_error": s.std_error,
            "zone_true": s.true,
        },
        units=dict(_BOARD_TEST_UNITS),
    )


def board_test_fields(record: Record) -> dict[str, Any]:
    """A ``board_test`` record as plain values: the fields of ``ModelBoardTest``, with
    ``table`` and ``summary`` as dicts of the ``BoardTestTable`` / ``ZoneSummary`` columns."""
    a, model = record.arrays, record.name
    kind = np.asarray(a["zone_kind"]).astype(str)
    return {
        "model": model,
        "board": [str(b) for b in a["image_board"]],
        "images": [str(i) for i in a["images"]],
        "square_mm": [float(s) for s in a["image_square_mm"]],
        "corner_image": a["corner_image"].astype(np.int64),
        "corner_id": a["corner_id"].astype(np.int64),
        "corner_left": a["corner_left"],
        "corner_right": a["corner_right"],
        "corner_xyz": a["corner_xyz"],
        "corner_gap": a["corner_gap"],
        "corner_rms": a["corner_rms"],
        "corner_status": a["corner_status"].astype(np.uint8),
        "table": {
            "image": a["row_image"].astype(np.int64),
            "kind": np.asarray(a["row_kind"]).astype(str),
            "corners": a["row_corners"].astype(np.int64),
            "true": a["row_true"],
            "measured": a["row_measured"],
            "error": a["row_error"],
            "z_mean": a["row_z_mean"],
            "pixel_mean": a["row_pixel_mean"],
        },
        "summary": {
            "model": np.full(kind.shape[0], model).astype(str),
            "kind": kind,
            "zone_start": a["zone_start"],
            "zone_end": a["zone_end"],
            "n": a["zone_n"].astype(np.int64),
            "mean_error": a["zone_mean_error"],
            "std_error": a["zone_std_error"],
            "true": a["zone_true"],
        },
        "summary_board": np.asarray(a["zone_board"]).astype(str),
    }


# ----- prediction records -----------------------------------------------------------------------


_PREDICTED_ROW_ARRAYS = ("bias", "std", "std_image", "std_calibration", "std_model", "value")
"""The arrays of a board-test prediction record, one entry per board-test row."""


def board_prediction_record(report) -> Record:
    """The ``prediction`` record ``board-test-<model>`` of a ``BoardPredictionReport``."""
    return Record(
        PREDICTION_RECORD,
        f"board-test-{report.model}",
        attrs={
            "mode": "board-test",
            "model": report.model,
            "method": report.method,
            **report.noise.to_dict(),
            "calibration": bool(report.calibration),
            "model_error": bool(report.model_error),
            "zone_mm": report.zone_mm,
            "within_band": report.within_band,
            "zones": json.dumps(report.zones),
        },
        # the predicted errors per board-test row (a PredictedErrors)
        arrays={k: getattr(report.rows, k) for k in _PREDICTED_ROW_ARRAYS},
        units={"sigma_px": "px", "zone_mm": "mm"},
    )


def measurement_prediction_record(report: Any, fields: Mapping[str, Any]) -> Record:
    """The ``prediction`` record ``<id>-<method>`` of a ``MeasurementPredictionReport``;
    ``fields``: the report as a flat dict (its JSON document)."""
    return Record(
        PREDICTION_RECORD,
        f"{report.measurement}-{report.method}",
        attrs={
            "mode": "measurement",
            **{("measurement_kind" if k == "kind" else k): v for k, v in fields.items()},
        },
        units={"sigma_px": "px", "relative_percent": "%"},
    )


def board_attrs(spec) -> tuple[dict[str, Any], dict[str, str]]:
    """The attributes a board is stored with (the parsed values of its spec, a
    ``features.boards`` board spec), and their units."""
    attrs: dict[str, Any] = {"kind": spec.kind, "cols": spec.cols, "rows": spec.rows}
    units = {"square_mm": "mm"}
    attrs["square_mm"] = spec.square_mm
    if spec.kind == "charuco":
        attrs.update(
            squares_x=spec.squares_x,
            squares_y=spec.squares_y,
            marker_mm=spec.marker_mm,
            dictionary=spec.dictionary,
        )
        units["marker_mm"] = "mm"
    return attrs, units


# ----- dense surfaces written by `surface` ---------------------------------------------------

SURFACE_RECORD = "surface"


def surface_record_name(image: str, model: str) -> str:
    """The ``surface`` record of an image and model: one per pair, replaced on rerun."""
    return f"{image}.{model}"


def surface_record(
    name: str, surface, *, image: str, model: str, attrs: Mapping[str, Any]
) -> Record:
    """The ``records/surface/<name>`` entry of a dense surface (``DenseSurface``).

    Arrays over the region's rows and columns: ``depth`` and ``sigma_depth`` (float32,
    mm, NaN without depth), ``status`` (uint8, ``DenseStatus``), ``score`` (ZNCC,
    float32), ``right`` (matched right pixel, float32, px), ``window`` (uint16, side of the
    window the depth comes from, px; 0 without depth), ``prefilter`` (float32, sigma of the
    Gaussian that prefiltered that window's halves, px; 0: none); ``region`` (u0, v0, u1,
    v1).
    """
    arrays = {
        "region": np.asarray(surface.region, dtype=np.int32),
        "depth": surface.depth.astype(np.float32),
        "sigma_depth": surface.sigma_depth.astype(np.float32),
        "status": surface.status.astype(np.uint8),
        "score": np.nan_to_num(surface.score, nan=-2.0).astype(np.float32),
        "right": surface.right.astype(np.float32),
        "window": surface.window.astype(np.uint16),
        "prefilter": surface.prefilter.astype(np.float32),
    }
    units = {"depth": "mm", "sigma_depth": "mm", "right": "px", "region": "px", "window": "px",
             "prefilter": "px"}  # fmt: skip
    return Record(
        SURFACE_RECORD,
        name,
        attrs={"image": image, "model": model, **dict(attrs)},
        arrays=arrays,
        units=units,
    )


# ----- depth profiles written by `measure --kind profile | area-profile` -----------------------

PROFILE_RECORD = "profile"
_PROFILE_NAME = re.compile(r"^p(\d+)$")


def next_profile_name(names: Sequence[str]) -> str:
    """The next free profile id: ``p001``, ``p002``, ..."""
    numbers = [int(m.group(1)) for n in names if (m := _PROFILE_NAME.match(n))]
    return f"p{max(numbers, default=0) + 1:03d}"


def profile_record(name: str, report) -> Record:
    """The ``records/profile/<name>`` entry of a profile report (``ProfileReport``).

    Attributes: ``model``, ``image``, ``measurement_kind`` (``profile`` or
    ``area-profile``), the extreme (``extreme_height``, ``extreme_sigma``,
    ``extreme_position``, ``extreme_slice``, ``extreme_at_gap``), the deepest and highest
    of the extreme slice, the plane (``plane_source``, ``plane_points``,
    ``plane_rejected``, ``plane_rms``), ``created``. Arrays, over all samples of all
    slices in order: ``sample_slice`` (int32), ``sample_pixel`` (n, 2) px,
    ``sample_status`` (uint8, the dense status), ``sample_height``, ``sample_sigma``
    (mm, NaN in gaps; + towards the probe), ``sample_position`` (mm along the path in
    the plane), ``sample_position_px``; ``left_px`` the operator's points; ``plane_origin``
    (3,) mm, ``plane_normal`` (3,), ``plane_cov`` (3, 3) of its two tilts (1) and offset
    (mm); with reference points ``ref_left_px``, ``ref_right_px``, ``ref_points`` (mm).
    """
    profiles = report.profiles
    e = report.extreme
    best = profiles[report.extreme_slice]
    plane = report.plane

    def cat(field):
        return np.concatenate([np.asarray(getattr(p.samples, field)) for p in profiles])

    arrays = {
        "left_px": np.asarray(report.left, dtype=np.float64),
        "sample_slice": np.concatenate(
            [np.full(p.samples.height.size, k, dtype=np.int32) for k, p in enumerate(profiles)]
        ),
        "sample_pixel": cat("pixels").astype(np.float64),
        "sample_status": cat("status").astype(np.uint8),
        "sample_height": cat("height"),
        "sample_sigma": cat("sigma"),
        "sample_position": cat("position_mm"),
        "sample_position_px": cat("position_px"),
        "plane_origin": np.asarray(plane.origin, dtype=np.float64),
        "plane_normal": np.asarray(plane.normal, dtype=np.float64),
        "plane_cov": np.asarray(plane.cov, dtype=np.float64),
    }
    if report.refs:
        arrays["ref_left_px"] = np.array([r["left_px"] for r in report.refs])
        arrays["ref_right_px"] = np.array([r["right_px"] for r in report.refs])
        arrays["ref_points"] = np.array([r["xyz_mm"] for r in report.refs])
    attrs = {
        "model": report.model,
        "image": report.image,
        "measurement_kind": report.kind,
        "extreme_height": e.height_mm,
        "extreme_sigma": e.sigma_mm,
        "extreme_position": e.position_mm,
        "extreme_slice": int(report.extreme_slice),
        "extreme_at_gap": bool(e.at_gap),
        "deepest_height": best.deepest.height_mm,
        "deepest_sigma": best.deepest.sigma_mm,
        "highest_height": best.highest.height_mm,
        "highest_sigma": best.highest.sigma_mm,
        "coverage": float(np.mean([p.coverage for p in profiles])),
        "plane_source": plane.source,
        "plane_points": int(plane.points),
        "plane_rejected": int(plane.rejected),
        "plane_rms": float(plane.rms_mm),
        "region": list(report.region),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    mm = ("extreme_height", "extreme_sigma", "extreme_position", "deepest_height",
          "deepest_sigma", "highest_height", "highest_sigma", "plane_rms", "sample_height",
          "sample_sigma", "sample_position", "plane_origin", "ref_points")  # fmt: skip
    units = {k: "mm" for k in mm if k in attrs or k in arrays}
    units.update({k: "px" for k in ("left_px", "sample_pixel", "sample_position_px",
                                    "ref_left_px", "ref_right_px") if k in arrays})  # fmt: skip
    return Record(PROFILE_RECORD, name, attrs=attrs, arrays=arrays, units=units)
