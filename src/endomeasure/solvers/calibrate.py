"""Calibration of a split-sensor camera model from images of flat targets (SPEC 6).

:func:`calibrate` fits the free parameters of a camera model and one board pose per
image by minimising the reprojection error in pixels over every detected corner of
every image in both halves (maximum likelihood under isotropic Gaussian pixel noise),
the same cost for every model, so models are compared on the same footing.

Initialisation never needs prism design data (:mod:`endomeasure.solvers.init_calibration`):
per-half OpenCV calibration -> the ``pinhole`` pair -> the ``raytrace`` model seeded
from it (or from a user's seed with nominal design values) -> joint refinement.

Outliers: after a fit, a corner whose residual length exceeds ``outlier_sigmas`` times
the robust per-axis noise ``sigma = 1.4826 * median(|r|)`` (over all residual
components; never below ``OUTLIER_FLOOR_PX``) is reported and dropped, and the fit is
repeated from its solution until no new outlier appears (at most
``max_outlier_rounds`` rounds). For Gaussian noise a 5-sigma residual length has
probability exp(-12.5) ~ 4e-6, so clean data lose nothing.

Refusals (:class:`~endomeasure.errors.CalibrationError`): too few images or corners,
degenerate geometry (all boards parallel, or all at one distance), an optimiser that
does not converge, a covariance that is singular (naming the undetermined parameters).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from endomeasure.conventions import Half, in_half
from endomeasure.errors import BadInputError, CalibrationError
from endomeasure.geometry.rotations import rotation_jacobian, rotation_matrix, skew
from endomeasure.models import CameraModel, model_class
from endomeasure.solvers.covariance import marginal_covariance
from endomeasure.solvers.reprojection import projector_for

__all__ = [
    "ViewDetections",
    "CalibrationOptions",
    "CalibrationResult",
    "calibrate",
    "DEFAULT_GLASS_INDEX",
    "MIN_IMAGES",
    "MIN_CORNERS_PER_HALF",
    "MIN_STEREO_IMAGES",
    "MIN_TILT_SPREAD_DEG",
    "MIN_DISTANCE_RATIO",
    "OUTLIER_FLOOR_PX",
]

DEFAULT_GLASS_INDEX = 1.5168
"""N-BK7 at the helium d-line (587.6 nm), the usual prism glass; override with ``glass_index``."""
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
section 3.3). Parallel boards seen through the test prism show about 6 degrees, boards
tilted by +-3 degrees about 14, the paper's +-30 degrees about 90."""
MIN_DISTANCE_RATIO = 1.15
"""Boards whose farthest distance is less than this ratio times the nearest count as
one distance: the prism's non-central geometry needs a range of depths."""
OUTLIER_FLOOR_PX = 0.1
"""Residuals below this are never called outliers: no corner detector is more accurate,
and exact synthetic data would otherwise make rounding noise look like outliers."""
FAILED_RESIDUAL_PX = 1e3
"""Residual given to a corner whose projection fails during the optimisation (ray aiming
lost, behind the probe): large and constant, so steps into failure are rejected."""
INVALID_MODEL_RESIDUAL_PX = 1e6
"""Residual of every corner for a trial step outside the model's valid domain (a face
behind the lens): larger than any real cost, so such a step is never accepted."""
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
    """

    name: str
    board: str
    ids: tuple[np.ndarray, np.ndarray]
    pixels: tuple[np.ndarray, np.ndarray]


@dataclasses.dataclass(frozen=True)
class CalibrationOptions:
    """Choices of a calibration.

    Attributes
    ----------
    glass_index : float or None
        Refractive index of the prism (``raytrace``); None keeps the seed's value or
        :data:`DEFAULT_GLASS_INDEX`.
    free_index : bool
        Estimate ``n_glass`` instead of holding it fixed (it is strongly correlated with
        the face tilts; see the correlations in the result).
    seed : mapping or None
        A ``raytrace`` model dict (:meth:`CameraModel.to_dict`) with nominal design
        values, used instead of the seeding from the pinhole pair.
    fixed : frozenset of str or None
        Parameters held fixed; None means the model's ``DEFAULT_FIXED`` (with
        ``n_glass`` freed by ``free_index``).
    outlier_sigmas : float
        Outlier threshold in robust standard deviations (module docstring).
    max_outlier_rounds : int
    max_nfev : int
        Residual evaluations allowed per optimisation.
    """

    glass_index: float | None = None
    free_index: bool = False
    seed: Mapping[str, Any] | None = None
    fixed: frozenset[str] | None = None
    outlier_sigmas: float = 5.0
    max_outlier_rounds: int = 3
    max_nfev: int = 200


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
    def param_names(self) -> tuple[str, ...]:
        return self.model.PARAM_NAMES

    @property
    def free_values(self) -> np.ndarray:
        """Values of the free parameters, shape (F,)."""
        return np.array([getattr(self.model, n) for n in self.free_names])

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
        return dict(zip(self.free_names, self.std.tolist(), strict=False))

    def covariance_of(self, names: Sequence[str]) -> np.ndarray:
        """Covariance block of the named free parameters, shape (len(names),) * 2."""
        idx = [self.free_names.index(n) for n in names]
        return self.covariance[np.ix_(idx, idx)]

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
    def image_distances(self) -> np.ndarray:
        """Distance from the model origin to each image's corner centroid, shape (I,), mm."""
        P = self.obs_points
        out = np.full(len(self.image_names), np.nan)
        for i in range(out.size):
            sel = self.obs_image == i
            if np.any(sel):
                out[i] = float(np.linalg.norm(P[sel].mean(axis=0)))
        return out

    @property
    def converged(self) -> bool:
        return self.status > 0


