"""Calibration of a split-sensor camera model from images of flat targets (SPEC 6).

:func:`calibrate` fits the free parameters of a camera model and one board pose per
image by bundle adjustment (:mod:`endomeasure.solvers.bundle`): the reprojection error
in pixels over every detected corner of every image in both halves, the same cost for
every model, so models are compared on the same footing.

The start is the model's own (registered with it, :func:`~endomeasure.models.model_start`):
a model built from the detections alone (``SEEDED_FROM`` None) gets one joint pass
before the outlier rule sees it; a model seeded from another one is started from that
model's refined calibration, which is computed first (or taken from ``start``). No
prism design data is needed, and no model is known here by name.

Refusals (:class:`~endomeasure.errors.CalibrationError`): too few images or corners,
degenerate geometry (all boards parallel, or all at one distance), an optimiser that
does not converge, a covariance that is singular (naming the undetermined parameters).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from endomeasure.conventions import Half, in_half
from endomeasure.errors import BadInputError, CalibrationError
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.models import CameraModel, ModelConfig, model_class, model_start
from endomeasure.models.start import Observations, Start, StartContext
from endomeasure.solvers.bundle import (
    NUMERICAL_FLOOR_PX,
    OUTLIER_FLOOR_PX,
    BundleProblem,
    all_residuals,
    fit_with_outliers,
    gauss_newton_step,
    refine,
)
from endomeasure.solvers.covariance import marginal_covariance
from endomeasure.solvers.verdict import MIN_CORRELATION_EIGENVALUE, Verdict, judge

__all__ = [
    "ViewDetections",
    "CalibrationOptions",
    "CalibrationResult",
    "calibrate",
    "MIN_IMAGES",
    "MIN_CORNERS_PER_HALF",
    "MIN_STEREO_IMAGES",
    "MIN_TILT_SPREAD_DEG",
    "MIN_DISTANCE_RATIO",
    "OUTLIER_FLOOR_PX",
]

MIN_CORNERS_PER_HALF = 6
"""A half-view with fewer corners is not used: a plane pose needs four points and
OpenCV's per-half initialisation needs a few more to be stable."""
MIN_IMAGES = 4
"""Images (with at least one usable half) needed: 4 is the fewest for which the
per-half initialisation and the joint fit are over-determined with margin."""
MIN_STEREO_IMAGES = 2
"""Images seen in both halves, to tie the halves together (the relative pose)."""
MIN_TILT_SPREAD_DEG = 10.0
"""Boards whose apparent normals (see ``_apparent_tilt_spread``) all lie within this
angle count as parallel: the focal length then trades against the distance (Zhang 2000,
section 3.3). Lens and prism distortion give truly parallel boards a few degrees of
apparent spread; the limit sits above that and far below the paper's +-30 degrees."""
MIN_DISTANCE_RATIO = 1.15
"""Boards whose farthest distance is less than this ratio times the nearest count as
one distance: the prism's non-central geometry needs a range of depths."""
MIN_PROJECTED_FRACTION = 0.5
"""A fit that seeds another one must project at least this share of the corners (the
rest, e.g. corners a pinhole pair places across the split, the next fit judges)."""
CONVERGED_RMS_LIMIT_PX = 20.0
"""A fit whose RMS stays above this has not found the board geometry (a wrong local
minimum or corrupted detections), whatever the optimiser's status says."""


# ----- inputs -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ViewDetections:
    """The corners of one board detected in one calibration image.

    Attributes
    ----------
    name : str
        Image name.
    board : str
        Key of the board in the ``boards`` mapping passed to :func:`calibrate`.
    ids : (ndarray, ndarray)
        Corner ids (``row * cols + col``) found in the left and in the right half,
        each of shape (n_h,), int.
    pixels : (ndarray, ndarray)
        Their full-image pixel coordinates, each of shape (n_h, 2), px.
    covariance : (ndarray or None, ndarray or None)
        The detector's formal covariance of each corner, shape (n_h, 2, 2), px^2 (NaN
        where unknown; None: none at all): the noise the verdict compares the fit with.
    """

    name: str
    board: str
    ids: tuple[np.ndarray, np.ndarray]
    pixels: tuple[np.ndarray, np.ndarray]
    covariance: tuple[np.ndarray | None, np.ndarray | None] = (None, None)


@dataclasses.dataclass(frozen=True)
class CalibrationOptions:
    """Choices of a calibration.

    Attributes
    ----------
    values : mapping of str to float
        Parameter values to start from and, when fixed, keep (e.g. ``{"n_glass": 1.6}``);
        a model without such a parameter ignores it.
    free : frozenset of str
        Parameters to estimate although the model holds them fixed by default.
    hold : frozenset of str
        Parameters to hold at their values (``values`` or the start's) although the model
        estimates them by default, e.g. a known glass index ``n_glass``.
    seed : mapping or None
        A model dict (:meth:`CameraModel.to_dict`) of the model being calibrated, with
        nominal design values, used by its initialiser instead of the analytic start.
    fixed : frozenset of str or None
        Parameters held fixed, the whole set; None means the model's ``DEFAULT_FIXED``
        and ``hold`` minus ``free``, with the ``EXTENSIONS`` the data call for freed.
    outlier_sigmas : float
        Outlier threshold in robust standard deviations (:mod:`endomeasure.solvers.bundle`).
    max_outlier_rounds : int
    max_nfev : int
        Residual evaluations allowed per optimisation.
    """

    values: Mapping[str, float] = dataclasses.field(default_factory=dict)
    free: frozenset[str] = frozenset()
    hold: frozenset[str] = frozenset()
    seed: Mapping[str, Any] | None = None
    fixed: frozenset[str] | None = None
    outlier_sigmas: float = 5.0
    max_outlier_rounds: int = 3
    max_nfev: int = 500


