"""Predicted error of measurements: the kind-aware layer over the uncertainty core.

:mod:`endomeasure.solvers.uncertainty` propagates noise through any black box; this
module makes the black box of a measurement kind (triangulate the points with the
model, then apply the kind's formula from :mod:`endomeasure.measure.kinds`) and offers
the two uses of SPEC section 8 that need no session:

- :func:`predict_measurement_error` — bias and standard deviation (and their budget by
  source) of one or many measurements from their pixels;
- :func:`error_map` — the predicted error of a measurement template (e.g. a 1 mm
  x-segment) placed at every point of a grid of the working volume
  (:func:`volume_grid`), for a calibrated probe or a design on paper.

It lives in ``measure`` (not ``solvers``) because the layering lets measurements use the
solvers, not the other way round.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from endomeasure.conventions import Status
from endomeasure.errors import BadInputError
from endomeasure.measure.kinds import PLANE_POINTS, evaluate, kind_spec, projected_points
from endomeasure.solvers.uncertainty import (
    MeasurementFunction,
    Propagation,
    checked_sigma,
    input_covariance,
    propagate,
)

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel
    from endomeasure.solvers.misfit import ModelMisfit

__all__ = [
    "PredictedErrors",
    "ROW_BATCH",
    "TEMPLATES",
    "Z95",
    "ErrorMap",
    "ImageNoise",
    "ImageNoiseByImage",
    "PredictedError",
    "accuracy_index",
    "image_noise",
    "error_map",
    "measurement_function",
    "predict_measurement_error",
    "template_points",
    "volume_grid",
]


Z95 = 1.959963984540054
"""Two-sided 95 % quantile of the standard normal distribution."""


@dataclasses.dataclass(frozen=True)
class ImageNoise:
    """The image noise a prediction assumes: its size, where it comes from, its
    correlations, or an independent standard deviation per point.

    ``ImageNoise(0.05)`` is 0.05 px on every coordinate, uncorrelated, "given";
    :meth:`per_point` builds the per-point form. Validated on construction.

    Attributes
    ----------
    sigma : float or (float, float), px
        Standard deviation of every pixel coordinate, or of u and v; with
        ``pixel_std``, its largest value (what a report quotes).
    source : str
        Where the noise comes from (``given``, ``calibration residuals``, ...).
    rho_images, rho_points : float
        Correlation of one point's errors in the two halves, and of different points'
        (:func:`~endomeasure.solvers.uncertainty.pixel_covariance`).
    pixel_std : ndarray, shape (n, 2 or 4) or (M, n, 2 or 4), px, or None
        Instead of ``sigma`` and the correlations: an independent standard deviation per
        point for its left and its right pixel (both coordinates alike), or for each of
        ``u_L, v_L, u_R, v_R``, e.g. an exact clicked pixel (0) and an automatic match at
        its own precision; with a leading M, one row per measurement of a batch (each
        point at the noise of the image it lies in). Read-only.
    """

    sigma: float | tuple[float, float]
    source: str = "given"
    rho_images: float = 0.0
    rho_points: float = 0.0
    pixel_std: np.ndarray | None = dataclasses.field(default=None, compare=False)

    def __post_init__(self):
        std = None if self.pixel_std is None else np.array(self.pixel_std, dtype=np.float64)
        if std is not None and (
            std.ndim not in (2, 3) or 0 in std.shape or std.shape[-1] not in (2, 4)
        ):
            raise BadInputError(
                f"pixel_std must have shape (n, 2 or 4) or (M, n, 2 or 4), got {std.shape}"
            )
        if std is not None and not (np.all(np.isfinite(std)) and np.all(std >= 0)):
            raise BadInputError("pixel_std must be non-negative numbers of pixels")
        object.__setattr__(self, "sigma", checked_sigma(self.sigma))
        for name, rho in (("rho-images", self.rho_images), ("rho-points", self.rho_points)):
            if not (math.isfinite(rho) and -1.0 <= rho <= 1.0):
                raise BadInputError(f"--{name} must lie in [-1, 1], not {rho}")
        if std is None:
            return
        # one description of the noise: the per-point form is uncorrelated, and its sigma
        # is only the largest value, for the report
        if self.rho_images != 0 or self.rho_points != 0:
            raise BadInputError("a per-point image noise (pixel_std) has no correlations")
        if self.sigma != float(std.max()):
            raise BadInputError(
                "the sigma of a per-point image noise is its largest pixel_std",
                hint="build it with ImageNoise.per_point",
            )
        std.flags.writeable = False
        object.__setattr__(self, "pixel_std", std)

    def __eq__(self, other) -> bool:
        if not isinstance(other, ImageNoise):
            return NotImplemented
        fields = ("sigma", "source", "rho_images", "rho_points")
        same = all(getattr(self, f) == getattr(other, f) for f in fields)
        if self.pixel_std is None or other.pixel_std is None:
            return same and self.pixel_std is other.pixel_std
        return same and np.array_equal(self.pixel_std, other.pixel_std)

    @classmethod
    def per_point(cls, pixel_std, source: str) -> ImageNoise:
        """Independent noise of each point's left and right pixel, ``pixel_std`` (n, 2 or
        4) or (M, n, 2 or 4), px (see the class attributes)."""
        std = np.asarray(pixel_std, dtype=np.float64)
        return cls(float(np.max(std, initial=0.0)), source, pixel_std=std)

    def of_rows(self, images: np.ndarray) -> ImageNoise:
        """The noise of a batch of measurements in ``images`` (M,) (index of the image
        each one lies in): this noise, the same for every image (see
        :class:`ImageNoiseByImage`)."""
        return self

    def covariance(self, n_points: int, param_cov=None, model_cov=None):
        """The input covariance of ``n_points`` points and its blocks
        (:func:`~endomeasure.solvers.uncertainty.input_covariance`, which takes the
        parameters' and the model misfit's covariance)."""
        if self.pixel_std is None:
            return input_covariance(n_points, self.sigma, self.rho_images, self.rho_points,
                                    param_cov, model_cov=model_cov)  # fmt: skip
        if self.pixel_std.shape[-2] != n_points:
            raise BadInputError(
                f"the image noise has a pixel_std for {self.pixel_std.shape[-2]} points, the "
                f"measurement has {n_points}"
            )
        return input_covariance(n_points, None, param_cov=param_cov, pixel_std=self.pixel_std,
                                model_cov=model_cov)  # fmt: skip

    def to_dict(self, correlations: bool = True) -> dict[str, Any]:
        """The report fields ``sigma_px``, ``sigma_source`` (and ``rho_images``,
        ``rho_points``)."""
        out: dict[str, Any] = {"sigma_px": self.sigma, "sigma_source": self.source}
        if correlations:
            out.update(rho_images=float(self.rho_images), rho_points=float(self.rho_points))
        return out


@dataclasses.dataclass(frozen=True)
class ImageNoiseByImage:
    """Image noise measured on each image of a set, for measurements that each lie in
    one image (a board test): per half and coordinate, independent from point to point,
    with the correlation of a point's two views.

    Attributes
    ----------
    std : ndarray, shape (I, 4), px
        Standard deviation of ``u_L, v_L, u_R, v_R`` in image i. Read-only.
    source : str
        Where it comes from (for the report).
    rho : ndarray, shape (I, 2), optional
        Correlation of a point's u_L with its u_R, and of v_L with v_R, in image i (zero
        if not given). Read-only.
    rho_images, rho_points : float
        Always 0: the scalar correlations of :class:`ImageNoise`, which reports read;
        this noise's correlations are ``rho``.
    """

    std: np.ndarray = dataclasses.field(compare=False)
    source: str
    rho: np.ndarray | None = dataclasses.field(default=None, compare=False)
    rho_images: float = dataclasses.field(default=0.0, init=False)
    rho_points: float = dataclasses.field(default=0.0, init=False)

    def __post_init__(self):
        std = np.array(self.std, dtype=np.float64)
        valid = np.all(np.isfinite(std)) and np.all(std >= 0)
        if std.ndim != 2 or std.shape[1] != 4 or not valid:
            raise BadInputError("a per-image noise must be (images, 4) non-negative pixels")
        rho = np.zeros((std.shape[0], 2)) if self.rho is None else np.array(self.rho, float)
        if rho.shape != (std.shape[0], 2) or not np.all(np.abs(rho) <= 1.0):
            raise BadInputError("a per-image noise's correlations must be (images, 2) in [-1, 1]")
        for name, value in (("std", std), ("rho", rho)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    @property
    def sigma(self) -> float:
        """The median over the image halves, px (what a report quotes; ``source`` says
        so)."""
        return float(np.median(self.std)) if self.std.size else math.nan

    def of_rows(self, images: np.ndarray) -> _RowNoise:
        """The noise of measurements in ``images`` (M,) (index of the image each one lies
        in): each point of a row at its image's noise, sized to the measurement's points
        when its covariance is asked for."""
        return _RowNoise(self, np.asarray(images, dtype=np.int64))

    def to_dict(self, correlations: bool = True) -> dict[str, Any]:
        """As :meth:`ImageNoise.to_dict`, with the range of the images' std and the
        median correlation of a point's two views (u, v)."""
        out: dict[str, Any] = {"sigma_px": self.sigma, "sigma_source": self.source}
        if correlations:
            out.update(rho_images=self.rho_images, rho_points=self.rho_points)
        if self.std.size:
            out["sigma_px_range"] = [float(self.std.min()), float(self.std.max())]
            out["rho_halves_median"] = [float(q) for q in np.median(self.rho, axis=0)]
        return out


