"""``endomeasure predict-error``: predicted measurement errors, in three modes.

SPEC section 8, issue 8, the paper's Section 4.

- :func:`predict_board_test` — predicted bias and standard deviation of every board-test
  measurement (from the corners' detected pixels, the image noise ``sigma`` with its
  correlations, and the calibration covariance), summarised per board, kind and zone
  next to the actual errors of :func:`endomeasure.pipeline.measure.board_test` (the
  paper's Fig. 5);
- :func:`predict_stored_measurement` — the prediction of one stored measurement, again,
  with other noise assumptions or another method;
- :func:`predict_map` — the predicted error of a template measurement over a grid of the
  working volume, for a calibrated model or for a model file with nominal parameters
  (an adapter design on paper, no calibration covariance).

How a zone's prediction is compared with the actual errors
-----------------------------------------------------------
Each measurement i of a zone has its own predicted bias ``b_i`` and std ``s_i`` (they
vary over the field). The actual errors of the zone are draws from the mixture of these
distributions, whose mean is ``mean(b_i)`` and whose standard deviation is
``sqrt(mean(s_i^2) + var(b_i))``: that is the predicted zone std compared with the
sample std of the actual errors. The band check asks for each error whether
``|e_i - b_i| <= 2 s_i``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError

__all__ = [
    "BAND_SIGMAS",
    "DEFAULT_DEPTHS_MM",
    "BoardPredictionReport",
    "MapReport",
    "MeasurementPredictionReport",
    "NoiseAssumptions",
    "predict_board_test",
    "predict_map",
    "predict_stored_measurement",
    "parse_depths",
]

BAND_SIGMAS = 2.0
"""Half-width of the band an actual error is checked against, in predicted std (issue 8)."""

DEFAULT_DEPTHS_MM = "10:45:5"
"""Depth planes of a map (start:stop:step, mm, stop included): the working range of the
paper's probe (SPEC section 2)."""

PREDICTION_RECORD = "prediction"


@dataclasses.dataclass(frozen=True)
class NoiseAssumptions:
    """What a prediction assumes about its inputs and how it propagates them: the
    choices the three modes share (``--sigma``, ``--rho-images``, ``--rho-points``,
    ``--method``, ``--no-calibration``, ``--samples``).

    Attributes
    ----------
    sigma : float, (float, float) or None
        Image noise, px: one number, or u and v; None takes the calibrated model's
        residual sigma.
    rho_images, rho_points : float
        Correlations of one point's errors in the two halves, and of different points'.
    method : {'ut', 'linear', 'mc'}
    calibration : bool
        Whether the calibration covariance joins the input (when the model has one).
    n_samples : int or None
        Monte Carlo samples (``mc`` only; default 20,000).
    seed : int
        Monte Carlo seed.
    """

    sigma: float | tuple[float, float] | None = None
    rho_images: float = 0.0
    rho_points: float = 0.0
    method: str = "ut"
    calibration: bool = True
    n_samples: int | None = None
    seed: int = 0

    def __post_init__(self):
        from endomeasure.solvers.uncertainty import METHODS

        for name, rho in (("rho-images", self.rho_images), ("rho-points", self.rho_points)):
            if not (math.isfinite(rho) and -1.0 <= rho <= 1.0):
                raise BadInputError(f"--{name} must lie in [-1, 1], not {rho}")
        if self.method not in METHODS:
            raise BadInputError(
                f"unknown method {self.method!r}", hint=f"use one of {', '.join(METHODS)}"
            )

    def sigma_px(self, cm, what: str) -> tuple[float | tuple[float, float], str]:
        """The image noise to use and where it comes from
        (:func:`~endomeasure.pipeline.measure.image_noise`)."""
        from endomeasure.pipeline.measure import image_noise

        return image_noise(self.sigma, cm, what)

    def propagation(self, sigma_px, param_cov) -> dict[str, Any]:
        """Keyword arguments of the predictors (:mod:`endomeasure.measure.predict`)."""
        options: dict[str, Any] = {}
        if self.method == "mc":
            options = {"n_samples": int(self.n_samples or 20_000), "seed": int(self.seed)}
        return dict(
            sigma=sigma_px,
            rho_images=self.rho_images,
            rho_points=self.rho_points,
            param_cov=param_cov if self.calibration else None,
            method=self.method,
            **options,
        )