# ----- the result -------------------------------------------------------------------------


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a)
    a.flags.writeable = False
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationResult:
    """A finished calibration: the fitted model, its uncertainty and its diagnostics.

    Observations are the corners seen in one half of one image, ``M`` of them.

    Attributes
    ----------
    model : CameraModel
        The fitted model.
    free_names : tuple of str, length F
        The estimated parameters (the rest were held fixed).
    covariance : ndarray, shape (F, F)
        Marginal covariance of the free parameters, board poses marginalised out,
        scaled by ``residual_variance`` (parameter units squared).
    residual_variance : float, px^2
        ``s^2 = SSR / (m - n)`` per residual component, over the inlier corners.
    image_names, image_boards : tuple of str, length I
    rvecs, tvecs : ndarray, shape (I, 3)
        Board poses ``T_model_board`` (rotation vector in rad, translation in mm).
    obs_image : ndarray of int, shape (M,)
        Index into ``image_names`` of each observation.
    obs_half : ndarray of int8, shape (M,)
        0 left, 1 right.
    obs_ids : ndarray of int, shape (M,)
    obs_board_points : ndarray, shape (M, 3), mm
        Corner coordinates in the board frame.
    obs_pixels : ndarray, shape (M, 2), px
        Detected pixels.
    residuals : ndarray, shape (M, 2), px
        Projected minus detected pixels for every observation (outliers included).
    inliers : ndarray of bool, shape (M,)
        False for the corners dropped as outliers.
    outlier_threshold_px : float
        The residual length above which corners were dropped.
    status : int
        ``scipy.optimize.least_squares`` status of the final fit (1-4: converged).
    message : str
    nfev : int
        Residual evaluations over all fits of this model.
    rounds : int
        Fits run (1 + outlier rounds that dropped corners).
    skipped_images : tuple of str
        Images not used (too few corners in both halves).
    start : str
        Where the optimisation started from.
    obs_covariance : ndarray, shape (M, 2, 2), px^2
        The detector's formal covariance of every observation (NaN where unknown).
    verdict : Verdict or None
        ok / warning / failed with the reasons (:mod:`endomeasure.solvers.verdict`).
    extensions : tuple of str
        Parameters the model holds fixed by default that the data called for
        (``EXTENSIONS``), freed in this fit.
    selection : tuple of str
        What the extension selection found, one sentence per group tried.
    uncertain : tuple of str
        Extensions the fit held that the data cannot rule out and the other parameters
        absorb (``ABSORBED_EXTENSIONS``, :func:`_with_uncertain_extensions`).
    uncertainty_covariance : ndarray, shape (G, G) or None
        The covariance a measurement's uncertainty uses: that of the free parameters and
        ``uncertain`` together, in the ``free_mask`` order of ``uncertainty_model``
        (None: ``covariance``, nothing uncertain).
    """

    model: CameraModel
    free_names: tuple[str, ...]
    covariance: np.ndarray
    residual_variance: float
    image_names: tuple[str, ...]
    image_boards: tuple[str, ...]
    rvecs: np.ndarray
    tvecs: np.ndarray
    obs_image: np.ndarray
    obs_half: np.ndarray
    obs_ids: np.ndarray
    obs_board_points: np.ndarray
    obs_pixels: np.ndarray
    residuals: np.ndarray
    inliers: np.ndarray
    outlier_threshold_px: float
    status: int
    message: str
    nfev: int
    rounds: int
    skipped_images: tuple[str, ...] = ()
    start: str = ""
    obs_covariance: np.ndarray | None = None
    verdict: Verdict | None = None
    extensions: tuple[str, ...] = ()
    selection: tuple[str, ...] = ()
    uncertain: tuple[str, ...] = ()
    uncertainty_covariance: np.ndarray | None = None

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                object.__setattr__(self, f.name, _frozen(value))

    # ----- names ------------------------------------------------------------------------
    @property
    def model_name(self) -> str:
        return self.model.NAME

    @property
    def uncertainty_model(self) -> CameraModel:
        """The fitted model with ``uncertain`` counted as free: the model whose
        ``free_mask`` orders :attr:`measurement_covariance`."""
        return self.model.with_config(fixed=self.model.config.fixed - set(self.uncertain))

    @property
    def measurement_covariance(self) -> np.ndarray:
        """The covariance a measurement's uncertainty varies ``uncertainty_model`` by."""
        c = self.uncertainty_covariance
        return self.covariance if c is None else c

    @property
    def param_names(self) -> tuple[str, ...]:
        return self.model.PARAM_NAMES

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the free parameters, shape (F,)."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the free parameters, shape (F, F)."""
        s = self.std
        with np.errstate(divide="ignore", invalid="ignore"):
            c = self.covariance / np.outer(s, s)
        return np.clip(c, -1.0, 1.0)

    def named_std(self) -> dict[str, float]:
        return dict(zip(self.free_names, self.std.tolist(), strict=True))

    def strongest_correlations(self, count: int = 5) -> list[tuple[str, str, float]]:
        """The ``count`` parameter pairs with the largest |correlation|."""
        c = self.correlation
        iu = np.triu_indices(c.shape[0], 1)
        order = np.argsort(-np.abs(c[iu]))[:count]
        return [
            (self.free_names[iu[0][k]], self.free_names[iu[1][k]], float(c[iu][k])) for k in order
        ]

    # ----- residual statistics ------------------------------------------------------------
    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def rms(self) -> float:
        """RMS residual length over the inlier corners, px."""
        r = self.residuals[self.inliers]
        return float(np.sqrt(np.mean(np.sum(r * r, axis=-1)))) if r.size else float("nan")

    def _rms_where(self, mask: np.ndarray) -> float:
        r = self.residuals[mask & self.inliers]
        return float(np.sqrt(np.mean(np.sum(r * r, axis=-1)))) if r.size else float("nan")

    @property
    def rms_half(self) -> np.ndarray:
        """RMS residual length per half (left, right), px, shape (2,)."""
        return np.array([self._rms_where(self.obs_half == h) for h in (0, 1)])

    @property
    def rms_image(self) -> np.ndarray:
        """RMS residual length per image, px, shape (I,)."""
        return np.array(
            [self._rms_where(self.obs_image == i) for i in range(len(self.image_names))]
        )

    @property
    def rms_image_half(self) -> np.ndarray:
        """RMS residual length per image and half, px, shape (I, 2) (NaN: half not seen)."""
        return np.array(
            [
                [self._rms_where((self.obs_image == i) & (self.obs_half == h)) for h in (0, 1)]
                for i in range(len(self.image_names))
            ]
        )

    @property
    def outlier_count(self) -> int:
        return int((~self.inliers).sum())

    def worst_images(self, count: int = 3) -> list[tuple[str, float]]:
        """The ``count`` images with the largest RMS, worst first."""
        rms = self.rms_image
        order = np.argsort(-np.nan_to_num(rms, nan=-1.0))[:count]
        return [(self.image_names[i], float(rms[i])) for i in order]

    @property
    def obs_points(self) -> np.ndarray:
        """Corner positions in the model frame, shape (M, 3), mm."""
        R = rotation_matrix(self.rvecs)[self.obs_image]
        return np.einsum("nij,nj->ni", R, self.obs_board_points) + self.tvecs[self.obs_image]

    @property
    def converged(self) -> bool:
        return self.status > 0