@dataclasses.dataclass(frozen=True)
class _RowNoise:
    """:class:`ImageNoiseByImage` for one batch of measurements, sized on use."""

    by_image: ImageNoiseByImage
    images: np.ndarray

    def covariance(self, n_points: int, param_cov=None, model_cov=None):
        std = self.by_image.std[self.images][:, None, :]
        rho = self.by_image.rho[self.images][:, None, :]
        return input_covariance(
            n_points, None, param_cov=param_cov,
            pixel_std=np.repeat(std, n_points, axis=1), pixel_rho=rho, model_cov=model_cov,
        )  # fmt: skip


def image_noise(
    given,
    residual_sigma: float | None,
    what: str,
    *,
    rho_images=0.0,
    rho_points=0.0,
    misfit: ModelMisfit | None = None,
) -> ImageNoise:
    """The image noise of a prediction: ``given`` (one number, or u and v, px), or else a
    calibration's residual sigma (px), less the model misfit it holds when ``misfit`` is
    known (that part is propagated as the model error); ``what`` names the model in the
    error when it has none."""
    if given is not None:
        return ImageNoise(given, "given", rho_images, rho_points)
    if residual_sigma is None:
        raise BadInputError(
            f"{what} carries no calibration residuals to estimate the image noise",
            hint="give --sigma PX (or U,V)",
        )
    if misfit is not None and misfit.present:
        return ImageNoise(misfit.noise_sigma, "calibration residuals less the model misfit",
                          rho_images, rho_points)  # fmt: skip
    return ImageNoise(residual_sigma, "calibration residuals", rho_images, rho_points)