# ----- observations -----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Observations:
    """Flattened corner observations (one row per corner per half per image)."""

    image_names: tuple[str, ...]
    image_boards: tuple[str, ...]
    image: np.ndarray  # (M,) int
    half: np.ndarray  # (M,) int8
    ids: np.ndarray  # (M,) int
    board_points: np.ndarray  # (M, 3) mm
    pixels: np.ndarray  # (M, 2) px
    skipped: tuple[str, ...]

    @property
    def n_images(self) -> int:
        return len(self.image_names)

    def subset(self, image: int, half: int) -> np.ndarray:
        return np.flatnonzero((self.image == image) & (self.half == half))


def _collect(
    detections: Sequence[ViewDetections],
    boards: Mapping[str, np.ndarray],
    image_size: tuple[int, int],
    split: int,
) -> Observations:
    """Validate detections and flatten them; images with no usable half are skipped."""
    names, bnames, img, hal, ids_all, X, q = [], [], [], [], [], [], []
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
            halves.append((ids, pix) if ids.size >= MIN_CORNERS_PER_HALF else None)
        if all(hv is None for hv in halves):
            skipped.append(view.name)
            continue
        k = len(names)
        names.append(view.name)
        bnames.append(view.board)
        for h, hv in zip(Half, halves, strict=False):
            if hv is None:
                continue
            ids, pix = hv
            img.append(np.full(ids.size, k))
            hal.append(np.full(ids.size, int(h), dtype=np.int8))
            ids_all.append(ids)
            X.append(corners[ids])
            q.append(pix)

    def cat(a, shape, dt):
        return np.concatenate(a).astype(dt) if a else np.zeros(shape, dt)

    return Observations(
        tuple(names),
        tuple(bnames),
        cat(img, (0,), np.int64),
        cat(hal, (0,), np.int8),
        cat(ids_all, (0,), np.int64),
        cat(X, (0, 3), np.float64),
        cat(q, (0, 2), np.float64),
        tuple(skipped),
    )


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
    for h, count in zip(Half, per_half, strict=False):
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


# ----- the optimisation ---------------------------------------------------------------------


@dataclasses.dataclass
class _Fit:
    model: CameraModel
    rvecs: np.ndarray
    tvecs: np.ndarray
    status: int = 0
    message: str = ""
    nfev: int = 0
    state: np.ndarray | None = None  # projector warm-start state per observation


