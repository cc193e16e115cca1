"""``endomeasure predict-error``: predicted measurement errors, in three modes.

SPEC section 8, the paper's Section 4.

- :func:`predict_board_test` — predicted bias and standard deviation of every board-test
  measurement (from the corners' detected pixels, the image noise with its correlations,
  and the calibration covariance), summarised per board, kind and zone next to the
  actual errors of the board test (the paper's Fig. 5;
  :func:`endomeasure.measure.board_runs.prediction_zones` says how they are compared);
- :func:`predict_stored_measurement` — the prediction of one stored measurement, again,
  with other noise assumptions or another method;
- :func:`predict_map` — the predicted error of a template measurement over a grid of the
  working volume, for a calibrated model or for a model file with nominal parameters
  (an adapter design on paper, no calibration covariance).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure import defaults
from endomeasure.errors import BadInputError

__all__ = [
    "DEFAULT_DEPTHS_MM",
    "BoardPredictionReport",
    "MapReport",
    "MeasurementPredictionReport",
    "NoiseAssumptions",
    "board_predictions",
    "predict_board_test",
    "predict_map",
    "predict_stored_measurement",
]

DEFAULT_DEPTHS_MM = (10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0)
"""Depth planes of a map of a model file, which brings no calibration to say where the
probe works, mm: the working range of the paper's probe (SPEC section 2)."""
MAP_PLANES = 8
"""Depth planes of a map over the depths where its calibration saw the board (when
``--depths`` is not given)."""

MC_SAMPLES = 20_000
"""Monte Carlo samples when ``--samples`` is not given."""