def accuracy_index(value: float, bias: float, std: float) -> float:
    """The predicted 95 % error bound relative to the value, ``(|bias| + Z95 std) / |value|``,
    percent; infinite for a zero value."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(100.0 * (abs(bias) + Z95 * std) / abs(value)) if value != 0 else math.inf


@dataclasses.dataclass(frozen=True)
class PredictedError:
    """One measurement's value with its predicted bias and standard deviation, and the
    standard deviation's budget by source (image noise, calibration, model misfit; NaN for
    a source not propagated), in the kind's unit."""

    value: float
    bias: float
    std: float
    std_image: float
    std_calibration: float
    std_model: float = math.nan

    @property
    def ci95(self) -> float:
        """Half-width of the 95 % interval, ``Z95 std``."""
        return Z95 * self.std

    @property
    def relative_percent(self) -> float:
        """The accuracy index (:func:`accuracy_index`), percent."""
        return accuracy_index(self.value, self.bias, self.std)

    @classmethod
    def of(cls, pred: Propagation, index: int = 0) -> PredictedError:
        """Measurement ``index`` of a propagation (parts it did not compute are NaN)."""
        std = float(pred.std[index])
        parts = {k: float(v[1][index]) for k, v in pred.parts.items()}
        return cls(
            float(pred.value[index]),
            float(pred.bias[index]),
            std,
            parts.get("image", math.nan),
            parts.get("calibration", math.nan),
            parts.get("model", math.nan),
        )

    def to_dict(self) -> dict[str, float]:
        return {
            "value": self.value,
            "bias": self.bias,
            "std": self.std,
            "std_image": self.std_image,
            "std_calibration": self.std_calibration,
            "std_model": self.std_model,
            "ci95": self.ci95,
            "relative_percent": self.relative_percent,
        }


