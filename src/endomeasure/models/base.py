"""The contract every camera model of the split-sensor probe fulfils.

A model is an immutable object: a flat float64 parameter vector with names
(``PARAM_NAMES``), read-only named views, and a separate :class:`ModelConfig` of fixed
values (image size, split column, which parameters calibration holds fixed). It answers
two vectorised questions per half (SPEC section 4):

- :meth:`CameraModel.rays` — backward: the ray in space each pixel sees, with its own
  origin (models may be non-central);
- :meth:`CameraModel.project` — forward: the pixel where each 3D point lands, with a
  per-point :class:`~endomeasure.conventions.Status`.

Points are in the model's reference frame (mm), pixels in full-image coordinates.

Everything else a solver needs is part of the contract too, so solvers and pipelines
never ask a model's name: the Jacobians with respect to points and parameters
(:meth:`CameraModel.project_jacobians`), a :class:`~endomeasure.models.projector.Projector`
that may keep warm-start state during an optimisation (:meth:`CameraModel.projector`),
parameter units (``PARAM_UNITS``), and where the model's calibration starts from
(``SEEDED_FROM``; the start itself is registered with the model, see
:mod:`endomeasure.models.registry` and :mod:`endomeasure.models.start`).
"""

from __future__ import annotations

import abc
import dataclasses
import json
from typing import Any, ClassVar, NamedTuple

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Half, Status, in_half
from endomeasure.models.projector import Projector

__all__ = [
    "CameraModel",
    "ModelConfig",
    "ParamBatch",
    "Projection",
    "ProjectionJacobian",
    "ProjectionJacobians",
    "OpenCVStereo",
    "Rays",
    "FD_STEP_PARAM",
    "FD_STEP_POINT",
    "finite_difference",
]

FD_STEP_PARAM = 1e-6
"""Relative central-difference step for model parameters (times ``max(1, |value|)``):
truncation error ~h^2 times the third derivative, rounding ~eps/h, both ~1e-10
relative, far below what a covariance needs."""
FD_STEP_POINT = 1e-6
"""The same relative step for point coordinates (times ``max(1, |coordinate|)``, mm)."""


class Rays(NamedTuple):
    origins: np.ndarray  # (..., 3) mm
    directions: np.ndarray  # (..., 3) unit
    status: np.ndarray  # (...,) uint8 Status


class Projection(NamedTuple):
    pixels: np.ndarray  # (..., 2) px, NaN where status != OK
    status: np.ndarray  # (...,) uint8 Status


class ProjectionJacobian(NamedTuple):
    pixels: np.ndarray  # (..., 2) px
    status: np.ndarray  # (...,) uint8 Status
    dq_dp: np.ndarray  # (..., 2, 3) px/mm: d pixel / d point, NaN where status != OK


class ProjectionJacobians(NamedTuple):
    pixels: np.ndarray  # (..., 2) px
    status: np.ndarray  # (...,) uint8 Status
    dq_dp: np.ndarray  # (..., 2, 3) px/mm, NaN where status != OK
    dq_dparams: np.ndarray  # (..., 2, F) px per parameter unit, NaN where status != OK


class OpenCVStereo(NamedTuple):
    """A model as OpenCV's stereo pair (``cv2.stereoCalibrate`` conventions)."""

    M1: np.ndarray  # (3, 3) left camera matrix, full-image pixels
    D1: np.ndarray  # (5,) k1 k2 p1 p2 k3
    M2: np.ndarray  # (3, 3) right camera matrix
    D2: np.ndarray  # (5,)
    R: np.ndarray  # (3, 3) T_right_left rotation
    T: np.ndarray  # (3,) mm