# ----- board test --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BoardPredictionReport:
    session: str
    model: str
    method: str
    sigma_px: float | tuple[float, float]
    sigma_source: str
    rho_images: float
    rho_points: float
    calibration: bool
    zone_mm: float
    zones: list[dict[str, Any]]
    """Per (board, kind, zone): n, actual mean/std, predicted mean/std (and the image and
    calibration parts of the std), the ratio actual/predicted std and the fraction of
    errors inside the predicted 2-sigma band."""
    within_band: float
    """Fraction of all measurements whose error lies in its predicted 2-sigma band."""
    plot: str | None
    rows: dict[str, np.ndarray] = dataclasses.field(repr=False, default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in dataclasses.asdict(self).items() if k != "rows"}
        return d


def _zone_rows(bt, bias, std, std_img, std_cal, zone_mm) -> list[dict[str, Any]]:
    from endomeasure.measure.board_test import BOARD_KINDS

    t = bt.table
    board_of_row = np.asarray(bt.board, dtype=str)[t.image]
    zone = np.floor(t.z_mean / zone_mm)
    ok = np.isfinite(t.error) & np.isfinite(std) & np.isfinite(t.z_mean)
    rows = []
    for board in dict.fromkeys(board_of_row.tolist()):
        for kind in BOARD_KINDS:
            base = ok & (board_of_row == board) & (t.kind == kind)
            for k in np.unique(zone[base]):
                sel = base & (zone == k)
                e, b, s = t.error[sel], bias[sel], std[sel]
                if e.size < 2:
                    continue
                pred_std = float(np.sqrt(np.mean(s**2) + np.var(b)))
                actual_std = float(np.std(e, ddof=1))
                rows.append(
                    {
                        "board": board,
                        "kind": kind,
                        "zone_start": float(k * zone_mm),
                        "zone_end": float((k + 1) * zone_mm),
                        "n": int(e.size),
                        "true": float(t.true[sel][0]),
                        "actual_mean": float(np.mean(e)),
                        "actual_std": actual_std,
                        "predicted_mean": float(np.mean(b)),
                        "predicted_std": pred_std,
                        "predicted_std_image": float(np.sqrt(np.mean(std_img[sel] ** 2))),
                        "predicted_std_calibration": float(np.sqrt(np.mean(std_cal[sel] ** 2)))
                        if np.all(np.isfinite(std_cal[sel]))
                        else None,
                        "std_ratio": actual_std / pred_std if pred_std > 0 else None,
                        "within_band": float(np.mean(np.abs(e - b) <= BAND_SIGMAS * s)),
                    }
                )
    return rows


def _board_pixels(model, board: str, ids, xyz, ql, qr):
    """Pixels of the ideal board at its estimated pose (the paper's Section 4: the
    prediction is made at the "calibration target positions calculated for the test set").

    The rigid transform board -> model frame is the least-squares fit (Kabsch) of the
    board's corner grid to the triangulated corners; the grid at that pose is projected
    into both halves. Corners that do not project keep their detected pixels.
    """
    from endomeasure.features.boards import parse_board_spec

    grid = np.asarray(parse_board_spec(board).object_points)[np.asarray(ids, dtype=np.int64)]
    ok = np.all(np.isfinite(xyz), axis=1)
    if ok.sum() < 3:
        return ql, qr
    a, b = grid[ok], xyz[ok]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    ideal = (grid - ca) @ rot.T + cb
    out = []
    for half, q in (("left", ql), ("right", qr)):
        proj = model.project(ideal, half)
        good = (proj.status == 0)[:, None]
        out.append(np.where(good, proj.pixels, q))
    return out[0], out[1]