@dataclasses.dataclass(frozen=True)
class NoiseAssumptions:
    """What a prediction assumes about its inputs and how it propagates them: the
    choices the three modes share (``--sigma``, ``--rho-images``, ``--rho-points``,
    ``--method``, ``--no-calibration``, ``--samples``).

    The image noise itself is an :class:`~endomeasure.measure.predict.ImageNoise`, which
    :meth:`image_noise` builds (and validates) once the model, and so the residual sigma
    a missing ``sigma`` stands for, is known.

    Attributes
    ----------
    sigma : float, (float, float) or None
        Image noise, px: one number, or u and v; None takes the calibrated model's
        residual sigma.
    rho_images, rho_points : float
        Correlations of one point's errors in the two halves, and of different points'
        (checked by ``ImageNoise``).
    method : {'ut', 'linear', 'mc'}
    calibration : bool
        Whether the calibration covariance joins the input (when the model has one).
    model_error : bool
        Whether the calibration's model misfit joins the input (when its residuals show
        one, :mod:`endomeasure.solvers.misfit`). The default image noise leaves the misfit
        out either way: it is noise only.
    n_samples : int or None
        Monte Carlo samples (``mc`` only; default :data:`MC_SAMPLES`).
    seed : int
        Monte Carlo seed.
    """

    sigma: float | tuple[float, float] | None = None
    rho_images: float = 0.0
    rho_points: float = 0.0
    method: str = "ut"
    calibration: bool = True
    model_error: bool = True
    n_samples: int | None = None
    seed: int = 0

    def __post_init__(self):
        from endomeasure.solvers.uncertainty import METHODS

        if self.method not in METHODS:
            raise BadInputError(
                f"unknown method {self.method!r}", hint=f"use one of {', '.join(METHODS)}"
            )
        for name in ("rho_images", "rho_points"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise BadInputError(f"--{name.replace('_', '-')} must be a number, not {value}")
        if self.n_samples is not None and not 100 <= int(self.n_samples) <= defaults.MAX_MC_SAMPLES:
            raise BadInputError(
                f"--samples {self.n_samples} is outside 100-{defaults.MAX_MC_SAMPLES:.0e}: fewer "
                "give no quantiles, more than that take minutes and gigabytes for no precision",
                hint="the default 20000 suits most uses",
            )

    def image_noise(self, cm, what: str):
        """The :class:`~endomeasure.measure.predict.ImageNoise` to use: ``sigma``, or the
        calibrated model ``cm``'s residual sigma less its model misfit; ``what`` names the
        model in errors."""
        from endomeasure.measure.predict import image_noise

        residual = None if cm is None else cm.sigma_px
        misfit = None if cm is None else cm.misfit
        return image_noise(self.sigma, residual, what, rho_images=self.rho_images,
                           rho_points=self.rho_points, misfit=misfit)  # fmt: skip

    def propagation(self, cm) -> dict[str, Any]:
        """The predictors' keywords besides the image noise
        (:func:`~endomeasure.measure.predict.predict_measurement_error`) for the
        calibrated model ``cm`` (None for a model file): ``param_cov`` (None without
        ``calibration``), ``misfit`` (None without ``model_error``), ``method`` and its
        Monte Carlo options."""
        options: dict[str, Any] = {}
        if self.method == "mc":
            options = {"n_samples": int(self.n_samples or MC_SAMPLES), "seed": int(self.seed)}
        cov = cm.param_cov if cm is not None and self.calibration else None
        misfit = cm.misfit if cm is not None and self.model_error else None
        return {"param_cov": cov, "misfit": misfit, "method": self.method, **options}

    def model_error_in(self, cm) -> bool:
        """Whether a prediction with ``cm`` propagates a model misfit."""
        return bool(self.model_error and cm is not None and cm.misfit is not None
                    and cm.misfit.present)  # fmt: skip


# ----- board test --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BoardPredictionReport:
    session: str
    model: str
    method: str
    noise: Any  # ImageNoise
    calibration: bool
    zone_mm: float
    zones: list[dict[str, Any]]
    """Per (board, kind, zone): n, actual mean/std, predicted mean/std (and the image and
    calibration parts of the std), the ratio actual/predicted std and the fraction of
    errors inside the predicted 2-sigma band."""
    within_band: float
    """Fraction of all measurements whose error lies in its predicted 2-sigma band."""
    plot: str | None
    rows: Any = dataclasses.field(repr=False)
    """The PredictedErrors of every board-test row."""
    model_error: bool = False
    """Whether the calibration's model misfit was propagated."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "model": self.model,
            "method": self.method,
            **self.noise.to_dict(),
            "calibration": self.calibration,
            "model_error": self.model_error,
            "zone_mm": self.zone_mm,
            "zones": self.zones,
            "within_band": self.within_band,
            "plot": self.plot,
        }


def _board_grids(bt) -> dict[str, np.ndarray]:
    """Each board's corner coordinates by id, parsed from the board test's specs."""
    from endomeasure.features.boards import parse_board_spec

    return {b: np.asarray(parse_board_spec(b).object_points) for b in dict.fromkeys(bt.board)}


def board_predictions(bt, model, noise, **options):
    """:func:`endomeasure.measure.board_runs.board_predictions` with the boards' corner
    grids parsed from the board test's specs (``noise``: an ImageNoise or
    ImageNoiseByImage; ``options``: ``param_cov``, ``at``, ``method``, ...)."""
    from endomeasure.measure.board_runs import board_predictions as predict

    return predict(bt, model, _board_grids(bt), noise, **options)


TEST_IMAGE_NOISE = "each test image's noise from its neighbouring corners, median"
"""The ``sigma_source`` of a board-test prediction at its default image noise."""


def board_test_noise(bt, model, noise: NoiseAssumptions, cm, what: str):
    """The image noise of a board-test prediction: ``noise``'s when it gives a sigma or
    correlations, else each test image's own noise per half and coordinate, and the
    correlation of a corner's two views
    (:func:`~endomeasure.measure.board_runs.test_image_noise`): what the images show,
    without the calibration's misfit that its residual sigma holds."""
    from endomeasure.measure.board_runs import measured_image_noise

    if noise.sigma is not None or noise.rho_images != 0 or noise.rho_points != 0:
        return noise.image_noise(cm, what)
    measured = measured_image_noise(bt, model, _board_grids(bt), TEST_IMAGE_NOISE)
    return noise.image_noise(cm, what) if measured is None else measured


def _board_test_of(session, reader, model: str, cm, zone_mm: float):
    """The stored board test of ``model``, or a new one (then also returned as a record)."""
    from endomeasure.io.records import BOARD_TEST_RECORD, board_test_fields, board_test_record
    from endomeasure.measure.board_runs import ModelBoardTest, board_sets, run_board_test

    if model in reader.record_names(BOARD_TEST_RECORD):
        fields = board_test_fields(reader.record(BOARD_TEST_RECORD, model))
        return ModelBoardTest.from_fields(fields), None
    boards = {name: b.attrs for name, b in reader.boards().items()}
    sets = board_sets(boards, reader.detections(), reader.image_names("test"), str(session))
    bt = run_board_test(model, cm.model, sets, zone_mm)
    return bt, board_test_record(bt, zone_mm)