# ----- observations -----------------------------------------------------------------------


def _collect(
    detections: Sequence[ViewDetections],
    boards: Mapping[str, np.ndarray],
    image_size: tuple[int, int],
    split: int,
) -> tuple[Observations, np.ndarray]:
    """Validate detections and flatten them; images with no usable half are skipped.

    Returns the observations and the detector's covariance of each, (M, 2, 2) px^2.
    """
    names, bnames, img, hal, ids_all, X, q, C = [], [], [], [], [], [], [], []
    skipped = []
    seen = set()
    for view in detections:
        if view.name in seen:
            raise BadInputError(f"image {view.name!r} appears twice in the calibration data")
        seen.add(view.name)
        if view.board not in boards:
            raise BadInputError(
                f"image {view.name!r} refers to board {view.board!r}, which is not given",
                hint=f"known boards: {', '.join(sorted(boards)) or 'none'}",
            )
        corners = np.asarray(boards[view.board], dtype=np.float64)
        if corners.ndim != 2 or corners.shape[1] != 3:
            raise BadInputError(f"board {view.board!r} corners must have shape (N, 3)")
        halves = []
        for h in Half:
            ids = np.asarray(view.ids[h], dtype=np.int64).reshape(-1)
            pix = np.asarray(view.pixels[h], dtype=np.float64).reshape(-1, 2)
            if ids.shape[0] != pix.shape[0]:
                raise BadInputError(
                    f"image {view.name!r}, {h.label} half: {ids.size} ids but {pix.shape[0]} pixels"
                )
            if ids.size and (ids.min() < 0 or ids.max() >= corners.shape[0]):
                raise BadInputError(
                    f"image {view.name!r}, {h.label} half: corner id out of range for "
                    f"board {view.board!r} ({corners.shape[0]} corners)"
                )
            if np.unique(ids).size != ids.size:
                raise BadInputError(f"image {view.name!r}, {h.label} half: repeated corner ids")
            if not np.all(np.isfinite(pix)):
                raise BadInputError(f"image {view.name!r}, {h.label} half: non-finite pixels")
            if not np.all(in_half(pix, h, split, image_size)):
                raise BadInputError(
                    f"image {view.name!r}: corners outside the {h.label} half "
                    f"(split {split}, image {image_size[0]}x{image_size[1]})",
                    hint="check the split column and the image size",
                )
            cov = _view_covariance(view, h, ids.size)
            halves.append((ids, pix, cov) if ids.size >= MIN_CORNERS_PER_HALF else None)
        if all(hv is None for hv in halves):
            skipped.append(view.name)
            continue
        k = len(names)
        names.append(view.name)
        bnames.append(view.board)
        for h, hv in zip(Half, halves, strict=True):
            if hv is None:
                continue
            ids, pix, cov = hv
            C.append(cov)
            img.append(np.full(ids.size, k))
            hal.append(np.full(ids.size, int(h), dtype=np.int8))
            ids_all.append(ids)
            X.append(corners[ids])
            q.append(pix)

    def cat(a, shape, dt):
        return np.concatenate(a).astype(dt) if a else np.zeros(shape, dt)

    obs = Observations(
        tuple(names),
        tuple(bnames),
        cat(img, (0,), np.int64),
        cat(hal, (0,), np.int8),
        cat(ids_all, (0,), np.int64),
        cat(X, (0, 3), np.float64),
        cat(q, (0, 2), np.float64),
        tuple(skipped),
    )
    return obs, cat(C, (0, 2, 2), np.float64)