class _Problem:
    """The bundle problem over a subset of observations: parameters + one pose per image."""

    def __init__(
        self, model: CameraModel, obs: Observations, use: np.ndarray, state: np.ndarray | None
    ):
        self.template = model
        self.free = np.flatnonzero(model.free_mask)
        self.F = self.free.size
        self.rows = np.flatnonzero(use)
        images = np.unique(obs.image[self.rows])
        self.images = images
        self.pose_of_obs = np.searchsorted(images, obs.image[self.rows])
        self.X = obs.board_points[self.rows]
        self.q = obs.pixels[self.rows]
        self.projector = projector_for(
            model, obs.half[self.rows], None if state is None else state[self.rows]
        )
        self.n = self.F + 6 * images.size
        self.m = 2 * self.rows.size
        # sparsity pattern: each residual pair touches the F parameters and its pose's 6
        M = self.rows.size
        cols = np.concatenate(
            [
                np.broadcast_to(np.arange(self.F), (M, self.F)),
                self.F + 6 * self.pose_of_obs[:, None] + np.arange(6)[None, :],
            ],
            axis=1,
        )
        self._cols = np.repeat(cols, 2, axis=0).reshape(-1)
        self._indptr = np.arange(0, 2 * M * (self.F + 6) + 1, self.F + 6)

    def pack(self, model, rvecs, tvecs) -> np.ndarray:
        poses = np.concatenate([rvecs[self.images], tvecs[self.images]], axis=1)
        return np.concatenate([model.params[self.free], poses.reshape(-1)])

    def unpack(self, x: np.ndarray):
        p = self.template.params.copy()
        p[self.free] = x[: self.F]
        poses = x[self.F :].reshape(-1, 6)
        return self.template.with_params(p), poses[:, :3], poses[:, 3:]

    def points(self, rv, tv):
        R = rotation_matrix(rv)[self.pose_of_obs]
        return np.einsum("nij,nj->ni", R, self.X) + tv[self.pose_of_obs]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        try:
            model, rv, tv = self.unpack(x)
        except ValueError:
            # a trial step outside the model's valid domain (a face behind the lens, a
            # negative focal length): a large constant cost makes the solver reject it
            return np.full(self.m, INVALID_MODEL_RESIDUAL_PX)
        P = self.points(rv, tv)
        q, ok = self.projector.project(model, P)
        r = q - self.q
        r[~ok] = FAILED_RESIDUAL_PX
        self._last = (x.copy(), model, rv, P)
        return r.reshape(-1)

    def jacobian_blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-observation Jacobians: parameters (M, 2, F) and own pose (M, 2, 6)."""
        if not (hasattr(self, "_last") and np.array_equal(self._last[0], x)):
            self.residuals(x)
        _, model, rv, P = self._last
        dq_dp, dq_dP = self.projector.jacobian(model, P)
        # a corner whose derivative cannot be traced (at the edge of total internal
        # reflection) contributes nothing to the step rather than poisoning it
        lost = ~(np.isfinite(dq_dp).all(axis=(1, 2)) & np.isfinite(dq_dP).all(axis=(1, 2)))
        if lost.any():
            dq_dp, dq_dP = dq_dp.copy(), dq_dP.copy()
            dq_dp[lost] = 0.0
            dq_dP[lost] = 0.0
        # d P / d(rvec, t) = [-[R X]_x J_l(rvec), I]
        RX = P - x[self.F :].reshape(-1, 6)[self.pose_of_obs, 3:]
        dP_drv = -skew(RX) @ rotation_jacobian(rv)[self.pose_of_obs]
        return dq_dp, np.concatenate([dq_dP @ dP_drv, dq_dP], axis=-1)

    def jacobian(self, x: np.ndarray):
        """Sparse residual Jacobian, shape (m, n): each row pair has F + 6 entries."""
        import scipy.sparse as sp

        dq_dp, dq_dpose = self.jacobian_blocks(x)
        blocks = np.concatenate([dq_dp, dq_dpose], axis=-1)  # (M, 2, F + 6)
        return sp.csr_matrix((blocks.reshape(-1), self._cols, self._indptr), shape=(self.m, self.n))

    def blocks(self, x: np.ndarray):
        """Row-wise parameter and pose Jacobians for the covariance: (m, F), (m, 6), pose of row."""
        dq_dp, dq_dpose = self.jacobian_blocks(x)
        return (
            dq_dp.reshape(self.m, self.F),
            dq_dpose.reshape(self.m, 6),
            np.repeat(self.pose_of_obs, 2),
        )


LSMR_OPTIONS = {"atol": 1e-12, "btol": 1e-12, "maxiter": 200}
"""Tolerances of the inner sparse solver of each trust-region step: tight, because
inexact steps stall the final convergence (scipy's defaults leave ~1e-6 relative)."""
_PRECONDITION_RIDGE = 1e-10  # relative ridge keeping the start's normal matrix factorable


def _least_squares(problem: _Problem, x0: np.ndarray, max_nfev: int):
    """``scipy.optimize.least_squares`` (trust-region reflective, LSMR steps), whitened.

    The unknowns are made unitless and decorrelated at the start: with the start's
    normal matrix ``N0 = J0^T J0`` (small and dense: F + 6 I unknowns), column-scaled
    by ``D = diag(N0)^-1/2`` and factored ``D N0 D = L L^T``, the solver works on
    ``z`` with ``x = x0 + D L^-T z``. Near the start the Jacobian in ``z`` is
    orthonormal, so each LSMR step solve takes a handful of iterations instead of
    hundreds (the pinhole's distortion terms are correlated beyond 0.99).

    MINPACK's Levenberg-Marquardt was tried and rejected: a trial step that loses a few
    corners (a ray at the edge of total internal reflection) makes it shrink its step
    until ``xtol`` stops it far from the minimum; the trust-region solver recovers.
    """
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import least_squares
    from scipy.sparse.linalg import LinearOperator

    J0 = problem.jacobian(x0)
    N0 = (J0.T @ J0).toarray()
    diag = np.diag(N0).copy()
    d = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    Nn = N0 * d[:, None] * d[None, :]
    Nn[np.diag_indices_from(Nn)] += _PRECONDITION_RIDGE
    L = cholesky(Nn, lower=True)
    P = d[:, None] * solve_triangular(L, np.eye(L.shape[0]), lower=True, trans="T")

    def fun(z):
        return problem.residuals(x0 + P @ z)

    # a unit step in z changes the linearised residuals by 1 px (RSS): let the first
    # trust region reach the size of the residual to be removed
    radius = max(1.0, float(np.linalg.norm(problem.residuals(x0))))

    def jac(z):
        J = problem.jacobian(x0 + P @ z)
        return LinearOperator(
            J.shape, matvec=lambda v: J @ (P @ v), rmatvec=lambda u: P.T @ (J.T @ u)
        )

    ls = least_squares(
        fun,
        np.zeros_like(x0),
        jac=jac,
        method="trf",
        x_scale=radius,
        tr_solver="lsmr",
        tr_options=LSMR_OPTIONS,
        ftol=1e-12,
        xtol=1e-12,
        gtol=1e-10,
        max_nfev=max_nfev,
    )
    ls.x = x0 + P @ ls.x
    return ls


def refine(
    model: CameraModel,
    obs: Observations,
    rvecs: np.ndarray,
    tvecs: np.ndarray,
    use: np.ndarray,
    max_nfev: int,
    state: np.ndarray | None = None,
) -> _Fit:
    """Jointly refine the free model parameters and the poses of the used observations.

    ``state`` is a previous fit's projector state over the same observations (warm starts).
    """
    problem = _Problem(model, obs, use, state)
    ls = _least_squares(problem, problem.pack(model, rvecs, tvecs), max_nfev)
    try:
        fitted, rv, tv = problem.unpack(ls.x)
    except ValueError as exc:
        raise CalibrationError(
            f"the {model.NAME} calibration did not converge (it left the model's valid "
            f"domain: {exc})",
            hint="check the detections, or add images at more distances and tilts",
        ) from None
    rvecs, tvecs = rvecs.copy(), tvecs.copy()
    rvecs[problem.images] = rv
    tvecs[problem.images] = tv
    new_state = problem.projector.state()
    if new_state is not None:
        full = np.full((obs.image.size, new_state.shape[1]), np.nan)
        if state is not None:
            full[:] = state
        full[problem.rows] = new_state
        new_state = full
    return _Fit(fitted, rvecs, tvecs, int(ls.status), str(ls.message), int(ls.nfev), new_state)


def all_residuals(model, obs: Observations, rvecs, tvecs, state=None) -> np.ndarray:
    """Projected minus detected pixels of every observation, shape (M, 2), NaN where failed."""
    projector = projector_for(model, obs.half, state)
    R = rotation_matrix(rvecs)[obs.image]
    P = np.einsum("nij,nj->ni", R, obs.board_points) + tvecs[obs.image]
    q, ok = projector.project(model, P)
    r = q - obs.pixels
    r[~ok] = np.nan
    return r


def _fit_with_outliers(model, obs, rvecs, tvecs, options: CalibrationOptions, state=None):
    """Refine, drop outliers by the rule in the module docstring, refit; returns the last fit."""
    use = np.ones(obs.image.size, dtype=bool)
    nfev = 0
    rounds = 0
    while True:
        fit = refine(model, obs, rvecs, tvecs, use, options.max_nfev, state)
        nfev += fit.nfev
        rounds += 1
        model, rvecs, tvecs, state = fit.model, fit.rvecs, fit.tvecs, fit.state
        r = all_residuals(model, obs, rvecs, tvecs, state)
        length = np.linalg.norm(r, axis=-1)
        sigma = 1.4826 * float(np.nanmedian(np.abs(r[use])))
        threshold = max(options.outlier_sigmas * sigma, OUTLIER_FLOOR_PX)
        new_use = use & (length <= threshold)  # NaN (failed) counts as an outlier
        if np.array_equal(new_use, use) or rounds > options.max_outlier_rounds:
            return fit, r, use, threshold, nfev, rounds
        use = new_use


# ----- the public entry point ------------------------------------------------------------------


def _configure(model_name: str, options: CalibrationOptions) -> frozenset[str]:
    cls = model_class(model_name)
    fixed = set(cls.DEFAULT_FIXED if options.fixed is None else options.fixed)
    unknown = fixed - set(cls.PARAM_NAMES)
    if unknown:
        raise BadInputError(f"unknown parameter(s) to fix for {model_name}: {sorted(unknown)}")
    if "n_glass" in cls.PARAM_NAMES and options.free_index:
        fixed.discard("n_glass")
    return frozenset(fixed)


def calibrate(
    model_name: str,
    detections: Sequence[ViewDetections],
    boards: Mapping[str, np.ndarray],
    image_size: tuple[int, int],
    split: int,
    options: CalibrationOptions | None = None,
    *,
    start: CalibrationResult | None = None,
) -> CalibrationResult:
    """Calibrate a camera model from board-corner detections.

    Parameters
    ----------
    model_name : {'pinhole', 'raytrace'} or another registered model
    detections : sequence of ViewDetections
        One entry per image.
    boards : mapping of str to ndarray, shape (N_b, 3), mm
        Board-frame corner coordinates (z = 0) by board name, indexed by corner id.
    image_size : (width, height), px
    split : int
        First column of the right half.
    options : CalibrationOptions, optional
    start : CalibrationResult, optional
        A finished calibration of the same images to start from: of the same model (a
        warm re-calibration, e.g. with new detections), or a ``pinhole`` calibration to
        seed another model from (saves recomputing it when both models are calibrated).
        Ignored when its images differ.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Too few images or corners, degenerate geometry, no convergence, or a singular
        covariance (the message names the undetermined parameters).
    BadInputError
        Malformed detections (ids out of range, pixels outside their half, ...).
    """
    from endomeasure.solvers import init_calibration as init

    options = options or CalibrationOptions()
    cls = model_class(model_name)  # KeyError for unknown names is the caller's concern
    fixed = _configure(model_name, options)
    obs = _collect(detections, boards, tuple(image_size), int(split))
    _check_amount(obs)
    _check_parallel(obs, tuple(image_size), int(split))

    if start is not None and start.image_names != obs.image_names:
        start = None  # a calibration of other images cannot seed the poses
    if start is not None and start.model_name == cls.NAME:
        # warm start: re-calibration of the same images (e.g. with new detections)
        model = start.model.with_config(fixed=fixed)
        if options.glass_index is not None and "n_glass" in cls.PARAM_NAMES:
            p = model.params.copy()
            p[cls.index("n_glass")] = options.glass_index
            model = model.with_params(p)
        rvecs, tvecs = np.array(start.rvecs), np.array(start.tvecs)
        fit, residuals, use, threshold, nfev, rounds = _fit_with_outliers(
            model, obs, rvecs, tvecs, options
        )
        return _finish(fit, obs, residuals, use, threshold, nfev, rounds, "an earlier calibration")
    if start is not None and start.model_name == "pinhole":
        pinhole, rvecs, tvecs = start.model, np.array(start.rvecs), np.array(start.tvecs)
        origin = "the pinhole calibration of the same images"
    else:
        pinhole, rvecs, tvecs = init.initial_pinhole(obs, tuple(image_size), int(split))
        origin = "per-half OpenCV calibration"
    _check_distances(obs, rvecs, tvecs)

    state = None
    if cls.NAME == "pinhole":
        model = pinhole.with_config(fixed=fixed)
        if start is None:
            # the per-half start is rough; one joint pass before the outlier rule sees it
            fit = refine(model, obs, rvecs, tvecs, np.ones(obs.image.size, bool), options.max_nfev)
            model, rvecs, tvecs = fit.model, fit.rvecs, fit.tvecs
            prefit_nfev = fit.nfev
        else:
            prefit_nfev = 0
    elif cls.NAME == "raytrace":
        if start is None:
            fit = refine(
                pinhole, obs, rvecs, tvecs, np.ones(obs.image.size, bool), options.max_nfev
            )
            pinhole, rvecs, tvecs = fit.model, fit.rvecs, fit.tvecs
            prefit_nfev = fit.nfev
        else:
            prefit_nfev = 0
        model, rvecs, tvecs, seed_nfev, state = init.seed_raytrace(
            pinhole, obs, rvecs, tvecs, fixed, options
        )
        prefit_nfev += seed_nfev
        origin = ("the seed model" if options.seed is not None else "the pinhole pair") + (
            f", via {origin}"
        )
    else:
        raise CalibrationError(
            f"no initialisation is known for the {cls.NAME!r} model",
            hint="calibrate with a seed of nominal values",
        )

    fit, residuals, use, threshold, nfev, rounds = _fit_with_outliers(
        model, obs, rvecs, tvecs, options, state
    )
    return _finish(fit, obs, residuals, use, threshold, nfev + prefit_nfev, rounds, origin)


def _finish(fit, obs, residuals, use, threshold, nfev, rounds, origin) -> CalibrationResult:
    model = fit.model
    name = model.NAME
    if fit.status <= 0:
        raise CalibrationError(
            f"the {name} calibration did not converge ({fit.message.strip()})",
            hint="check the detections, or add images at more distances and tilts",
        )
    inl = residuals[use]
    if not np.all(np.isfinite(inl)):
        raise CalibrationError(
            f"the {name} calibration did not converge: {int((~np.isfinite(inl)).any(-1).sum())} "
            "corners cannot be projected through the fitted model",
            hint="check the split column and the detections",
        )
    rms = float(np.sqrt(np.mean(np.sum(inl * inl, axis=-1))))
    if rms > CONVERGED_RMS_LIMIT_PX:
        raise CalibrationError(
            f"the {name} calibration did not converge: RMS residual {rms:.1f} px",
            hint="check the detections (corner ids must match between halves) and the split",
        )
    problem = _Problem(model, obs, use, fit.state)
    x = problem.pack(model, fit.rvecs, fit.tvecs)
    dof = problem.m - problem.n
    if dof <= 0:
        raise CalibrationError(
            f"too few corners for the {name} model: {problem.m} residuals for {problem.n} unknowns",
            hint="add images",
        )
    ssr = float(np.sum(inl * inl))
    s2 = ssr / dof
    Jp, Jq, pose_rows = problem.blocks(x)
    mc = marginal_covariance(Jp, Jq, pose_rows, problem.images.size, s2)
    free_names = tuple(model.PARAM_NAMES[i] for i in problem.free)
    if mc.covariance is None:
        names = ", ".join(free_names[i] for i in mc.undetermined) or "(all)"
        raise CalibrationError(
            f"the {name} calibration is singular: parameters not determined by the data: {names}",
            hint="fix them (e.g. keep n_glass fixed) or add images with more tilt and distance",
        )
    return CalibrationResult(
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
        outlier_threshold_px=float(threshold),
        status=fit.status,
        message=fit.message,
        nfev=nfev,
        rounds=rounds,
        skipped_images=obs.skipped,
        start=origin,
    )