def predict_board_test(
    session: str | Path,
    model: str = "raytrace",
    noise: NoiseAssumptions = NoiseAssumptions(),  # noqa: B008 (immutable)
    *,
    zone_mm: float | None = None,
    plot: str | Path | None = None,
    store: bool = True,
) -> BoardPredictionReport:
    """Predicted vs actual board-test errors per board, kind and zone (the paper's Fig. 5).

    Uses the session's stored board test of ``model`` (running it, and storing it with
    the prediction, if there is none). Stores a ``prediction`` record named
    ``board-test-<model>``.
    """
    from endomeasure.io.outputs import PLOT_SUFFIXES, checked_output, checked_session_target
    from endomeasure.io.records import board_prediction_record
    from endomeasure.io.session import edit_session, open_session
    from endomeasure.measure.board_runs import prediction_zones, within_band
    from endomeasure.measure.board_test import checked_zone_mm
    from endomeasure.pipeline import calibrated_model

    zone = checked_zone_mm(defaults.ZONE_MM if zone_mm is None else zone_mm)
    if store:
        checked_session_target(session, create=False)
    if plot is not None:
        plot = checked_output(plot, "plot", inputs=[session], suffixes=PLOT_SUFFIXES)
    with open_session(session) as reader:
        cm = calibrated_model(reader, model, session)
        if noise.sigma is not None:
            noise.image_noise(cm, f"model {model!r}")  # checked before any work
        bt, new_record = _board_test_of(session, reader, model, cm, zone)
    image_noise = board_test_noise(bt, cm.model, noise, cm, f"model {model!r}")
    pred = board_predictions(bt, cm.model, image_noise, **noise.propagation(cm))
    zones = prediction_zones(bt, pred, zone)
    written = None
    if plot is not None:
        from endomeasure.measure.plots import plot_predicted_vs_actual

        written = str(plot_predicted_vs_actual(zones, plot))
    report = BoardPredictionReport(
        str(session), model, noise.method, image_noise, noise.calibration, zone, zones,
        within_band(bt, pred.bias, pred.std), written, pred, noise.model_error_in(cm),
    )  # fmt: skip
    # one edit for both records: the session is copied once, and a failure stores neither
    records = [] if new_record is None else [new_record]
    if store:
        records.append(board_prediction_record(report))
    if records:
        with edit_session(session) as writer:
            for record in records:
                writer.write_record(record)
    return report


# ----- one stored measurement ---------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MeasurementPredictionReport:
    session: str
    measurement: str
    model: str
    kind: str
    unit: str
    method: str
    noise: Any  # ImageNoise
    error: Any  # PredictedError
    n_invalid: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "measurement": self.measurement,
            "model": self.model,
            "kind": self.kind,
            "unit": self.unit,
            "method": self.method,
            **self.noise.to_dict(),
            **self.error.to_dict(),
            "n_invalid": self.n_invalid,
        }


def _without_unused(image_noise, stored):
    """The image noise of a stored measurement's inputs: for a ``--plane`` one, none on
    the right pixels of the points placed on the plane (they are not used)."""
    if not stored.plane:
        return image_noise
    from endomeasure.measure.predict import ImageNoise
    from endomeasure.solvers.uncertainty import pixel_sigmas

    if image_noise.rho_images or image_noise.rho_points:
        raise BadInputError(
            "a --plane measurement's prediction takes no correlations (its placed points "
            "have no right pixel)",
            hint="leave out --rho-images and --rho-points",
        )
    std = np.tile(np.tile(pixel_sigmas(image_noise.sigma), 2), (stored.pixels_left.shape[0], 1))
    std[np.isnan(stored.pixels_right).any(axis=1), 2:] = 0.0
    return ImageNoise.per_point(std, image_noise.source)