def _view_covariance(view: ViewDetections, half: Half, n: int) -> np.ndarray:
    """The detector's covariance of a view's corners in one half, NaN where not given."""
    given = view.covariance[half]
    if given is None:
        return np.full((n, 2, 2), np.nan)
    cov = np.asarray(given, dtype=np.float64)
    if cov.shape != (n, 2, 2):
        raise BadInputError(
            f"image {view.name!r}, {half.label} half: corner covariance of shape {cov.shape} "
            f"for {n} corners"
        )
    return cov


def _check_amount(obs: Observations) -> None:
    per_half = [len(set(obs.image[obs.half == h].tolist())) for h in (0, 1)]
    stereo = len(set(obs.image[obs.half == 0].tolist()) & set(obs.image[obs.half == 1].tolist()))
    hint = (
        f"take at least {MIN_IMAGES} images of the board at different distances and tilts, "
        f"with {MIN_CORNERS_PER_HALF} or more corners in each half"
    )
    if obs.n_images < MIN_IMAGES:
        raise CalibrationError(
            f"too few usable calibration images: {obs.n_images} (need {MIN_IMAGES})", hint=hint
        )
    for h, count in zip(Half, per_half, strict=True):
        if count < MIN_IMAGES - 1:
            raise CalibrationError(
                f"too few images with {MIN_CORNERS_PER_HALF}+ corners in the {h.label} half: "
                f"{count} (need {MIN_IMAGES - 1})",
                hint=hint,
            )
    if stereo < MIN_STEREO_IMAGES:
        raise CalibrationError(
            f"too few images with the board seen in both halves: {stereo} "
            f"(need {MIN_STEREO_IMAGES})",
            hint="place the board where both halves see it in some images",
        )


def _apparent_tilt_spread(obs: Observations, image_size, split) -> float:
    """Largest angle between board normals seen in one half, without calibration, deg.

    Parallel planes share their vanishing line ``l = H^-T (0, 0, 1)`` whatever the
    camera (H the board-to-image homography), so the spread of the lines measures how
    far the boards are from parallel. The lines are turned into normals ``K^T l`` with a
    nominal camera (focal length ``max(half width, height)`` px, a ~55-degree field;
    principal point at the half's centre); lens and prism distortion bend the
    homographies a little, so parallel boards show a few degrees of apparent spread.
    """
    import cv2

    width, height = image_size
    spreads = [0.0]
    for h in Half:
        lo, hi = (0, split) if h is Half.LEFT else (split, width)
        f0 = float(max(hi - lo, height))
        K = np.array([[f0, 0.0, (lo + hi - 1) / 2.0], [0.0, f0, (height - 1) / 2.0], [0, 0, 1.0]])
        normals = []
        for i in range(obs.n_images):
            sel = obs.subset(i, int(h))
            if sel.size < MIN_CORNERS_PER_HALF:
                continue
            H, _ = cv2.findHomography(obs.board_points[sel, :2], obs.pixels[sel], 0)
            if H is None or not np.all(np.isfinite(H)):
                continue
            n = K.T @ np.linalg.solve(H.T, np.array([0.0, 0.0, 1.0]))
            normals.append(n / np.linalg.norm(n))
        if len(normals) >= 2:
            N = np.array(normals)
            spreads.append(float(np.degrees(np.arccos(np.clip(np.abs(N @ N.T), 0, 1).min()))))
    return max(spreads)


def _check_parallel(obs: Observations, image_size, split) -> None:
    spread = _apparent_tilt_spread(obs, image_size, split)
    if spread < MIN_TILT_SPREAD_DEG:
        raise CalibrationError(
            f"degenerate calibration geometry: all boards are parallel (apparent normals "
            f"within {spread:.1f} deg)",
            hint="tilt the board by 10-30 deg about both axes in several images",
        )