class ParamBatch(NamedTuple):
    """Parameter vectors of one model kind for a batch of items (pixels, correspondences):
    a few distinct vectors and, per item, which one it uses.

    What :meth:`CameraModel.rays` and
    :func:`~endomeasure.solvers.triangulate.triangulate` take as ``params`` to work
    under many models at once (e.g. the sigma points of a calibration covariance), with
    the per-vector work (validity, faces, fold-back radius) done once per vector.
    """

    table: np.ndarray
    """(K, P) the distinct parameter vectors."""
    index: np.ndarray | None
    """(...) int: the row of ``table`` of each item (None: a one-row table for all)."""

    @classmethod
    def of(cls, params: np.ndarray | ParamBatch) -> ParamBatch:
        """A batch from one parameter vector per item, ``params`` (..., P)."""
        if isinstance(params, ParamBatch):
            return params
        p = np.asarray(params, dtype=np.float64)
        table, index = np.unique(p.reshape(-1, p.shape[-1]), axis=0, return_inverse=True)
        return cls(table, index.reshape(p.shape[:-1]))

    @classmethod
    def for_items(cls, params: np.ndarray | ParamBatch, shape: tuple, size: int) -> ParamBatch:
        """:meth:`of`, checked against items of leading shape ``shape`` and vectors of
        ``size`` parameters, with the index flattened (ValueError when they differ)."""
        batch = cls.of(params)
        if batch.index is None and batch.table.shape[0] == 1:  # one vector for every item
            batch = cls(batch.table, np.zeros(tuple(shape), dtype=np.int64))
        if (
            batch.index is None
            or batch.index.shape != tuple(shape)
            or batch.table.shape[1:] != (size,)
        ):
            raise ValueError(
                f"params must have shape {(*shape, size)}, got a batch of "
                f"{getattr(batch.index, 'shape', None)} vectors of {batch.table.shape[1:]}"
            )
        return cls(batch.table, batch.index.reshape(-1))

    def take(self, items) -> ParamBatch:
        """The batch of a selection of the items (any numpy index of ``index``); a batch
        of one shared vector (``index`` None) stays one."""
        return self if self.index is None else ParamBatch(self.table, self.index[items])

    def per_item(self, j: int) -> float | np.ndarray:
        """Parameter ``j`` of every item: a float when the batch holds one vector."""
        if self.table.shape[0] == 1:
            return float(self.table[0, j])
        return self.table[self.index, j]


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Fixed values of a model that are not estimated.

    Attributes
    ----------
    image_size : (int, int)
        ``(width, height)`` of the whole sensor image, px.
    split : int
        First column of the right half.
    fixed : frozenset of str
        Names of parameters that calibration holds at their current values.
    """

    image_size: tuple[int, int]
    split: int
    fixed: frozenset[str] = frozenset()

    def __post_init__(self):
        width, height = (int(v) for v in self.image_size)
        object.__setattr__(self, "image_size", (width, height))
        object.__setattr__(self, "split", int(self.split))
        object.__setattr__(self, "fixed", frozenset(self.fixed))
        if not (width > 0 and height > 0 and 0 < self.split < width):
            raise ValueError(
                f"image size {width}x{height} with split column {self.split} is not valid"
            )

    def with_fixed(self, fixed) -> ModelConfig:
        """The same image geometry with other fixed parameters."""
        return dataclasses.replace(self, fixed=frozenset(fixed))

    def to_dict(self) -> dict[str, Any]:
        return {
            "image_size": list(self.image_size),
            "split": self.split,
            "fixed": sorted(self.fixed),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelConfig:
        return cls(tuple(data["image_size"]), int(data["split"]), frozenset(data.get("fixed", ())))


@dataclasses.dataclass(frozen=True, eq=False)
class CameraModel(abc.ABC):
    """Base class of camera models; see the module docstring.

    Subclasses define ``NAME``, ``PARAM_NAMES``, ``PARAM_UNITS``, ``GROUPS`` (name ->
    slice of ``params``), ``DEFAULT_FIXED``, ``SEEDED_FROM``, and implement :meth:`_rays`
    and :meth:`_project` for one half on flat arrays.
    Optional, with generic defaults: :meth:`_constraints` (valid parameter values),
    :meth:`_rays_rows` (one parameter vector per pixel), closed-form Jacobians
    (:meth:`_project_jacobian`, :meth:`_project_jacobians`) and ``PROJECTOR``.
    """

    params: np.ndarray
    config: ModelConfig

    NAME: ClassVar[str]
    PARAM_NAMES: ClassVar[tuple[str, ...]]
    PARAM_UNITS: ClassVar[dict[str, str]]
    """Unit of each parameter by name: ``px``, ``mm``, ``rad`` or ``1``."""
    GROUPS: ClassVar[dict[str, slice]] = {}
    DEFAULT_FIXED: ClassVar[frozenset[str]] = frozenset()
    EXTENSIONS: ClassVar[tuple[tuple[str, ...], ...]] = ()
    """Groups of ``DEFAULT_FIXED`` parameters that calibration may free when the data
    call for them (tried in this order, each kept only if held-out images or the
    information criterion say it helps; see ``solvers.calibrate``)."""
    ABSORBED_EXTENSIONS: ClassVar[tuple[tuple[str, ...], ...]] = ()
    """Groups of ``EXTENSIONS`` whose effect the other parameters absorb without a trace
    in the residuals while it moves every absolute position (a moving entrance pupil
    against the face distances shifts the frame's origin along the axis): held by a fit,
    their uncertainty stays in the covariance measurements use
    (``CalibrationResult.uncertain``)."""
    SEEDED_FROM: ClassVar[str | None] = None
    """Registry name of the model whose calibration this one's start is built from;
    None: the start is built from the detections alone."""
    PROJECTOR: ClassVar[type[Projector]] = Projector

    def __post_init__(self):
        params = np.array(self.params, dtype=np.float64).reshape(-1)
        if params.shape != (len(self.PARAM_NAMES),):
            raise ValueError(
                f"{self.NAME} model needs {len(self.PARAM_NAMES)} parameters, got {params.size}"
            )
        if not np.all(np.isfinite(params)):
            raise ValueError(f"{self.NAME} model parameters must be finite")
        unknown = set(self.config.fixed) - set(self.PARAM_NAMES)
        if unknown:
            raise ValueError(f"unknown fixed parameter(s) {sorted(unknown)} for {self.NAME}")
        params.flags.writeable = False
        object.__setattr__(self, "params", params)
        for holds, message in self._constraints(params):
            if not holds:
                raise ValueError(message)

    @classmethod
    def _constraints(cls, params: np.ndarray) -> list[tuple[np.ndarray, str]]:
        """Subclass hook: the rules valid parameter vectors ``params`` (..., P) obey, as
        ``(holds, message)`` pairs with ``holds`` of shape (...)."""
        return []

    @classmethod
    def valid_params(cls, params: np.ndarray) -> np.ndarray:
        """Whether each parameter vector (..., P) makes a valid model, shape (...)."""
        params = np.asarray(params, dtype=np.float64)
        ok = np.all(np.isfinite(params), axis=-1)
        for holds, _ in cls._constraints(params):
            ok &= holds
        return ok

    # ----- named access -------------------------------------------------------------
    @classmethod
    def index(cls, name: str) -> int:
        """Position of a parameter in ``params``."""
        try:
            return cls.PARAM_NAMES.index(name)
        except ValueError:
            raise KeyError(f"{cls.NAME} has no parameter {name!r}") from None

    @classmethod
    def column(cls, params: np.ndarray, name: str) -> np.ndarray:
        """The values of one named parameter in parameter vectors ``params`` (..., P)."""
        return params[..., cls.index(name)]

    @classmethod
    def unit(cls, name: str) -> str:
        """Unit of a named parameter (``px``, ``mm``, ``rad`` or ``1``)."""
        cls.index(name)
        return cls.PARAM_UNITS[name]

    def __getattr__(self, name: str):
        # only reached when normal lookup fails: named parameters and groups
        names = type(self).PARAM_NAMES
        if name in names:
            return float(self.params[names.index(name)])
        groups = type(self).GROUPS
        if name in groups:
            return self.params[groups[name]]  # read-only view
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")

    def named_params(self) -> dict[str, float]:
        return dict(zip(self.PARAM_NAMES, self.params.tolist(), strict=True))

    @property
    def free_mask(self) -> np.ndarray:
        """Boolean mask of the parameters calibration estimates, shape (P,)."""
        return np.array([n not in self.config.fixed for n in self.PARAM_NAMES])

    def with_params(self, params: np.ndarray) -> CameraModel:
        """A new model of the same kind and configuration with other parameters."""
        return dataclasses.replace(self, params=np.asarray(params, dtype=np.float64))

    def with_values(self, values: dict[str, float]) -> CameraModel:
        """A new model with the named parameters of ``values`` that it has set."""
        p = self.params.copy()
        for name, value in values.items():
            if name in self.PARAM_NAMES:
                p[self.index(name)] = value
        return self.with_params(p)

    def with_config(self, **changes) -> CameraModel:
        return dataclasses.replace(self, config=dataclasses.replace(self.config, **changes))

    # ----- plain-data round trip ----------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON-ready description: registry name, names, values, configuration."""
        return {
            "model": self.NAME,
            "param_names": list(self.PARAM_NAMES),
            "params": self.params.tolist(),
            "config": self.config.to_dict(),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CameraModel:
        """The model of a :meth:`to_dict` description, also one written by an earlier
        version: values are matched by name, and extension parameters the description
        lacks (``EXTENSIONS``, all neutral at 0) are 0 and held fixed, so the stored
        model projects as it did. Any other mismatch is a ValueError."""
        if data.get("model") != cls.NAME:
            raise ValueError(f"expected a {cls.NAME!r} model, got {data.get('model')!r}")
        names = tuple(data.get("param_names", cls.PARAM_NAMES))
        values = np.asarray(data["params"], dtype=np.float64).reshape(-1)
        config = ModelConfig.from_dict(data["config"])
        if names == cls.PARAM_NAMES:
            return cls(values, config)
        extensions = {name for group in cls.EXTENSIONS for name in group}
        missing = set(cls.PARAM_NAMES) - set(names)
        if (
            len(set(names)) != len(names)
            or values.shape != (len(names),)
            or not set(names) <= set(cls.PARAM_NAMES)
            or not missing <= extensions
        ):
            raise ValueError(f"parameter names of the {cls.NAME} model do not match this version")
        given = dict(zip(names, values.tolist(), strict=True))
        params = np.array([given.get(name, 0.0) for name in cls.PARAM_NAMES])
        return cls(params, config.with_fixed(config.fixed | missing))

    # ----- the two questions ----------------------------------------------------------
    def rays(
        self, pixels: np.ndarray, half: Half | str, params: np.ndarray | ParamBatch | None = None
    ) -> Rays:
        """Backward: the ray each pixel of a half sees.

        Parameters
        ----------
        pixels : ndarray, shape (..., 2), px
            Full-image pixel coordinates.
        half : Half or {'left', 'right'}
        params : ndarray, shape (..., P), or ParamBatch with index of shape (...), optional
            A parameter vector per pixel instead of the model's own: traces a batch of
            models of this kind and configuration at once. Pixels with an invalid vector
            (:meth:`valid_params`) get ``INVALID_INPUT``.

        Returns
        -------
        Rays
            Origins (mm) and unit directions in the model frame. Pixels outside the
            half, NaN input or failed inversions get NaN rays and a status.
        """
        half = Half.parse(half)
        flat, shape, status = _flat_input(pixels, 2, "pixels")
        finite = status == Status.OK
        inside = in_half(flat, half, self.config.split, self.config.image_size)
        status[finite & ~inside] = Status.OUTSIDE_HALF
        batch = None
        if params is not None:
            batch = ParamBatch.for_items(params, shape, self.params.size)
            valid = self.valid_params(batch.table)[batch.index]
            status[(status == Status.OK) & ~valid] = Status.INVALID_INPUT
        origins = np.full((flat.shape[0], 3), np.nan)
        directions = np.full((flat.shape[0], 3), np.nan)
        todo = np.flatnonzero(status == Status.OK)
        if todo.size:
            if batch is None:
                o, d, s = self._rays(flat[todo], half)
            else:
                o, d, s = self._rays_rows(flat[todo], half, batch.take(todo))
            origins[todo], directions[todo], status[todo] = o, d, s
        bad = status != Status.OK
        origins[bad] = np.nan
        directions[bad] = np.nan
        return Rays(
            origins.reshape(*shape, 3), directions.reshape(*shape, 3), status.reshape(shape)
        )

    def project(self, points: np.ndarray, half: Half | str) -> Projection:
        """Forward: the pixel where each 3D point lands in a half.

        Parameters
        ----------
        points : ndarray, shape (..., 3), mm
            Points in the model frame.
        half : Half or {'left', 'right'}

        Returns
        -------
        Projection
            Pixels (px) and a status per point; every non-OK point is NaN, so a
            projection is either right or visibly absent.
        """
        return Projection(*self._forward(points, half, self._project))

    def project_jacobian(self, points: np.ndarray, half: Half | str) -> ProjectionJacobian:
        """:meth:`project` and the derivative of each pixel with respect to its point.

        Returns
        -------
        ProjectionJacobian
            ``dq_dp`` has shape (..., 2, 3), px/mm, NaN where status is not OK.
        """
        return ProjectionJacobian(*self._forward(points, half, self._project_jacobian, (2, 3)))

    def project_jacobians(
        self, points: np.ndarray, half: Half | str, free: np.ndarray | None = None
    ) -> ProjectionJacobians:
        """:meth:`project_jacobian` and the derivatives with respect to the parameters.

        Parameters
        ----------
        points : ndarray, shape (..., 3), mm
        half : Half or {'left', 'right'}
        free : ndarray of int, shape (F,), optional
            Positions in ``params`` to differentiate by (default: all ``P``).

        Returns
        -------
        ProjectionJacobians
            ``dq_dparams`` has shape (..., 2, F), px per parameter unit; both Jacobians
            are NaN where status is not OK.
        """
        free = np.arange(self.params.size) if free is None else np.asarray(free)
        if free.dtype == bool:
            raise TypeError("free must hold parameter positions, not a mask (np.flatnonzero)")
        free = free.astype(np.int64)

        def evaluate(flat, half):
            return self._project_jacobians(flat, half, free)

        return ProjectionJacobians(*self._forward(points, half, evaluate, (2, 3), (2, free.size)))

    def _forward(self, points, half, evaluate, *extra_shapes: tuple[int, ...]) -> tuple:
        """``evaluate(flat_points, half) -> (pixels, status, *extras)`` on the finite
        points of ``points`` (..., 3), then :meth:`valid_projection`; every output NaN
        where the status is not OK, shaped like the input."""
        half = Half.parse(half)
        flat, shape, status = _flat_input(points, 3, "points")
        pixels = np.full((flat.shape[0], 2), np.nan)
        extras = [np.full((flat.shape[0], *e), np.nan) for e in extra_shapes]
        todo = _todo(status)
        if flat[todo].size:
            pixels[todo], status[todo], *values = evaluate(flat[todo], half)
            for out, value in zip(extras, values, strict=True):
                out[todo] = value
        pixels, status = self.valid_projection(pixels, status, half)
        bad = status != Status.OK
        for out in extras:
            out[bad] = np.nan
        return (
            pixels.reshape(*shape, 2),
            status.reshape(shape),
            *(out.reshape(*shape, *e) for out, e in zip(extras, extra_shapes, strict=True)),
        )

    def valid_projection(
        self, pixels: np.ndarray, status: np.ndarray, half: Half
    ) -> tuple[np.ndarray, np.ndarray]:
        """The one rule of a valid projection, applied to a model's raw output.

        ``pixels`` (N, 2) float64 and ``status`` (N,) uint8, as :meth:`_project` returns
        them: an OK pixel outside its half becomes ``OUTSIDE_HALF``, and every pixel whose
        status is not OK is NaN. Changes both arrays in place and returns them.
        """
        ok = status == Status.OK
        inside = in_half(pixels, half, self.config.split, self.config.image_size)
        status[ok & ~inside] = Status.OUTSIDE_HALF
        pixels[status != Status.OK] = np.nan
        return pixels, status

    def opencv_stereo(self) -> OpenCVStereo | None:
        """The model as OpenCV's stereo pair, or None when it has no such equivalent."""
        return None

    def projector(self, halves: np.ndarray, state: np.ndarray | None = None) -> Projector:
        """The solver-side projector of this model kind over observations in ``halves``
        (N,), warm-started from a previous projector's ``state``."""
        return self.PROJECTOR(self, halves, state)

    def _project_jacobian(self, points: np.ndarray, half: Half):
        """Default: central differences of :meth:`_project`; models override it with
        closed forms. Returns pixels (N, 2), status (N,), dq_dp (N, 2, 3)."""
        pixels, status = self._project(points, half)
        step = FD_STEP_POINT * np.maximum(1.0, np.abs(points))
        dq_dp = np.empty((points.shape[0], 2, 3))
        for axis in range(3):
            offset = np.zeros_like(points)
            offset[:, axis] = step[:, axis]
            plus, st_p = self._project(points + offset, half)
            minus, st_m = self._project(points - offset, half)
            dq_dp[:, :, axis] = (plus - minus) / (2.0 * step[:, axis, None])
            status = np.where((status == Status.OK) & ((st_p != Status.OK) | (st_m != Status.OK)),
                              Status.NOT_CONVERGED, status)  # fmt: skip
        return pixels, status, dq_dp

    def _project_jacobians(self, points: np.ndarray, half: Half, free: np.ndarray):
        """Default: :meth:`_project_jacobian` and central differences of :meth:`_project`
        over the parameters ``free``, one-sided at the edge of the valid domain.
        Returns pixels (N, 2), status (N,), dq_dp (N, 2, 3), dq_dparams (N, 2, F)."""
        pixels, status, dq_dp = self._project_jacobian(points, half)
        dq_dparams = np.empty((points.shape[0], 2, free.size))
        for k, i in enumerate(free):
            step = FD_STEP_PARAM * max(1.0, abs(float(self.params[i])))
            plus, minus = (self._stepped_pixels(points, half, i, sign * step) for sign in (1, -1))
            dq_dparams[:, :, k] = finite_difference(plus, pixels, minus, step)
        return pixels, status, dq_dp, dq_dparams

    def _stepped_pixels(self, points, half, i: int, step: float) -> np.ndarray | None:
        """:meth:`_project` with parameter ``i`` moved by ``step``; None when that leaves
        the valid domain."""
        p = self.params.copy()
        p[i] += step
        return self.with_params(p)._project(points, half)[0] if self.valid_params(p) else None

    @abc.abstractmethod
    def _rays(self, pixels: np.ndarray, half: Half) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays of finite pixels inside the half, shape (N, 2) -> (N,3), (N,3), (N,)."""

    def _rays_rows(self, pixels: np.ndarray, half: Half, batch: ParamBatch):
        """:meth:`_rays` with a valid parameter vector per pixel (``batch.index`` (N,)).

        Default: one :meth:`_rays` call per vector used; models override it with one
        vectorised pass.
        """
        origins = np.empty((pixels.shape[0], 3))
        directions = np.empty((pixels.shape[0], 3))
        status = np.empty(pixels.shape[0], dtype=STATUS_DTYPE)
        for k in np.unique(batch.index):
            mine = np.flatnonzero(batch.index == k)
            o, d, s = self.with_params(batch.table[k])._rays(pixels[mine], half)
            origins[mine], directions[mine], status[mine] = o, d, s
        return origins, directions, status

    @abc.abstractmethod
    def _project(self, points: np.ndarray, half: Half) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of finite points, shape (N, 3) -> (N, 2), (N,), with the model's own
        failures as status (behind, fold-back, lost in the prism, no convergence); the
        half rule is :meth:`valid_projection`'s."""


def finite_difference(plus, centre, minus, step: float):
    """Central difference of values at ``+-step`` (one-sided where a side is None: it left
    the valid domain; NaN where both did)."""
    if plus is not None and minus is not None:
        return (plus - minus) / (2.0 * step)
    if plus is not None:
        return (plus - centre) / step
    if minus is not None:
        return (centre - minus) / step
    return np.full_like(centre, np.nan)


def _todo(status: np.ndarray):
    """Rows still OK after the input check: a slice when all are (no gather copies)."""
    todo = np.flatnonzero(status == Status.OK)
    return slice(None) if todo.size == status.size else todo


def _flat_input(values, width: int, name: str) -> tuple[np.ndarray, tuple, np.ndarray]:
    """``values (..., width)`` as float64 rows ``(N, width)``, the leading shape, and a
    status per row (``INVALID_INPUT`` where any entry is NaN or infinite)."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape[-1:] != (width,):
        raise ValueError(f"{name} must have shape (..., {width}), got {values.shape}")
    flat = values.reshape(-1, width)
    status = np.full(flat.shape[0], Status.OK, dtype=STATUS_DTYPE)
    status[~np.all(np.isfinite(flat), axis=-1)] = Status.INVALID_INPUT
    return flat, values.shape[:-1], status