def predict_stored_measurement(
    session: str | Path,
    measurement: str,
    noise: NoiseAssumptions = NoiseAssumptions(),  # noqa: B008 (immutable)
    *,
    model: str | None = None,
    store: bool = True,
) -> MeasurementPredictionReport:
    """Predict the error of a measurement stored by ``measure`` (by its id, e.g. ``m001``).

    ``model`` defaults to the model the measurement was made with. Stores a
    ``prediction`` record named ``<id>-<method>``.
    """
    from endomeasure.io.records import (
        MEASUREMENT_RECORD,
        measurement_prediction_record,
        stored_measurement,
    )
    from endomeasure.io.session import edit_session, open_session
    from endomeasure.measure.kinds import kind_spec
    from endomeasure.measure.predict import PredictedError, predict_measurement_error
    from endomeasure.pipeline import calibrated_model

    if store:
        from endomeasure.io.outputs import checked_session_target

        checked_session_target(session, create=False)
    with open_session(session) as reader:
        stored = stored_measurement(reader.record(MEASUREMENT_RECORD, measurement))
        name = model or stored.model
        cm = calibrated_model(reader, name, session)
    image_noise = noise.image_noise(cm, f"model {name!r}")
    pred = predict_measurement_error(
        cm.model,
        stored.kind,
        stored.pixels_left,
        stored.pixels_right,
        noise=_without_unused(image_noise, stored),
        plane=stored.plane,
        **noise.propagation(cm),
    )
    report = MeasurementPredictionReport(
        str(session), measurement, name, stored.kind, kind_spec(stored.kind).unit,
        noise.method, image_noise, PredictedError.of(pred),
        int(pred.n_invalid[0]),
    )  # fmt: skip
    if store:
        with edit_session(session) as writer:
            writer.write_record(measurement_prediction_record(report, report.to_dict()))
    return report


# ----- maps over the working volume -----------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MapReport:
    source: str
    model: str
    method: str
    noise: Any  # ImageNoise
    calibration: bool
    depths: list[float]
    per_depth: list[dict[str, Any]]
    plot: str | None
    csv: str | None
    error_map: Any = dataclasses.field(repr=False)  # ErrorMap
    model_error: bool = False

    @property
    def template(self) -> str:
        return self.error_map.template

    @property
    def size_mm(self) -> float:
        return self.error_map.size_mm

    @property
    def true(self) -> float:
        return self.error_map.true

    def to_dict(self, points: bool = True) -> dict[str, Any]:
        d = {
            "source": self.source,
            "model": self.model,
            "template": self.template,
            "size_mm": self.size_mm,
            "true": self.true,
            "method": self.method,
            **self.noise.to_dict(),
            "calibration": self.calibration,
            "model_error": self.model_error,
            "depths": list(self.depths),
            "per_depth": [dict(row) for row in self.per_depth],
            "plot": self.plot,
            "csv": self.csv,
        }
        if points:
            em = self.error_map
            d["points"] = [
                {
                    "xyz_mm": em.centres[i].tolist(),
                    "bias": float(em.errors.bias[i]),
                    "std": float(em.errors.std[i]),
                }
                for i in np.flatnonzero(em.visible)
            ]
        return d


def _map_model(session, model: str, model_file):
    """(camera model, calibrated model or None, source, name) of a map."""
    if model_file is not None:
        from endomeasure.io.export import read_model_file

        cam = read_model_file(model_file)
        return cam, None, str(model_file), cam.NAME
    if session is None:
        raise BadInputError("a map needs a session with a calibrated model, or --model-file")
    from endomeasure.io.session import open_session
    from endomeasure.pipeline import calibrated_model

    with open_session(session) as reader:
        cm = calibrated_model(reader, model, session)
    return cm.model, cm, str(session), model


def _per_depth(em, depths: np.ndarray) -> list[dict[str, Any]]:
    rows = []
    for d in depths:
        sel = np.isclose(em.centres[:, 2], d) & np.isfinite(em.errors.std)
        if not sel.any():
            continue
        rows.append(
            {
                "z_mm": float(d),
                "n": int(sel.sum()),
                "std_median": float(np.median(em.errors.std[sel])),
                "std_max": float(np.max(em.errors.std[sel])),
                "bias_median": float(np.median(em.errors.bias[sel])),
            }
        )
    return rows