def _check_distances(obs: Observations, rvecs: np.ndarray, tvecs: np.ndarray) -> None:
    """Refuse boards all at one distance (poses from the initialisation)."""
    R = rotation_matrix(rvecs)
    centres = np.array(
        [
            (R[i] @ obs.board_points[obs.image == i].mean(axis=0)) + tvecs[i]
            for i in range(obs.n_images)
        ]
    )
    dist = np.linalg.norm(centres, axis=-1)
    if dist.max() < MIN_DISTANCE_RATIO * dist.min():
        raise CalibrationError(
            f"degenerate calibration geometry: all boards at one distance "
            f"({dist.min():.1f}-{dist.max():.1f} mm)",
            hint="take images over the working range (e.g. 10-45 mm), not at one distance",
        )


# ----- the public entry point ------------------------------------------------------------------


def calibrate(
    model_name: str,
    detections: Sequence[ViewDetections],
    boards: Mapping[str, np.ndarray],
    image_size: tuple[int, int],
    split: int,
    options: CalibrationOptions | None = None,
    *,
    start: CalibrationResult | Sequence[CalibrationResult] | None = None,
) -> CalibrationResult:
    """Calibrate a camera model from board-corner detections.

    Parameters
    ----------
    model_name : str
        A registered model (:data:`endomeasure.models.MODELS`).
    detections : sequence of ViewDetections
        One entry per image.
    boards : mapping of str to ndarray, shape (N_b, 3), mm
        Board-frame corner coordinates (z = 0) by board name, indexed by corner id.
    image_size : (width, height), px
    split : int
        First column of the right half.
    options : CalibrationOptions, optional
    start : CalibrationResult or sequence of them, optional
        Finished calibrations of the same images to start from: of the same model (a
        warm re-calibration, e.g. with new detections), or of a model in this model's
        seeding chain (saves recomputing it when several models are calibrated).
        Calibrations of other images are ignored.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Too few images or corners, degenerate geometry, no convergence, or a singular
        covariance (the message names the undetermined parameters).
    BadInputError
        Malformed detections (ids out of range, pixels outside their half, ...), or a
        seed or option that does not fit the model.
    """
    options = options or CalibrationOptions()
    cls = model_class(model_name)  # KeyError for unknown names is the caller's concern
    config = ModelConfig(tuple(image_size), int(split), _fixed_parameters(cls, options))
    obs, obs_cov = _collect(detections, boards, config.image_size, config.split)
    _check_amount(obs)
    _check_parallel(obs, config.image_size, config.split)
    starts = [start] if isinstance(start, CalibrationResult) else list(start or ())
    given = {r.model_name: r for r in starts if _same_images(r, obs, config)}
    chain = _Chain(obs, config, options, given)
    if cls.NAME in given:
        # warm start: re-calibration of the same images (e.g. with new detections)
        previous = given[cls.NAME]
        # the extensions the data called for stay free (unless the caller fixed the set)
        kept = set(previous.extensions) if options.fixed is None else set()
        fixed = config.fixed - kept
        model = previous.model.with_config(fixed=fixed).with_values(dict(options.values))
        first = Start(model, np.array(previous.rvecs), np.array(previous.tvecs),
                      "an earlier calibration")  # fmt: skip
    else:
        first = chain.start_of(cls, config, _seed_model(cls, options.seed, config))
    fitted = _fit(first.model, obs, first.rvecs, first.tvecs, options, first.state)
    nfev = chain.nfev + fitted.nfev
    extensions, selection = (), ()
    if options.fixed is None:
        selected = _select_extensions(fitted, obs, options)
        nfev += selected.nfev
        fitted, extensions, selection = selected.fitted, selected.freed, selected.findings
    result = _finish(fitted, obs, nfev, first.origin, obs_cov)
    result = dataclasses.replace(result, extensions=extensions, selection=selection)
    if options.fixed is not None:
        return result
    return _with_uncertain_extensions(result, fitted, obs, options)


def _fit(model, obs: Observations, rvecs, tvecs, options: CalibrationOptions, state=None):
    return fit_with_outliers(
        model,
        obs,
        rvecs,
        tvecs,
        max_nfev=options.max_nfev,
        outlier_sigmas=options.outlier_sigmas,
        max_rounds=options.max_outlier_rounds,
        state=state,
    )


class _Selection(NamedTuple):
    fitted: Any  # OutlierFit
    freed: tuple[str, ...]
    findings: tuple[str, ...]
    nfev: int