def measurement_function(
    model: CameraModel,
    kind: str,
    n_points: int,
    *,
    with_params: bool = False,
    with_offsets: bool = False,
    plane: bool = False,
) -> MeasurementFunction:
    """The black box ``f`` of a measurement kind (see :class:`MeasurementFunction`).

    With ``plane``, ``n_points`` counts the kind's points after the
    :data:`~endomeasure.measure.kinds.PLANE_POINTS` of a measurement plane, which come
    first in the inputs; the kind's :func:`~endomeasure.measure.kinds.projected_points`
    are placed on that plane.
    """
    spec = kind_spec(kind)
    if n_points < spec.min_points or (spec.max_points is not None and n_points > spec.max_points):
        raise BadInputError(
            f"{kind} cannot be measured from {n_points} points",
            hint=f"{kind} needs {spec.min_points}"
            + ("" if spec.max_points == spec.min_points else " or more")
            + " points",
        )
    if not plane:
        return MeasurementFunction(
            model, spec.function, n_points, with_params=with_params, with_offsets=with_offsets
        )
    on_plane = np.concatenate([np.zeros(PLANE_POINTS, bool), projected_points(kind, n_points)])

    def on_the_plane(points: np.ndarray) -> np.ndarray:
        return spec.function(points[..., PLANE_POINTS:, :])

    return MeasurementFunction(model, on_the_plane, PLANE_POINTS + n_points,
                               with_params=with_params, with_offsets=with_offsets,
                               on_plane=on_plane)  # fmt: skip