def board_predictions(bt, model, *, at="board", **propagation) -> dict[str, np.ndarray]:
    """Predicted bias, std and its parts for every row of a board test's table.

    ``propagation``: the noise and method keywords of
    :func:`~endomeasure.measure.predict.predict_measurement_error` (``sigma``,
    ``rho_images``, ``rho_points``, ``param_cov``, ``method``, ...).

    ``at='board'`` predicts at the pixels of the ideal board at its estimated pose
    (:func:`_board_pixels`), ``at='detections'`` at the detected pixels. The first is the
    better estimate of the error distribution: a prediction at noisy pixels is itself
    noisy, and for a segment whose ends carry a large depth noise it is biased upwards
    (the observed depth difference of its ends tilts the segment, which turns the
    quadratic depth term into a linear one).

    Returns
    -------
    dict with ``bias``, ``std``, ``std_image``, ``std_calibration``, ``value`` (M,).
    """
    from endomeasure.measure.board_test import BOARD_KINDS, BoardImage, stencil_pixels
    from endomeasure.measure.predict import predict_measurement_error

    t = bt.table
    images = []
    for k in range(len(bt.images)):
        ids, ql, qr, xyz = bt.image_pixels(k)
        if at == "board":
            ql, qr = _board_pixels(model, bt.board[k], ids, xyz, ql, qr)
        images.append(BoardImage(ids, xyz, ql, qr))
    m = t.kind.shape[0]
    out = {
        key: np.full(m, np.nan) for key in ("bias", "std", "std_image", "std_calibration", "value")
    }
    for kind, measure_kind in BOARD_KINDS.items():
        rows = np.flatnonzero(t.kind == kind)
        if rows.size == 0:
            continue
        ql, qr = stencil_pixels(t, images, kind)
        pred = predict_measurement_error(model, measure_kind, ql, qr, **propagation)
        out["bias"][rows] = pred.bias
        out["std"][rows] = pred.std
        out["value"][rows] = pred.value
        if "image" in pred.parts:
            out["std_image"][rows] = pred.parts["image"][1]
        if "calibration" in pred.parts:
            out["std_calibration"][rows] = pred.parts["calibration"][1]
        elif propagation.get("param_cov") is None:
            out["std_image"][rows] = pred.std
    return out


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

    Uses the session's stored board test of ``model`` (running it first if there is
    none). Stores a ``prediction`` record named ``board-test-<model>``.
    """
    from endomeasure.io.session import Record, edit_session, open_session
    from endomeasure.pipeline.measure import (
        BOARD_TEST_RECORD,
        DEFAULT_ZONE_MM,
        board_test,
        load_board_test,
        load_calibrated_model,
    )

    with open_session(session) as reader:
        cm = load_calibrated_model(reader, model, session)
        stored = model in reader.record_names(BOARD_TEST_RECORD)
        bt = load_board_test(reader, model) if stored else None
    if bt is None:
        bt = board_test(session, model, zone_mm or DEFAULT_ZONE_MM).models[model]
    zone = float(zone_mm) if zone_mm is not None else DEFAULT_ZONE_MM
    if not (math.isfinite(zone) and zone > 0):
        raise BadInputError(f"the zone width must be a positive number of mm, not {zone}")
    sigma_px, source = noise.sigma_px(cm, f"model {model!r}")
    pred = board_predictions(bt, cm.model, **noise.propagation(sigma_px, cm.param_cov))
    zones = _zone_rows(
        bt, pred["bias"], pred["std"], pred["std_image"], pred["std_calibration"], zone
    )
    ok = np.isfinite(bt.table.error) & np.isfinite(pred["std"])
    within = float(
        np.mean(np.abs(bt.table.error[ok] - pred["bias"][ok]) <= BAND_SIGMAS * pred["std"][ok])
    )
    written = None
    if plot is not None:
        from endomeasure.measure.plots import plot_predicted_vs_actual

        written = str(plot_predicted_vs_actual(zones, plot))
    report = BoardPredictionReport(
        str(session),
        model,
        noise.method,
        sigma_px,
        source,
        float(noise.rho_images),
        float(noise.rho_points),
        noise.calibration,
        zone,
        zones,
        within,
        written,
        pred,
    )
    if store:
        with edit_session(session) as writer:
            writer.write_record(
                Record(
                    PREDICTION_RECORD,
                    f"board-test-{model}",
                    attrs={
                        "mode": "board-test",
                        "model": model,
                        "method": noise.method,
                        "sigma_px": sigma_px,
                        "sigma_source": source,
                        "rho_images": float(noise.rho_images),
                        "rho_points": float(noise.rho_points),
                        "calibration": bool(noise.calibration),
                        "zone_mm": zone,
                        "within_band": within,
                        "zones": json.dumps(zones),
                    },
                    arrays={k: v for k, v in pred.items()},
                    units={"sigma_px": "px", "zone_mm": "mm"},
                )
            )
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
    sigma_px: float | tuple[float, float]
    sigma_source: str
    rho_images: float
    rho_points: float
    value: float
    bias: float
    std: float
    std_image: float
    std_calibration: float
    ci95: float
    relative_percent: float
    n_invalid: int

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


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
    from endomeasure.io.session import Record, edit_session, open_session
    from endomeasure.measure.kinds import kind_spec
    from endomeasure.measure.predict import predict_measurement_error
    from endomeasure.pipeline.measure import (
        MEASUREMENT_RECORD,
        Z95,
        accuracy_index,
        load_calibrated_model,
    )

    with open_session(session) as reader:
        rec = reader.record(MEASUREMENT_RECORD, measurement)
        name = model or str(rec.attrs["model"])
        cm = load_calibrated_model(reader, name, session)
    kind = str(rec.attrs["measurement_kind"])
    sigma_px, source = noise.sigma_px(cm, f"model {name!r}")
    pred = predict_measurement_error(
        cm.model,
        kind,
        rec.arrays["pixels_left"],
        rec.arrays["pixels_right"],
        **noise.propagation(sigma_px, cm.param_cov),
    )
    value, bias, std = float(pred.value[0]), float(pred.bias[0]), float(pred.std[0])
    parts = {k: float(v[1][0]) for k, v in pred.parts.items()}
    report = MeasurementPredictionReport(
        str(session),
        measurement,
        name,
        kind,
        kind_spec(kind).unit,
        noise.method,
        sigma_px,
        source,
        float(noise.rho_images),
        float(noise.rho_points),
        value,
        bias,
        std,
        parts.get("image", std if not noise.calibration else math.nan),
        parts.get("calibration", math.nan),
        Z95 * std,
        accuracy_index(value, bias, std),
        int(pred.n_invalid[0]),
    )
    if store:
        with edit_session(session) as writer:
            writer.write_record(
                Record(
                    PREDICTION_RECORD,
                    f"{measurement}-{noise.method}",
                    attrs={
                        "mode": "measurement",
                        **{
                            ("measurement_kind" if k == "kind" else k): v
                            for k, v in report.to_dict().items()
                        },
                    },
                    units={"sigma_px": "px", "relative_percent": "%"},
                )
            )
    return report


# ----- maps over the working volume -----------------------------------------------------------


def parse_depths(text: str) -> np.ndarray:
    """``"start:stop:step"`` (stop included) or ``"z1,z2,..."`` -> depths, mm."""
    s = str(text).strip()
    try:
        if ":" in s:
            a, b, c = (float(x) for x in s.split(":"))
            if not (c > 0 and b >= a):
                raise ValueError
            depths = np.arange(a, b + 0.5 * c, c)
        else:
            depths = np.array([float(x) for x in s.split(",")])
    except ValueError:
        raise BadInputError(  # noqa: B904 (the message says everything)
            f"cannot read the depths {text!r}",
            hint="give START:STOP:STEP in mm (e.g. 10:45:5) or a list 12,20,30",
        )
    if depths.size == 0 or not np.all(np.isfinite(depths) & (depths > 0)):
        raise BadInputError(f"depths must be positive numbers of mm, got {text!r}")
    return depths


@dataclasses.dataclass(frozen=True)
class MapReport:
    source: str
    model: str
    template: str
    size_mm: float
    true: float
    method: str
    sigma_px: float | tuple[float, float]
    sigma_source: str
    rho_images: float
    rho_points: float
    calibration: bool
    depths: list[float]
    per_depth: list[dict[str, Any]]
    plot: str | None
    csv: str | None
    centres: np.ndarray = dataclasses.field(repr=False)
    std: np.ndarray = dataclasses.field(repr=False)
    bias: np.ndarray = dataclasses.field(repr=False)
    visible: np.ndarray = dataclasses.field(repr=False)

    def to_dict(self, points: bool = True) -> dict[str, Any]:
        d = {
            k: v
            for k, v in dataclasses.asdict(self).items()
            if k not in ("centres", "std", "bias", "visible")
        }
        if points:
            d["points"] = [
                {
                    "xyz_mm": self.centres[i].tolist(),
                    "bias": float(self.bias[i]),
                    "std": float(self.std[i]),
                }
                for i in np.flatnonzero(self.visible)
            ]
        return d


def _load_model_file(path: str | Path):
    from endomeasure.models import model_from_dict

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise BadInputError(f"cannot read the model file ({exc})", path=str(path)) from None
    if isinstance(data, dict) and "model" not in data and "camera_model" in data:
        data = data["camera_model"]
    try:
        return model_from_dict(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise BadInputError(
            f"not a camera model ({exc})",
            path=str(path),
            hint="write it with `endomeasure export` or model.to_json()",
        ) from None


def predict_map(
    session: str | Path | None,
    *,
    model: str = "raytrace",
    model_file: str | Path | None = None,
    template: str = "x-segment",
    size_mm: float = 1.0,
    depths: str | Sequence[float] = DEFAULT_DEPTHS_MM,
    grid: tuple[int, int] = (24, 18),
    noise: NoiseAssumptions = NoiseAssumptions(),  # noqa: B008 (immutable)
    plot: str | Path | None = None,
    csv: str | Path | None = None,
) -> MapReport:
    """Predicted std of a template measurement over a grid of the working volume.

    Either a calibrated ``model`` of ``session`` (with its covariance unless
    ``noise.calibration=False``, and its residual sigma by default) or ``model_file``, a
    JSON model with nominal parameters (no covariance; ``noise.sigma`` must be given).
    """
    from endomeasure.measure.predict import TEMPLATES, error_map, volume_grid

    if template not in TEMPLATES:
        raise BadInputError(
            f"unknown map template {template!r}", hint=f"use one of {', '.join(TEMPLATES)}"
        )
    n_u, n_v = grid
    if n_u < 2 or n_v < 2:
        raise BadInputError(f"the map grid needs at least 2x2 points, got {n_u}x{n_v}")
    z = parse_depths(depths) if isinstance(depths, str) else np.asarray(depths, dtype=float)
    if model_file is not None:
        cam = _load_model_file(model_file)
        param_cov, cm, source, name = None, None, str(model_file), cam.NAME
    else:
        if session is None:
            raise BadInputError("a map needs a session with a calibrated model, or --model-file")
        from endomeasure.io.session import open_session
        from endomeasure.pipeline.measure import load_calibrated_model

        with open_session(session) as reader:
            cm = load_calibrated_model(reader, model, session)
        cam, name, source = cm.model, model, str(session)
        param_cov = cm.param_cov
    calibration = noise.calibration and param_cov is not None
    what = "a model file" if cm is None else f"model {model!r}"
    sigma_px, sigma_source = noise.sigma_px(cm, what)
    centres = volume_grid(cam, z, n_u, n_v)
    if centres.shape[0] == 0:
        raise BadInputError(
            "no grid point of these depths is seen by both halves",
            hint="choose depths inside the working range",
        )
    em = error_map(
        cam,
        centres,
        template,
        size_mm,
        **noise.propagation(sigma_px, param_cov),
    )
    per_depth = []
    for d in z:
        sel = np.isclose(centres[:, 2], d) & np.isfinite(em.std)
        if not sel.any():
            continue
        per_depth.append(
            {
                "z_mm": float(d),
                "n": int(sel.sum()),
                "std_median": float(np.median(em.std[sel])),
                "std_max": float(np.max(em.std[sel])),
                "bias_median": float(np.median(em.bias[sel])),
            }
        )
    written_plot = written_csv = None
    if plot is not None:
        from endomeasure.measure.plots import plot_error_map

        written_plot = str(plot_error_map(em, plot))
    if csv is not None:
        path = Path(csv)
        path.parent.mkdir(parents=True, exist_ok=True)
        data = np.column_stack(
            [centres, em.visible, em.value, em.bias, em.std, em.std_image, em.std_calibration]
        )
        np.savetxt(
            path,
            data,
            delimiter=",",
            fmt="%.9g",
            header="x_mm,y_mm,z_mm,visible,value,bias,std,std_image,std_calibration",
            comments="",
        )
        written_csv = str(path)
    return MapReport(
        source,
        name,
        template,
        float(size_mm),
        em.true,
        noise.method,
        sigma_px,
        sigma_source,
        float(noise.rho_images),
        float(noise.rho_points),
        calibration,
        [float(d) for d in z],
        per_depth,
        written_plot,
        written_csv,
        centres,
        em.std,
        em.bias,
        em.visible,
    )