def _select_extensions(fitted, obs: Observations, options: CalibrationOptions) -> _Selection:
    """Free the model's ``EXTENSIONS`` that the data call for, by the information criterion.

    Each group (in the model's order) is freed from the current fit and refined on the
    same inlier corners; it is kept when the Bayesian information criterion
    ``m ln(C) + k ln(m)`` falls (``m`` residual components of all corners, ``k`` the
    group's size, ``C`` the cost), i.e. when ``m ln(C_0 / C_1) > k ln(m)``: a parameter
    that only fits noise lowers the cost by about one noise variance, far less than
    ``ln(m)`` of them. The cost is the squared residual of every corner, capped at the
    outlier threshold, with a corner the model cannot project counted at the cap: a
    term that folds the lens back or puts a pole in the field loses corners, and must
    pay for them. A group that leaves a combination of parameters undetermined by the
    data (a correlation eigenvalue below the verdict's limit) is not kept. A second pass
    retries the groups the first rejected before it kept a later one (a radial term can
    make a pupil term worthwhile); a group tried from the fit that still stands is not
    tried again. A group whose gain predicted by one linearised step
    (:func:`_linearised_gain`) falls well short of the threshold is not refined at all.
    Parameters the user gave a value for are not freed. After a change the outlier rule
    runs again.
    """
    model = fitted.fit.model
    cap = float(fitted.threshold_px) ** 2
    use = fitted.inliers
    m = 2 * int(use.size)
    current, nfev, freed, findings = fitted.fit, 0, [], []
    cost = _capped_cost(current, obs, cap)
    chosen = set(options.values) | options.hold
    pending = [g for g in model.EXTENSIONS
               if all(n in model.config.fixed and n not in chosen for n in g)]  # fmt: skip

    def threshold(group):  # the criterion's price of the group's parameters
        return len(group) * np.log(m)

    tried_from: dict[tuple[str, ...], Any] = {}  # the fit each group was last tried from
    for _ in range(2):
        rejected = []
        for group in pending:
            if tried_from.get(group) is current:
                rejected.append(group)  # nothing was freed since: the same trial again
                continue
            tried_from[group] = current
            trial_model = current.model.with_config(fixed=current.model.config.fixed - set(group))
            predicted = _linearised_gain(trial_model, obs, current, use, cost, m)
            if predicted <= SCREEN_FRACTION * threshold(group):
                findings.append(
                    f"kept fixed {', '.join(group)}: the linearised information criterion "
                    f"changes by {-predicted + threshold(group):+.1f} (not refined)"
                )
                rejected.append(group)
                continue
            try:
                trial = refine(trial_model, obs, current.rvecs, current.tvecs, use,
                               options.max_nfev, current.state)  # fmt: skip
            except CalibrationError:
                rejected.append(group)
                continue
            nfev += trial.nfev
            trial_cost = _capped_cost(trial, obs, cap) if trial.status > 0 else np.inf
            gain = m * np.log(cost / trial_cost) if trial_cost < np.inf else -np.inf
            kept = gain > threshold(group) and _determined(trial, obs, use)
            findings.append(
                f"{'freed' if kept else 'kept fixed'} {', '.join(group)}: the information "
                f"criterion changes by {-gain + threshold(group):+.1f} "
                f"(RMS {np.sqrt(2 * cost / m):.4f} -> {np.sqrt(2 * trial_cost / m):.4f} px, "
                "capped)"
            )
            if kept:
                current, cost = trial, trial_cost
                freed.extend(group)
            else:
                rejected.append(group)
        if len(rejected) == len(pending):
            break
        pending = rejected
    if not freed:
        return _Selection(fitted, (), tuple(findings), nfev)
    again = _fit(current.model, obs, current.rvecs, current.tvecs, options, current.state)
    return _Selection(again, tuple(freed), tuple(findings), nfev + again.nfev)


def _with_uncertain_extensions(result: CalibrationResult, fitted, obs: Observations,
                               options: CalibrationOptions) -> CalibrationResult:  # fmt: skip
    """The covariance widened by the absorbed extensions the fit held.

    A group the information criterion kept fixed stays at its neutral value, the best
    estimate the data allow; but the probe may hold it at any value the data cannot tell
    from that one. Most groups would leave a trace in the residuals, which the verdict
    compares with the noise. A group in the model's ``ABSORBED_EXTENSIONS`` leaves none:
    a moving entrance pupil, absorbed by the face distances, shifts the model frame's
    origin along the axis, and with it every absolute depth, by many times the fitted
    parameters' own sigma (``docs/models.md``, "Uncertainty of what the fit held"). So
    the covariance measurements use is that of the fit with every such group free at its
    held value (no prior), while it stays regular: a group the data cannot separate from
    the fitted parameters at all changes no prediction. The fit, its residuals, its
    covariance and its verdict remain those of the estimated parameters. Parameters the
    user gave a value for or held are left out.
    """
    model = result.model
    chosen = set(options.values) | options.hold
    held: list[str] = []
    covariance = None
    for group in model.ABSORBED_EXTENSIONS:
        if not all(n in model.config.fixed and n not in chosen for n in group):
            continue
        trial = fitted.fit._replace(
            model=model.with_config(fixed=model.config.fixed - {*held, *group})
        )
        mc = _marginal(trial, obs, fitted.inliers, result.residual_variance)
        if mc.covariance is not None:
            held.extend(group)
            covariance = mc.covariance
    return dataclasses.replace(result, uncertain=tuple(held), uncertainty_covariance=covariance)


SCREEN_FRACTION = 0.5
"""A group whose linearised gain (:func:`_linearised_gain`) is below this fraction of
the criterion's threshold is not refined: a margin of 2 on the linearisation, which
near a converged fit predicts the refined gain far better than that
(``tests/solvers/test_extensions.py`` checks the margin holds for every group)."""