def predict_measurement_error(
    model: CameraModel,
    kind: str,
    pixels_left: np.ndarray,
    pixels_right: np.ndarray,
    *,
    noise: ImageNoise,
    param_cov: np.ndarray | None = None,
    misfit: ModelMisfit | None = None,
    method: str = "ut",
    plane: bool = False,
    **options,
) -> Propagation:
    """Predicted bias and standard deviation of measurements from their pixels.

    Parameters
    ----------
    model : CameraModel
    kind : str
        Measurement kind.
    pixels_left, pixels_right : ndarray, shape (n, 2) or (M, n, 2), px
        The measurements' points in each half.
    noise : ImageNoise
        The image noise of the pixels (e.g. ``ImageNoise(0.05)``).
    param_cov : ndarray, shape (F, F), optional
        Covariance of the model's free parameters (F = ``model.free_mask.sum()``);
        without it only image noise is propagated.
    misfit : ModelMisfit, optional
        The calibration's model misfit, propagated as the input block ``model`` (when it
        is present).
    method : {'ut', 'linear', 'mc'}
    plane : bool
        A measurement plane (:mod:`endomeasure.measure.kinds`): the first
        :data:`~endomeasure.measure.kinds.PLANE_POINTS` pixels are the plane's points,
        the rest the kind's; the right pixels of the points placed on the plane are not
        used (they may be NaN) and should carry no noise.
    **options
        Passed to the propagator (``alpha``, ``beta``, ``kappa``; ``n_samples``,
        ``seed``, ``parts``; ``step``; ``cross``). The UT adds cross points on the
        pixels of measurements of three or more points, which make the variance
        second-order exact for any curvature of the measurement (so no per-kind beta).

    Returns
    -------
    Propagation
        Shape (M,), or (1,) for a single measurement.
    """
    ql = np.asarray(pixels_left, dtype=np.float64)
    if ql.ndim == 2:
        ql = ql[None]
        pixels_right = np.asarray(pixels_right, dtype=np.float64)[None]
    n = ql.shape[-2]
    qr = np.asarray(pixels_right, dtype=np.float64)
    n_kind = n - PLANE_POINTS if plane else n
    if param_cov is not None:
        f_free = int(model.free_mask.sum())
        if np.shape(param_cov) != (f_free, f_free):
            raise BadInputError(
                f"the parameter covariance must be {f_free}x{f_free} for the {model.NAME} "
                f"model's free parameters, got {np.shape(param_cov)}"
            )
    offsets = misfit is not None and misfit.present
    f = measurement_function(model, kind, n_kind, with_params=param_cov is not None,
                             with_offsets=offsets, plane=plane)  # fmt: skip
    # an unused right pixel: any finite value (the left one) keeps the inputs finite
    qr = np.where(f.on_plane[:, None], ql, qr)
    cov, blocks = noise.covariance(n, param_cov, misfit.covariance(ql) if offsets else None)
    return propagate(f, f.inputs(ql, qr), cov, method, blocks=blocks, **options)


# ----- error maps over the working volume ----------------------------------------------------

TEMPLATES: dict[str, tuple[str, np.ndarray]] = {
    # name: (kind, point offsets in units of the template size, relative to the centre)
    "x-segment": ("length", np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])),
    "y-segment": ("length", np.array([[0.0, -0.5, 0.0], [0.0, 0.5, 0.0]])),
    "z-segment": ("length", np.array([[0.0, 0.0, -0.5], [0.0, 0.0, 0.5]])),
    "point-plane": (
        "depth",
        np.array([[0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0], [-0.5, -0.5, 0.0]]),
    ),
    "area": (
        "area",
        np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]]),
    ),
}
"""Measurement templates for error maps: segments of the template size along x, y, z; a
square of that side facing the probe, measured as a point-to-plane distance (one corner
against the plane of the other three, as in the board test) or as an area."""


def template_points(template: str, centres: np.ndarray, size_mm: float = 1.0) -> np.ndarray:
    """The points of a template centred at each centre, shape (K, n, 3), mm."""
    if template not in TEMPLATES:
        raise BadInputError(
            f"unknown map template {template!r}", hint=f"use one of {', '.join(TEMPLATES)}"
        )
    if not (np.isfinite(size_mm) and size_mm > 0):
        raise BadInputError(f"the template size must be a positive number of mm, got {size_mm}")
    _, offsets = TEMPLATES[template]
    return np.asarray(centres, dtype=np.float64)[..., None, :] + size_mm * offsets


def volume_grid(
    model: CameraModel,
    depths: np.ndarray,
    n_u: int = 40,
    n_v: int = 30,
    margin_px: float = 10.0,
) -> np.ndarray:
    """Grid points of the working volume seen by both halves.

    Parameters
    ----------
    model : CameraModel
    depths : ndarray, shape (D,), mm
        Planes ``z = depth``.
    n_u, n_v : int
        Pixels per row and column of a regular grid over the left half (inset by
        ``margin_px``); each pixel's ray is cut with every depth plane.
    margin_px : float

    Returns
    -------
    ndarray, shape (K, 3), mm
        Ordered depth-major; only points the right half sees too (K <= D n_u n_v).
    """
    width, height = model.config.image_size
    u = np.linspace(margin_px, model.config.split - 1 - margin_px, n_u)
    v = np.linspace(margin_px, height - 1 - margin_px, n_v)
    q = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    rays = model.rays(q, "left")
    depths = np.asarray(depths, dtype=np.float64).reshape(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (depths[:, None] - rays.origins[None, :, 2]) / rays.directions[None, :, 2]
    p = (rays.origins[None] + s[..., None] * rays.directions[None]).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1) & (s.reshape(-1) > 0)]
    return p[model.project(p, "right").status == Status.OK]