def predict_map(
    session: str | Path | None,
    *,
    model: str = "raytrace",
    model_file: str | Path | None = None,
    template: str = "x-segment",
    size_mm: float = 1.0,
    depths: Sequence[float] | None = None,
    grid: tuple[int, int] = (24, 18),
    noise: NoiseAssumptions = NoiseAssumptions(),  # noqa: B008 (immutable)
    plot: str | Path | None = None,
    csv: str | Path | None = None,
    calibrated=None,
) -> MapReport:
    """Predicted std of a template measurement over a grid of the working volume.

    Either a calibrated ``model`` of ``session`` (with its covariance unless
    ``noise.calibration=False``, and its residual sigma by default) or ``model_file``, a
    JSON model with nominal parameters (no covariance; ``noise.sigma`` must be given).
    ``depths``: the planes of the grid, mm (default: ``MAP_PLANES`` planes over the depths
    where the calibration saw the board, or for a model file the paper's working range,
    ``DEFAULT_DEPTHS_MM``); ``grid``: (NU, NV) pixels over the left half. ``calibrated``:
    the session's ``model`` already loaded (a ``CalibratedModel``), not read again.
    """
    from endomeasure.io.export import write_map_csv
    from endomeasure.io.outputs import PLOT_SUFFIXES, checked_outputs
    from endomeasure.measure.predict import TEMPLATES, error_map, volume_grid

    if template not in TEMPLATES:
        raise BadInputError(
            f"unknown map template {template!r}", hint=f"use one of {', '.join(TEMPLATES)}"
        )
    n_u, n_v = grid
    if n_u < 2 or n_v < 2:
        raise BadInputError(f"the map grid needs at least 2x2 points, got {n_u}x{n_v}")
    if not (math.isfinite(size_mm) and size_mm > 0):
        raise BadInputError(f"the template size must be a positive number of mm, not {size_mm}")
    n_planes = MAP_PLANES if depths is None else len(depths)
    if n_planes > defaults.MAX_MAP_DEPTHS:
        raise BadInputError(
            f"{n_planes} depth planes is more than {defaults.MAX_MAP_DEPTHS}, more than a map "
            "can show",
            hint="give fewer --depths",
        )
    if n_u * n_v * n_planes > defaults.MAX_MAP_POINTS:
        raise BadInputError(
            f"a map of {n_u}x{n_v} points on {n_planes} planes has {n_u * n_v * n_planes} "
            f"points, more than {defaults.MAX_MAP_POINTS}: it would run for hours",
            hint="give a coarser --grid or fewer --depths",
        )
    plot, csv = checked_outputs(
        [(plot, "plot", PLOT_SUFFIXES), (csv, "CSV file", None)], inputs=[session, model_file]
    )
    if calibrated is not None:
        cam, cm, source, name = calibrated.model, calibrated, str(session), model
    else:
        cam, cm, source, name = _map_model(session, model, model_file)
    if depths is None:
        seen = None if cm is None else cm.depth_range_mm
        depths = DEFAULT_DEPTHS_MM if seen is None else np.linspace(*seen, MAP_PLANES).round(1)
    z = np.asarray(depths, dtype=float)
    if z.size == 0 or not np.all(np.isfinite(z) & (z > 0)):
        raise BadInputError(f"depths must be positive numbers of mm, got {list(depths)}")
    param_cov = None if cm is None else cm.param_cov
    image_noise = noise.image_noise(cm, "a model file" if cm is None else f"model {model!r}")
    centres = volume_grid(cam, z, n_u, n_v)
    if centres.shape[0] == 0:
        raise BadInputError(
            "no grid point of these depths is seen by both halves",
            hint="choose depths inside the working range",
        )
    em = error_map(cam, centres, template, size_mm, noise=image_noise, **noise.propagation(cm))
    written_plot = None
    if plot is not None:
        from endomeasure.measure.plots import plot_error_map

        written_plot = str(plot_error_map(em, plot))
    written_csv = None if csv is None else str(write_map_csv(em, csv))
    return MapReport(
        source, name, noise.method, image_noise,
        noise.calibration and param_cov is not None, [float(d) for d in z], _per_depth(em, z),
        written_plot, written_csv, em, noise.model_error_in(cm),
    )  # fmt: skip