def _linearised_gain(trial_model, obs: Observations, current, use: np.ndarray, cost: float,
                     m: int) -> float:  # fmt: skip
    """The information criterion's gain ``m ln(C_0 / C_1)`` predicted for freeing a group
    by one Gauss-Newton step from the current fit (the score test): ``C_1 = C_0 - g^T
    H^-1 g`` with the gradient ``g`` and normal matrix ``H`` of the trial problem (the
    group freed, every pose) on the inlier corners. Infinite where ``H`` cannot be
    factored, so that the refinement decides."""
    problem = BundleProblem(trial_model, obs, use, current.state)
    x = problem.pack(trial_model, current.rvecs, current.tvecs)
    r = problem.residuals(x)
    H, g = problem.normal_equations(x, r, np.ones(r.size, dtype=bool))
    step = gauss_newton_step(H, g)
    if step is None:
        return np.inf
    decrease = -float(g @ step)
    if not (np.isfinite(decrease) and decrease < cost):
        return np.inf
    return float(m * np.log(cost / (cost - decrease)))


def _capped_cost(fit, obs: Observations, cap: float) -> float:
    """Sum over every corner of ``min(|r|^2, cap)``, a corner not projected costing ``cap``,
    plus the projections' own precision (:data:`NUMERICAL_FLOOR_PX` per corner), so that
    fits of exact data do not compare their round-off."""
    r = all_residuals(fit.model, obs, fit.rvecs, fit.tvecs, fit.state)
    squared = np.sum(r * r, axis=-1)
    capped = np.where(np.isfinite(squared), np.minimum(squared, cap), cap)
    return float(np.sum(capped + NUMERICAL_FLOOR_PX**2))


def _determined(fit, obs: Observations, use: np.ndarray) -> bool:
    """Whether the data determine every free parameter of a fit: a regular covariance
    whose correlation matrix has no eigenvalue below the verdict's limit (a term that
    trades against others, e.g. a moving pupil against the face distances, would leave
    the scale of every measurement to a combination the data hardly see)."""
    cov = _marginal(fit, obs, use, 1.0).covariance
    if cov is None:
        return False
    s = np.sqrt(np.diag(cov))
    correlation = cov / np.outer(s, s)
    return bool(np.linalg.eigvalsh(correlation)[0] >= MIN_CORRELATION_EIGENVALUE)


def _same_images(result: CalibrationResult, obs: Observations, config: ModelConfig) -> bool:
    """Whether an earlier result calibrated the same images on the same sensor geometry."""
    other = result.model.config
    return result.image_names == obs.image_names and (other.image_size, other.split) == (
        config.image_size,
        config.split,
    )


def _fixed_parameters(cls: type[CameraModel], options: CalibrationOptions) -> frozenset[str]:
    fixed = set(cls.DEFAULT_FIXED | options.hold if options.fixed is None else options.fixed)
    for what, names in (("fix", fixed), ("free", options.free), ("set", options.values)):
        unknown = set(names) - set(cls.PARAM_NAMES)
        if unknown:
            raise BadInputError(f"unknown parameter(s) to {what} for {cls.NAME}: {sorted(unknown)}")
    return frozenset(fixed - set(options.free))


def _seed_model(cls: type[CameraModel], seed: Mapping[str, Any] | None, config: ModelConfig):
    """The user's seed as a model of the kind being calibrated (BadInputError if not)."""
    if seed is None:
        return None
    if seed.get("model") != cls.NAME:
        raise BadInputError(
            f"the seed describes a {seed.get('model')!r} model, not a {cls.NAME} model",
            hint="give a model file of that kind (as written by `endomeasure export`)",
        )
    try:
        return cls.from_dict({**seed, "config": config.to_dict()})
    except (KeyError, TypeError, ValueError) as exc:
        raise BadInputError(f"the seed is not a valid {cls.NAME} model: {exc}") from None