class PredictedErrors(NamedTuple):
    """:class:`PredictedError` for many measurements at once: arrays (M,) in the kinds'
    units, NaN where a measurement was not predicted."""

    value: np.ndarray
    bias: np.ndarray
    std: np.ndarray
    std_image: np.ndarray
    std_calibration: np.ndarray
    std_model: np.ndarray

    @classmethod
    def empty(cls, m: int) -> PredictedErrors:
        return cls(*(np.full(m, np.nan) for _ in cls._fields))

    def fill(self, rows, pred: Propagation) -> None:
        """Write a propagation's measurements into ``rows`` (parts it did not compute
        stay NaN)."""
        self.value[rows], self.bias[rows], self.std[rows] = pred.value, pred.bias, pred.std
        if "image" in pred.parts:
            self.std_image[rows] = pred.parts["image"][1]
        for name, out in (("calibration", self.std_calibration), ("model", self.std_model)):
            if name in pred.parts:
                out[rows] = pred.parts[name][1]


ROW_BATCH = 1024
"""Measurements predicted in one call where each has its own input covariance (a model
misfit, a per-image noise): ``(4n + F)^2`` values each (F free parameters), so a batch
holds some tens of MB, whatever the number of measurements."""


class ErrorMap(NamedTuple):
    """Predicted error of a template measurement at each grid point (arrays (K,))."""

    centres: np.ndarray  # (K, 3) mm
    true: float  # the template's true value (mm or mm^2)
    visible: np.ndarray  # (K,) bool: all template points seen in both halves
    errors: PredictedErrors  # (K,) each; value: the noise-free measurement (``true`` up to
    # the model); std_calibration NaN without param_cov; NaN where not visible
    template: str
    size_mm: float


def error_map(
    model: CameraModel,
    centres: np.ndarray,
    template: str = "x-segment",
    size_mm: float = 1.0,
    *,
    noise: ImageNoise,
    param_cov: np.ndarray | None = None,
    misfit: ModelMisfit | None = None,
    method: str = "ut",
    **options,
) -> ErrorMap:
    """Predicted uncertainty of a template measurement over the working volume.

    Parameters
    ----------
    model : CameraModel
        A calibrated model or a design with nominal parameters.
    centres : ndarray, shape (K, 3), mm
        Where to place the template (e.g. :func:`volume_grid`).
    template : str
        One of :data:`TEMPLATES`.
    size_mm : float
        Template size (segment length, square side).
    noise, param_cov, misfit, method, **options
        As in :func:`predict_measurement_error`; a misfit makes every template's input
        covariance its own, so the templates go in batches of :data:`ROW_BATCH`.

    Returns
    -------
    ErrorMap
        Templates with a point outside either half are NaN and not visible.
    """
    kind, _ = TEMPLATES.get(template, (None, None))
    pts = template_points(template, centres, size_mm)
    K, n, _ = pts.shape
    pl = model.project(pts, "left")
    pr = model.project(pts, "right")
    visible = np.all((pl.status == Status.OK) & (pr.status == Status.OK), axis=1)
    true = float(evaluate(kind, template_points(template, np.zeros((1, 3)), size_mm))[0])
    errors = PredictedErrors.empty(K)
    rows = np.flatnonzero(visible)
    step = ROW_BATCH if misfit is not None and misfit.present else max(rows.size, 1)
    for start in range(0, rows.size, step):
        batch = rows[start : start + step]
        res = predict_measurement_error(
            model, kind, pl.pixels[batch], pr.pixels[batch], noise=noise,
            param_cov=param_cov, misfit=misfit, method=method, **options,
        )  # fmt: skip
        errors.fill(batch, res)
    centres = np.asarray(centres, dtype=np.float64)
    return ErrorMap(centres, true, visible, errors, template, float(size_mm))