class _Chain:
    """Builds the start of a model from the detections or from the model it is seeded
    from, calibrating that one first unless a finished calibration of it is given."""

    def __init__(self, obs: Observations, config: ModelConfig, options: CalibrationOptions,
                 given: Mapping[str, CalibrationResult]):  # fmt: skip
        self.obs, self.config, self.options, self.given = obs, config, options, given
        self.nfev = 0  # residual evaluations spent on starts

    def refine(self, model, obs, rvecs, tvecs, state=None, max_nfev=None):
        """The bundle adjustment an initialiser may call (:class:`StartContext`)."""
        use = np.ones(obs.image.size, dtype=bool)
        limit = self.options.max_nfev if max_nfev is None else min(max_nfev, self.options.max_nfev)
        fit = refine(model, obs, rvecs, tvecs, use, limit, state)
        self.nfev += fit.nfev
        return fit

    def _check(self, fit) -> None:
        """:func:`_check_fit` on a fit of every corner that starts another one; corners it
        cannot project (a seed model near the split) are left to the fits after it, as
        long as most of them can be projected."""
        residuals = all_residuals(fit.model, self.obs, fit.rvecs, fit.tvecs, fit.state)
        projected = np.isfinite(residuals).all(axis=-1)
        if projected.mean() >= MIN_PROJECTED_FRACTION:
            residuals = residuals[projected]
        _check_fit(fit, residuals, "the start of the")

    def start_of(self, cls: type[CameraModel], config: ModelConfig, seed=None) -> Start:
        base = None if cls.SEEDED_FROM is None else self.refined(model_class(cls.SEEDED_FROM))
        ctx = StartContext(self.obs, config, dict(self.options.values), seed, self.refine)
        start = model_start(cls.NAME)(ctx, base)
        if base is None:
            # a start from the detections alone is rough: check the geometry it shows,
            # and make one joint pass, from the user's values, before anything else sees it
            _check_distances(self.obs, start.rvecs, start.tvecs)
            fit = self.refine(start.model.with_values(ctx.values), self.obs, start.rvecs,
                              start.tvecs)  # fmt: skip
            self._check(fit)
            return Start(fit.model, fit.rvecs, fit.tvecs, start.origin, state=fit.state)
        # a fixed value must hold whatever the seeding did; a free one was only its start
        model = start.model.with_values({k: v for k, v in ctx.values.items() if k in config.fixed})
        return start._replace(model=model, origin=f"{start.origin}, via {base.origin}")

    def refined(self, cls: type[CameraModel]) -> Start:
        """A refined calibration of ``cls`` to seed another model from."""
        if cls.NAME in self.given:
            done = self.given[cls.NAME]
            _check_distances(self.obs, done.rvecs, done.tvecs)
            origin = f"the {cls.NAME} calibration of the same images"
            return Start(done.model, np.array(done.rvecs), np.array(done.tvecs), origin)
        start = self.start_of(cls, self.config.with_fixed(cls.DEFAULT_FIXED))
        if cls.SEEDED_FROM is None:
            return start  # already refined once
        fit = self.refine(start.model, self.obs, start.rvecs, start.tvecs, start.state)
        self._check(fit)
        return Start(fit.model, fit.rvecs, fit.tvecs, start.origin, state=fit.state)


def _check_fit(fit, inl: np.ndarray, what: str = "the") -> None:
    """Refuse a fit that did not converge: the optimiser's status, corners ``inl`` (the
    residuals of the fitted corners, (M, 2) px) that cannot be projected, an RMS that no
    detection noise explains."""
    name = fit.model.NAME
    if fit.status <= 0:
        raise CalibrationError(
            f"{what} {name} calibration did not converge ({fit.message.strip()})",
            hint="check the detections, or add images at more distances and tilts",
        )
    if not np.all(np.isfinite(inl)):
        raise CalibrationError(
            f"{what} {name} calibration did not converge: "
            f"{int((~np.isfinite(inl)).any(-1).sum())} corners cannot be projected through "
            "the fitted model",
            hint="check the split column and the detections",
        )
    rms = float(np.sqrt(np.mean(np.sum(inl * inl, axis=-1))))
    if rms > CONVERGED_RMS_LIMIT_PX:
        raise CalibrationError(
            f"{what} {name} calibration did not converge: RMS residual {rms:.1f} px",
            hint="check the detections (corner ids must match between halves) and the split",
        )


def _marginal(fit, obs: Observations, use: np.ndarray, s2: float, problem=None):
    """The marginal covariance of a fit's free parameters (board poses marginalised out)
    for residual variance ``s2``; ``problem``: the fit's bundle problem if already built."""
    problem = problem or BundleProblem(fit.model, obs, use, fit.state)
    Jp, Jq, pose_rows = problem.blocks(problem.pack(fit.model, fit.rvecs, fit.tvecs))
    return marginal_covariance(Jp, Jq, pose_rows, problem.images.size, s2)


def _finish(
    fitted, obs: Observations, nfev: int, origin: str, obs_cov: np.ndarray
) -> CalibrationResult:
    fit, residuals, use = fitted.fit, fitted.residuals, fitted.inliers
    model = fit.model
    name = model.NAME
    inl = residuals[use]
    _check_fit(fit, inl)
    problem = BundleProblem(model, obs, use, fit.state)
    dof = problem.m - problem.n
    if dof <= 0:
        raise CalibrationError(
            f"too few corners for the {name} model: {problem.m} residuals for {problem.n} unknowns",
            hint="add images",
        )
    s2 = float(np.sum(inl * inl)) / dof
    mc = _marginal(fit, obs, use, s2, problem)
    free_names = tuple(model.PARAM_NAMES[i] for i in problem.free)
    if mc.covariance is None:
        names = ", ".join(free_names[i] for i in mc.undetermined) or "(all)"
        raise CalibrationError(
            f"the {name} calibration is singular: parameters not determined by the data: {names}",
            hint="fix them or add images with more tilt and distance",
        )
    result = CalibrationResult(
        model=model,
        free_names=free_names,
        covariance=mc.covariance,
        residual_variance=s2,
        image_names=obs.image_names,
        image_boards=obs.image_boards,
        rvecs=fit.rvecs,
        tvecs=fit.tvecs,
        obs_image=obs.image,
        obs_half=obs.half,
        obs_ids=obs.ids,
        obs_board_points=obs.board_points,
        obs_pixels=obs.pixels,
        residuals=residuals,
        inliers=use,
        outlier_threshold_px=float(fitted.threshold_px),
        status=fit.status,
        message=fit.message,
        nfev=nfev,
        rounds=fitted.rounds,
        skipped_images=obs.skipped,
        start=origin,
        obs_covariance=obs_cov,
    )
    return dataclasses.replace(result, verdict=judge(result, problem.n))
