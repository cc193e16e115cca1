"""Automatic correspondence search for operator points (SPEC section 7).

An operator clicks a point in one half; :func:`find_match` finds the same surface point
in the other half, or refuses with a reason. It never guesses: a refused point has no
match, only the reason and the diagnostics that led to it.

The search
----------
1. **Curve.** The point's ray is sampled over the working depth range and projected
   into the other half (:func:`~endomeasure.measure.epipolar.epipolar_curve`), at most
   0.4 px between samples. Only samples whose whole patch lies inside the other half
   are searched.
2. **Patch warp.** The two halves see the surface through different prism faces, so
   the local image scale and shear differ between them (the default biprism's halves
   show opposite keystone distortion). At each curve
   sample the search patch is warped by the local affine map between the halves,
   ``A = dq_other / dq_ref``, for a surface facing the probe (a plane of constant z)
   at that sample's depth: ``A = (d q_other / d p) (d p / d q_ref)``, with the first
   factor from :meth:`CameraModel.project_jacobian` and the second from the rays of the
   neighbouring pixels met on that plane. For the refinement (step 5) the default
   ``warp='plane'`` replaces ``A`` by the exact map of that plane (every patch sample's
   ray met with it and projected): over a patch of typical size the raytrace map is far
   enough from affine to bias an affine-warped match. ``warp='none'`` compares plain
   square patches, for comparison (what each warp gives: ``docs/benchmarks.md``,
   section ``correspondence``).
3. **Correlation.** Normalised cross-correlation (NCC) of the reference patch with the
   warped patch at every sample (bilinear interpolation, no quantisation of sub-pixel
   positions), after removing each patch's mean *and* brightness ramp: vignetting,
   illumination fall-off and the dark band of the prism apex tilt the brightness
   differently in the two halves.
4. **Checks**, in this order, each a refusal with a reason (:class:`MatchStatus`):

   - the reference patch must carry texture along the search direction
     (``untextured``, see below);
   - the curve must have room for the patch somewhere in the other half (``outside``);
   - no second peak of the curve, outside the main peak's lobe, may come within
     :data:`MAX_SECOND_RATIO` of the best while itself passing as a match
     (``ambiguous``: repeated texture);
   - the peak must not sit where the searchable stretch of the curve ends (at the edge
     of the other half or of the depth range), because the match could lie beyond it
     (``outside``);
   - searching back from the best candidate must find the query point again, or at
     least score it within :data:`MAX_SECOND_RATIO` of its own best (``outside``: a
     point the other half does not see correlates best with some unrelated point,
     whose own match lies elsewhere);
   - the peak's NCC, corrected for image noise (``signal_score``), must reach
     :data:`MIN_SCORE` (``low_score``), before and after the refinement.
5. **Sub-pixel.** A parabola through the peak and its neighbours in curve parameter
   gives the start; then a Gauss-Newton (Lucas-Kanade) refinement of the pixel, a small
   linear shape correction (the surface's tilt), gain, offset and brightness ramp on
   the warped patch, both patches sampled by cubic B-spline interpolation. The pixel is
   free across the curve, so the final pair is *not* forced onto the epipolar curve
   and its ray gap (the common perpendicular of the two
   rays) is a real check of the calibration and the match.

Relative gain field
-------------------
Vignetting and the apex band darken each half towards its own edges, so one surface
point's brightness changes *across a patch* differently in the two views: a gain that
varies over the patch, which the brightness model (gain, offset, ramp) cannot hold. On a
feature that is not symmetric (a dark mark on brighter texture) it moves the match: on
the random designs' scenes, every mark's match lay 0.005-0.03 px left of the truth, the
same without image noise, and not without vignetting. A free gain ramp in the refinement
would absorb it, but on an edge it mimics a shift and doubles the scatter. So the field is
measured apart, on a window :data:`GAIN_REACH` times the patch's, where both views of the
same surface (the plane warp maps one onto the other) are smoothed alike
(:data:`GAIN_SMOOTH_PX`): the texture cancels in the ratio of the two, the log of which is
fitted by a plane; the reference patch is multiplied by that field before the refinement
(:func:`_relative_gain`). What it changes on the random designs' scenes:
``docs/accuracy.md``, "Operator distances on the scenes" (``bench/operator_designs.py``).

Texture criterion
-----------------
A match can only be located along the curve if the reference patch changes along the
search direction (the direction in the reference half that mimics a move along the
curve). From the patch's derivative along it and the image noise ``sigma`` (estimated
around the point from the median absolute 3x3 Laplacian, Immerkaer's operator) the
search predicts the standard deviation with which it can place the match along the
curve (``precision_px``, see :func:`_localisation_precision`); a patch that cannot be
placed to :data:`MAX_PRECISION_PX` is refused as untextured; flat patches and stripes
running along the curve predict far worse than textured surfaces.

Precision
---------
The reported ``precision_px`` is the standard deviation of the matched pixel along the
curve, in pixels of the searched half (:func:`_match_precision`), where ``measure``
applies it. From the reference patch's derivative energy ``E`` (noise subtracted),
mapped into the searched half by the final warp, over ``n`` samples:

``var = (a^2 s_r^2 + rho s_t^2) / E * (1 + n D s_t^2 / E) + m^2 / E``

with ``a`` the gain between the halves, ``s_r`` and ``s_t`` the noise of the reference
and the searched half, ``rho`` the mean correlation row sum of the searched half's
interpolated noise at the warped samples (1 on the pixel grid, ``1/det A`` for samples
packed closer than pixels by a compressing warp), ``D = 2.16 /px^2`` the variance of the
derivative of spline-interpolated unit noise and ``m`` the misfit: the mean square of
what the searched patch differs from the reference patch's photometric fit by, beyond
what the two noises give, measured at each match (:func:`_measured_misfit`, a
least-squares fit's a-posteriori variance).
The first factor is the classic least-squares term. The second is the noise times the
*noise's own derivative* in the searched patch (the refinement's gradients are those of
the noisy image): negligible on strong texture, but where the per-sample gradient is
about equal to the noise (weak texture at sensor noise) it is as large as the first.
How honest the result is against the simulator's truth: ``docs/accuracy.md``, "Match
precision against the simulator's truth" (``bench/match_precision.py``).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from scipy.ndimage import gaussian_filter

from endomeasure import defaults
from endomeasure.conventions import Half, Status, in_half
from endomeasure.errors import BadInputError
from endomeasure.geometry.rays import common_perpendicular
from endomeasure.interpolation import (
    CARDINAL_REACH,
    cardinal_weights,
    noise_transfer,
    spline_coefficients,
    spline_sample,
)
from endomeasure.measure.epipolar import (
    DEPTH_RANGE_MM,
    EpipolarCurve,
    epipolar_curve,
    other_half,
)

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel

__all__ = [
    "Match",
    "MatchSettings",
    "MatchStatus",
    "WARPS",
    "find_match",
    "find_matches",
    "estimate_noise",
    "noise_level",
    "NoiseLevel",
    "noise_corrected_score",
    "match_precision",
    "MIN_SCORE",
    "MAX_SECOND_RATIO",
    "MAX_PRECISION_PX",
    "BACK_TOLERANCE_PX",
]

WARPS = ("plane", "affine", "none")

MIN_SCORE = 0.8
"""Lowest accepted peak NCC (after the noise correction, ``signal_score``): between
the scores of true matches on textured surfaces and the best that an unrelated patch of
smooth random texture reaches somewhere along a curve of a few hundred samples."""
MAX_SECOND_RATIO = 0.9
"""Largest accepted ratio of the second-highest peak (outside the main peak's lobe) to
the highest one. Repeated texture along the curve gives ratios near 1, random texture
at a true match clearly less."""
MAX_PRECISION_PX = 0.15
"""Worst accepted predicted precision (1 sigma) of the match along the curve, px. On a
flat patch the derivative energy left after subtracting the noise's expectation is a
fluctuation (plus the error of the noise estimate) that predicts a few tenths of a
pixel or worse; the threshold keeps a margin below that."""
BACK_TOLERANCE_PX = 1.0
"""The back search must return within this distance of the original point (or score it
within ``MAX_SECOND_RATIO`` of its own best) for the match to count as mutual."""
NOISE_FLOOR_DN = 1.0 / np.sqrt(12.0)
"""Smallest image noise assumed for integer images: the rounding to whole grey levels."""
_NOISE_WINDOW_PATCHES = 4
"""Side of the local noise-estimation window, in patch sizes."""
_REFINE_ITERATIONS = 12
_REFINE_TOL_PX = 1e-3
_REFINE_MAX_SHIFT_PX = 1.5
"""The 2-D refinement may move the match at most this far from the curve peak; further
means it has locked onto something else, and the curve peak is kept."""
_REFINE_MAX_SHAPE = 0.3
"""Largest entry of the refinement's linear shape correction (30 % scale or shear)."""
_JACOBIAN_STEP_PX = 0.5
GAIN_REACH = 2.0
"""Half-width of the window the relative gain field is measured on, in patch half-widths:
wide enough that the field's slope stands out of the texture's, close enough that the
plane warp still holds."""
GAIN_SMOOTH_PX = 3.0
"""Gaussian smoothing (sigma, px of the reference half) of both views before their ratio
is taken: it averages the texture and the noise over some 30 pixels, far less than the
field changes over."""
"""Half step of the central differences of the rays used for the local affine map."""


class MatchStatus(enum.StrEnum):
    """Outcome of a correspondence search (stable strings, used in JSON output)."""

    OK = "ok"
    OUTSIDE = "outside"
    """The point is not seen in both halves (within the working depth range)."""
    UNTEXTURED = "untextured"
    """The reference patch has too little texture along the search direction."""
    AMBIGUOUS = "ambiguous"
    """Another peak along the curve correlates almost as well (e.g. repeated texture)."""
    LOW_SCORE = "low_score"
    """The best candidate correlates too weakly to be trusted."""


@dataclasses.dataclass(frozen=True, eq=False)
class Match:
    """Result of :func:`find_match` for one point.

    Attributes
    ----------
    pixel : ndarray, shape (2,), px
        The query point (full-image coordinates) in ``half``.
    half : Half
        The half of the query point; the match is in the other one.
    status : MatchStatus
    message : str
        One line explaining a refusal ('' when OK).
    match : ndarray, shape (2,), px
        The matched pixel in the other half; NaN unless OK.
    candidate : ndarray, shape (2,), px
        The best position found on the curve, also for refused points (for plots and
        diagnosis); NaN if the search never got that far.
    score : float
        NCC at the match (at the curve peak for refused points), in [-1, 1]; NaN if none.
    signal_score : float
        ``score`` corrected for image noise (an estimate of the correlation of the noise-
        free patches, capped at 1); ``min_score`` applies to it.
    second_ratio : float
        Second-highest peak over the highest, NaN if not computed; 0 if no other peak.
    depth_mm : float, mm
        z coordinate of the matched point on the query point's ray (foot of the common
        perpendicular); NaN unless OK.
    point : ndarray, shape (3,), mm
        Midpoint of the common perpendicular of the two rays; NaN unless OK.
    ray_gap_mm : float, mm
        Length of the common perpendicular (0 for a perfect calibration and match).
    precision_px : float, px
        Predicted standard deviation of the match along the curve, in pixels of the
        other half, from the reference patch's texture, the image noise of both halves,
        the warp and the two patches' misfit measured at the match (see the module
        notes, *Precision*); for refused points the reference half's first-order
        estimate; inf if untextured.
    noise_sigma : float
        Image noise used for the texture criterion, grey levels.
    back_px : float, px
        Distance of the back search's peak from the query point; NaN if not run.
    curve : ndarray, shape (M, 2), px
        The searched samples of the epipolar curve in the other half (for plots).
    curve_depths_mm : ndarray, shape (M,), mm
        z of the ray point behind each curve sample.
    """

    pixel: np.ndarray
    half: Half
    status: MatchStatus
    message: str
    match: np.ndarray
    candidate: np.ndarray
    score: float
    signal_score: float
    second_ratio: float
    depth_mm: float
    point: np.ndarray
    ray_gap_mm: float
    precision_px: float
    noise_sigma: float
    back_px: float
    curve: np.ndarray
    curve_depths_mm: np.ndarray

    @property
    def ok(self) -> bool:
        return self.status is MatchStatus.OK

    @property
    def left(self) -> np.ndarray:
        """The left-half pixel of the pair (NaN if refused and the query is right)."""
        return self.pixel if self.half is Half.LEFT else self.match

    @property
    def right(self) -> np.ndarray:
        """The right-half pixel of the pair (NaN if refused and the query is left)."""
        return self.match if self.half is Half.LEFT else self.pixel

    def to_dict(self, curve: bool = False) -> dict[str, Any]:
        """Plain, JSON-ready data (NaN as None); ``curve`` adds the curve samples."""

        def num(x):
            x = float(x)
            return x if np.isfinite(x) else None

        def vec(a):
            return [num(x) for x in np.asarray(a).ravel()]

        out = {
            "pixel": vec(self.pixel),
            "half": self.half.label,
            "status": self.status.value,
            "message": self.message,
            "match": vec(self.match),
            "candidate": vec(self.candidate),
            "score": num(self.score),
            "signal_score": num(self.signal_score),
            "second_ratio": num(self.second_ratio),
            "depth_mm": num(self.depth_mm),
            "point_mm": vec(self.point),
            "ray_gap_mm": num(self.ray_gap_mm),
            "precision_px": num(self.precision_px),
            "noise_sigma": num(self.noise_sigma),
            "back_px": num(self.back_px),
        }
        if curve:
            out["curve"] = [vec(q) for q in self.curve]
        return out


@dataclasses.dataclass(frozen=True)
class MatchSettings:
    """How :func:`find_matches` searches and when it refuses a point.

    Attributes
    ----------
    depth_range_mm : (near, far), mm
        Working depth range searched (z in the model frame), ``0 < near < far``.
    patch : int, px
        Side of the square correlation patch (odd, at least 5).
    warp : {'plane', 'affine', 'none'}
        How the search patch is warped into the other half: ``'plane'`` searches with
        the local affine map between the halves and refines with the exact map of a
        surface of constant depth; ``'affine'`` uses the affine map throughout;
        ``'none'`` compares plain square patches.
    min_score, max_second_ratio, max_precision_px : float
        Refusal thresholds (:data:`MIN_SCORE`, :data:`MAX_SECOND_RATIO`,
        :data:`MAX_PRECISION_PX`).
    noise_sigma : float or None, grey levels
        Image noise; None estimates it around each point.
    check_back : bool
        Search back from the candidate to confirm it (the one-half-only test).

    Raises
    ------
    BadInputError
        For a depth range, patch size or warp that is not valid.
    """

    depth_range_mm: tuple[float, float] = DEPTH_RANGE_MM
    patch: int = defaults.PATCH_PX
    warp: str = "plane"
    min_score: float = MIN_SCORE
    max_second_ratio: float = MAX_SECOND_RATIO
    max_precision_px: float = MAX_PRECISION_PX
    noise_sigma: float | None = None
    check_back: bool = True

    def __post_init__(self):
        try:
            near, far = (float(v) for v in self.depth_range_mm)
        except (TypeError, ValueError):
            raise BadInputError(
                f"depth range {self.depth_range_mm!r} is not a pair of numbers"
            ) from None
        if not (0.0 < near < far and np.isfinite(far)):
            raise BadInputError(
                f"depth range {near:g}-{far:g} mm is not valid", hint="give 0 < near < far in mm"
            )
        patch = self.patch
        if not (isinstance(patch, int | np.integer) and patch >= 5 and patch % 2 == 1):
            raise BadInputError(
                f"patch size {patch!r} is not valid", hint="use an odd size >= 5 px"
            )
        if patch > defaults.MAX_PATCH_PX:
            raise BadInputError(
                f"patch size {patch} px is larger than {defaults.MAX_PATCH_PX} px: so wide a patch "
                "spans changes of depth and no longer localises a point",
                hint=f"use an odd size from 5 to {defaults.MAX_PATCH_PX} px",
            )
        if self.warp not in WARPS:
            raise BadInputError(
                f"unknown patch warp {self.warp!r}", hint=f"use one of {', '.join(WARPS)}"
            )
        noise = None if self.noise_sigma is None else float(self.noise_sigma)
        for name, value in (
            ("depth_range_mm", (near, far)), ("patch", int(patch)),
            ("min_score", float(self.min_score)),
            ("max_second_ratio", float(self.max_second_ratio)),
            ("max_precision_px", float(self.max_precision_px)),
            ("noise_sigma", noise), ("check_back", bool(self.check_back)),
        ):  # fmt: skip
            object.__setattr__(self, name, value)

    @functools.cached_property
    def offsets(self) -> np.ndarray:
        """Patch sample offsets, shape (patch * patch, 2), px, row-major (built once)."""
        r = self.patch // 2
        dv, du = np.mgrid[-r : r + 1, -r : r + 1]
        return np.stack([du.ravel(), dv.ravel()], axis=-1).astype(np.float64)


# ----- image access ----------------------------------------------------------------------


class _Image(NamedTuple):
    """The searched image: float64 grey levels (H, W) and the noise floor of its type,
    in its grey levels."""

    grey: np.ndarray
    floor: float


def _grey(image: np.ndarray, model: CameraModel) -> _Image:
    """The image as an :class:`_Image`, checked against the model's sensor."""
    image = np.asarray(image)
    width, height = model.config.image_size
    if image.ndim == 3 and image.shape[2] in (1, 3, 4):
        channels = image[..., :3] if image.shape[2] == 4 else image
        grey = channels.astype(np.float64).mean(axis=2)
    elif image.ndim == 2:
        grey = image.astype(np.float64)
    else:
        raise BadInputError(
            f"image of shape {image.shape} is neither grey (H, W) nor colour (H, W, 3)"
        )
    if grey.shape != (height, width):
        raise BadInputError(
            f"image is {grey.shape[1]}x{grey.shape[0]} but the model expects {width}x{height}",
            hint="use the session's images or a model calibrated for this sensor",
        )
    if image.dtype.kind in "ui":
        floor = NOISE_FLOOR_DN
    elif image.dtype.kind == "f":
        if not np.all(np.isfinite(grey)):
            raise BadInputError("image contains NaN or infinite values")
        floor = 0.0
    else:
        raise BadInputError(f"image of type {image.dtype} is not a grey-level image")
    return _Image(grey, floor)


def _half_columns(model: CameraModel, half: Half) -> tuple[int, int]:
    """First and last pixel column of a half."""
    split = model.config.split
    return (0, split - 1) if half is Half.LEFT else (split, model.config.image_size[0] - 1)


def _sample(grey: np.ndarray, u: np.ndarray, v: np.ndarray, cols: tuple[int, int]) -> np.ndarray:
    """Bilinear samples of ``grey`` at ``(u, v)`` using only columns ``cols[0]..cols[1]``.

    Positions must already lie inside the half (callers check); the clipping only keeps
    the weight-zero neighbour of a sample on the last column inside the half.
    """
    c0, c1 = cols
    u = np.clip(u, c0, c1)
    v = np.clip(v, 0, grey.shape[0] - 1)
    iu = np.minimum(np.floor(u).astype(np.intp), c1 - 1)
    iv = np.minimum(np.floor(v).astype(np.intp), grey.shape[0] - 2)
    fu = u - iu
    fv = v - iv
    top = grey[iv, iu] * (1.0 - fu) + grey[iv, iu + 1] * fu
    bottom = grey[iv + 1, iu] * (1.0 - fu) + grey[iv + 1, iu + 1] * fu
    return top * (1.0 - fv) + bottom * fv


def _sample_spline(
    grey: np.ndarray, positions: np.ndarray, cols: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cubic B-spline value and gradient (d/du, d/dv) of ``grey`` at ``positions``
    (..., 2), using only columns ``cols`` (:mod:`endomeasure.interpolation`).

    Notes
    -----
    Bilinear interpolation blurs by an amount that depends on the sub-pixel phase (none
    on the grid, a ``[1/2, 1/2]`` average midway), so two patches sampled at different
    phases differ by more than a shift and a least-squares fit between them is pulled
    towards whole pixels. The cubic B-spline interpolates with a nearly phase-independent
    response.
    """
    coeffs, origin = spline_coefficients(grey, positions, cols=cols)
    return spline_sample(coeffs, origin, positions)


_CORRELATION_REACH = 4
"""Pixels either side whose spline weights enter :func:`_interpolated_noise_correlation`."""
_SPLINE_TABLE_STEPS = 1024
"""Sub-pixel phases tabulated by :func:`_spline_table` (linear interpolation between
them is exact to about 1e-7)."""


@functools.cache
def _spline_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tables over the phases ``k / S``, ``k = 0..S`` (``S`` = :data:`_SPLINE_TABLE_STEPS`):
    the spline weights (S + 1, 2R + 1), the 1-D noise variance ``sum w^2`` and its
    derivative (S + 1,)."""
    phase = np.arange(_SPLINE_TABLE_STEPS + 1) / _SPLINE_TABLE_STEPS
    weight, slope = cardinal_weights(phase)
    variance = np.sum(weight**2, axis=-1)
    d_variance = 2.0 * np.sum(weight * slope, axis=-1)
    return weight, variance, d_variance


def _spline_noise_variance(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Variance of unit white pixel noise after cubic spline interpolation at
    ``positions`` (..., 2), and its gradient in ``(u, v)`` (..., 2).

    It is 1 on the pixel grid and 0.57 midway between four pixels (0.76 per axis): an
    interpolated image is least noisy between pixels.
    """
    _, table, d_table = _spline_table()
    grid = np.linspace(0.0, 1.0, _SPLINE_TABLE_STEPS + 1)
    frac = positions - np.floor(positions)
    per_axis = np.interp(frac, grid, table)
    d_axis = np.interp(frac, grid, d_table)
    variance = per_axis[..., 0] * per_axis[..., 1]
    gradient = np.stack([d_axis[..., 0] * per_axis[..., 1], per_axis[..., 0] * d_axis[..., 1]], -1)
    return variance, gradient


def _tabulated_weights(frac: np.ndarray) -> np.ndarray:
    """Spline weights at phases ``frac`` in [0, 1), (..., 2R + 1), from the table."""
    table = _spline_table()[0]
    x = np.asarray(frac) * _SPLINE_TABLE_STEPS
    k = np.minimum(np.floor(x).astype(np.intp), _SPLINE_TABLE_STEPS - 1)
    f = (x - k)[..., None]
    return (1.0 - f) * table[k] + f * table[k + 1]


def _inside(positions: np.ndarray, cols: tuple[int, int], height: int) -> np.ndarray:
    """Whether sample positions (..., 2) lie where bilinear sampling stays in the half."""
    u = positions[..., 0]
    v = positions[..., 1]
    return (u >= cols[0]) & (u <= cols[1]) & (v >= 0) & (v <= height - 1)


def estimate_noise(grey: np.ndarray) -> float:
    """Robust standard deviation of additive image noise, grey levels.

    Parameters
    ----------
    grey : ndarray, shape (H, W)
        A grey-level image region (at least 3x3).

    Returns
    -------
    float

    Notes
    -----
    Immerkaer's operator ``L = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` cancels constant
    and linear intensity (and most smooth texture); on white noise of deviation
    ``sigma`` its output has deviation ``6 sigma``. The median of ``|L|`` over the region,
    divided by ``0.6745 * 6`` (the Gaussian median absolute deviation), is insensitive
    to the few large responses at edges.
    """
    g = np.asarray(grey, dtype=np.float64)
    if g.shape[0] < 3 or g.shape[1] < 3:
        return 0.0
    return float(np.median(np.abs(_immerkaer(g))) / _IMMERKAER_MAD)


_IMMERKAER_MAD = 0.6745 * 6.0
"""Median absolute response of Immerkaer's operator to unit white noise."""


def _immerkaer(g: np.ndarray) -> np.ndarray:
    """Immerkaer's operator on the interior pixels of ``g`` (H - 2, W - 2)."""
    return (
        g[:-2, :-2] - 2 * g[:-2, 1:-1] + g[:-2, 2:]
        - 2 * g[1:-1, :-2] + 4 * g[1:-1, 1:-1] - 2 * g[1:-1, 2:]
        + g[2:, :-2] - 2 * g[2:, 1:-1] + g[2:, 2:]
    )  # fmt: skip


class NoiseLevel(NamedTuple):
    """Image noise as a function of the signal, ``sigma^2(I) = read + shot * (I - black)``
    (grey levels; the Poisson-Gaussian model of a photon-counting sensor)."""

    read: float
    shot: float
    black: float

    def sigma(self, level) -> np.ndarray:
        """Noise deviation at grey level(s) ``level``."""
        excess = np.maximum(np.asarray(level, dtype=np.float64) - self.black, 0.0)
        return np.sqrt(self.read + self.shot * excess)


_NOISE_BINS = 16
"""Signal bins of :func:`noise_level`."""
_NOISE_BIN_MIN = 500
"""Fewest pixels a bin needs to give its noise."""


def noise_level(grey: np.ndarray, smooth_px: int = 5) -> NoiseLevel:
    """The noise-level function of an image half, fitted to robust noise estimates in
    bins of the local signal.

    Each pixel's Immerkaer response (:func:`estimate_noise`) is binned by the local mean
    (a ``smooth_px`` box); per bin the median absolute response gives the deviation, and
    a straight line through the variances against the signal, weighted by each bin's
    count, gives the read and shot terms (both kept >= 0, the read term at least the
    8-bit rounding's 1/12). A sensor's noise grows with its signal: one number for the
    whole image understates it in the bright, textured centre of an endoscope's view.
    """
    import cv2

    g = np.asarray(grey, dtype=np.float64)
    floor = 1.0 / 12.0
    if g.shape[0] < 3 or g.shape[1] < 3:
        return NoiseLevel(floor, 0.0, 0.0)
    lap = np.abs(_immerkaer(g)).ravel()
    level = cv2.blur(g, (smooth_px, smooth_px))[1:-1, 1:-1].ravel()
    black = float(np.percentile(level, 0.5))
    edges = np.unique(np.percentile(level, np.linspace(0, 100, _NOISE_BINS + 1)))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, edges.size - 2)
    x, y, wt = [], [], []
    for k in range(edges.size - 1):
        members = which == k
        if members.sum() < _NOISE_BIN_MIN:
            continue
        x.append(np.median(level[members]) - black)
        y.append((np.median(lap[members]) / _IMMERKAER_MAD) ** 2)
        wt.append(members.sum())
    if len(x) < 2:
        return NoiseLevel(max(estimate_noise(g) ** 2, floor), 0.0, black)
    x, y, wt = np.array(x), np.array(y), np.sqrt(np.array(wt, dtype=float))
    shot, read = np.polyfit(x, y, 1, w=wt)
    if shot < 0:
        shot, read = 0.0, float(np.average(y, weights=wt))
    return NoiseLevel(max(float(read), floor), float(shot), black)


def _local_noise(grey: np.ndarray, pixel: np.ndarray, cols: tuple[int, int], patch: int) -> float:
    half_window = _NOISE_WINDOW_PATCHES * patch // 2
    u, v = int(round(pixel[0])), int(round(pixel[1]))
    u0, u1 = max(cols[0], u - half_window), min(cols[1] + 1, u + half_window + 1)
    v0, v1 = max(0, v - half_window), min(grey.shape[0], v + half_window + 1)
    return estimate_noise(grey[v0:v1, u0:u1])


# ----- the search ----------------------------------------------------------------------


@dataclasses.dataclass
class _Search:
    """One direction's search along a curve (internal)."""

    curve: EpipolarCurve
    valid: np.ndarray  # (M,) searched samples
    affine: np.ndarray  # (M, 2, 2) ref -> other pixel map
    ncc: np.ndarray  # (M,) NaN where not valid
    best: int = -1  # index of the highest valid NCC, -1 if none


def _local_affine(
    model: CameraModel, pixel: np.ndarray, half: Half, curve: EpipolarCurve
) -> np.ndarray:
    """Affine maps ref-half -> other-half pixel offsets at each curve sample, (M, 2, 2).

    For a surface of constant z through each sample point; NaN where undefined.
    """
    h = _JACOBIAN_STEP_PX
    steps = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    rays = model.rays(pixel + steps, half)
    z = curve.depths_mm[:, None, None]  # (M, 1, 1)
    t = (z - rays.origins[None, :, 2:3]) / rays.directions[None, :, 2:3]  # (M, 4, 1)
    points = rays.origins[None] + t * rays.directions[None]  # (M, 4, 3)
    dp_du = (points[:, 0] - points[:, 1]) / (2 * h)
    dp_dv = (points[:, 2] - points[:, 3]) / (2 * h)
    dp_dq = np.stack([dp_du, dp_dv], axis=-1)  # (M, 3, 2)
    jac = model.project_jacobian(curve.points, other_half(half)).dq_dp  # (M, 2, 3)
    return jac @ dp_dq


def _ncc_rows(patches: np.ndarray, template_unit: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """NCC of each row of ``patches`` (K, n), sampled at ``offsets`` (n, 2), with a
    template normalised by :func:`_template` (n,); both are compared ramp-free."""
    centred = _ramp_free(patches, offsets)
    norm = np.linalg.norm(centred, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = (centred @ template_unit) / norm
    return np.where(norm > 1e-12, ncc, 0.0)


def _template(grey, pixel, cols, offsets) -> tuple[np.ndarray, np.ndarray]:
    """The raw reference patch and its normalised (zero-mean, ramp-free, unit) version."""
    raw = _sample(grey, pixel[0] + offsets[:, 0], pixel[1] + offsets[:, 1], cols)
    centred = _ramp_free(raw[None], offsets)[0]
    norm = np.linalg.norm(centred)
    return raw, (centred / norm if norm > 0 else centred)


def _interpolated_noise_factor(positions: np.ndarray) -> float:
    """Mean of ``sum w^2`` over bilinear samples at ``positions`` (..., 2): the factor by
    which interpolation scales the variance of white pixel noise (1 on the pixel grid,
    1/4 midway between four pixels)."""
    frac = positions - np.floor(positions)
    per_axis = (1.0 - frac) ** 2 + frac**2
    return float(np.mean(per_axis[..., 0] * per_axis[..., 1]))


def _signal_score(ncc, template_pos, template_raw, other_pos, other_raw, offsets, noise) -> float:
    """The NCC corrected for image noise: an estimate of the correlation of the signals.

    Notes
    -----
    With independent noise of variance ``n1``, ``n2`` in two patches of signal-plus-noise
    variance ``v1``, ``v2``, the expected NCC of two identical signals is
    ``sqrt((1 - n1/v1)(1 - n2/v2))``; dividing by it makes the score comparable between
    clean and noisy images (and between well and weakly textured patches), so one
    threshold serves both. Each factor is floored at 0.05 (such a patch is refused as
    untextured before this is used) and the result is capped at 1.
    """
    dof = offsets.shape[0] - 3
    pairs = [
        (float(np.sum(_ramp_free(raw[None], offsets) ** 2)) / dof,
         noise**2 * _interpolated_noise_factor(pos))
        for pos, raw in ((template_pos, template_raw), (other_pos, other_raw))
    ]  # fmt: skip
    return float(noise_corrected_score(ncc, *pairs))


def noise_corrected_score(ncc, first, second) -> np.ndarray:
    """``ncc / sqrt((1 - n1/v1)(1 - n2/v2))`` (vectorised): each of ``first``, ``second``
    is a window's ``(v, n)``, its variance about its plane per degree of freedom and its
    noise variance; each factor floored at 0.05 (0.05 where ``v`` is not positive), the
    score capped at 1 (:func:`_signal_score`'s notes)."""
    factors = []
    for variance, noise_var in (first, second):
        variance = np.asarray(variance, dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.where(variance > 0, np.maximum(1.0 - noise_var / variance, 0.05), 0.05)
        factors.append(f)
    with np.errstate(invalid="ignore"):
        return np.minimum(1.0, ncc / np.sqrt(factors[0] * factors[1]))


def _search(model, grey, pixel, half: Half, settings: MatchSettings) -> _Search | None:
    """Correlate the patch at ``pixel`` along its curve in the other half."""
    curve = epipolar_curve(model, pixel, half, settings.depth_range_mm)
    m = curve.pixels.shape[0]
    if m == 0:
        return None
    target = other_half(half)
    cols = _half_columns(model, target)
    height = grey.shape[0]
    offsets = settings.offsets
    if settings.warp != "none":
        affine = _local_affine(model, pixel, half, curve)
    else:
        affine = np.broadcast_to(np.eye(2), (m, 2, 2)).copy()
    affine[~curve.inside] = np.nan
    corners = offsets[[0, -1, settings.patch - 1, -settings.patch]]  # the 4 patch corners
    corner_pos = curve.pixels[:, None, :] + np.einsum("mij,kj->mki", affine, corners)
    valid = curve.inside & np.all(_inside(corner_pos, cols, height), axis=1)
    ncc = np.full(m, np.nan)
    search = _Search(curve, valid, affine, ncc)
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return search
    pos = curve.pixels[idx, None, :] + np.einsum("mij,kj->mki", affine[idx], offsets)
    patches = _sample(grey, pos[..., 0], pos[..., 1], cols)
    _, template_unit = _template(grey, pixel, _half_columns(model, half), offsets)
    ncc[idx] = _ncc_rows(patches, template_unit, offsets)
    search.best = int(idx[np.argmax(ncc[idx])])
    return search


def _bilinear_weights(u: float, v: float) -> dict[tuple[int, int], float]:
    """Pixel weights of one bilinear sample at ``(u, v)``: {(column, row): weight}."""
    iu, iv = int(np.floor(u)), int(np.floor(v))
    fu, fv = u - iu, v - iv
    return {
        (iu, iv): (1 - fu) * (1 - fv), (iu + 1, iv): fu * (1 - fv),
        (iu, iv + 1): (1 - fu) * fv, (iu + 1, iv + 1): fu * fv,
    }  # fmt: skip


def _localisation_precision(grey, pixel, cols, offsets, direction, noise) -> float:
    """Predicted standard deviation of the match position along the search direction, px.

    Notes
    -----
    For two patches with independent noise ``sigma``, the least-squares shift along a
    unit direction ``t`` has variance ``2 sigma^2 / sum g^2`` with ``g`` the signal's
    derivative along ``t``. ``g`` is measured by central differences of the reference
    patch, which carry noise of their own: its variance per sample, ``sigma^2 sum w^2``
    (``w`` the pixel weights of the difference of two bilinear samples, the same for
    every patch sample), is subtracted from the measured energy. The derivative's mean
    is removed first: a constant slope (a brightness ramp) locates nothing, because the
    correlation is blind to gain and offset. NaN direction or no signal gives ``inf``.
    """
    if direction is None:
        return np.inf
    du, dv = direction
    plus = _sample(grey, pixel[0] + offsets[:, 0] + du, pixel[1] + offsets[:, 1] + dv, cols)
    minus = _sample(grey, pixel[0] + offsets[:, 0] - du, pixel[1] + offsets[:, 1] - dv, cols)
    g = (plus - minus) / 2.0
    weights = {k: 0.5 * w for k, w in _bilinear_weights(pixel[0] + du, pixel[1] + dv).items()}
    for k, w in _bilinear_weights(pixel[0] - du, pixel[1] - dv).items():
        weights[k] = weights.get(k, 0.0) - 0.5 * w
    noise_var = noise**2 * sum(w * w for w in weights.values())
    energy = float(np.sum((g - g.mean()) ** 2)) - (g.size - 1) * noise_var
    if not energy > 0:
        return np.inf
    return float(np.sqrt(2.0 * noise**2 / energy))


def _interpolated_noise_correlation(positions: np.ndarray) -> float:
    """Mean row sum of the correlation matrix of unit white pixel noise interpolated by
    the cubic spline at ``positions`` (n, 2): 1 for samples on the pixel grid, about
    ``1 / det(A)`` for samples packed by a compressing warp ``A``, ``0.87`` (the mean
    variance alone) for samples far apart. It scales the weight of the searched half's
    noise in the match: a smooth signal gradient sees the noise of all correlated
    samples."""
    # row i of the correlation matrix summed over j is sum_kl w_i(k, l) S(k, l), with
    # S the sum over all samples of their weights on the pixel grid; the weights beyond
    # _CORRELATION_REACH pixels are below 0.005 and are left out
    reach = _CORRELATION_REACH
    taps = np.arange(-reach, reach + 1)
    middle = slice(CARDINAL_REACH - reach, CARDINAL_REACH + reach + 1)
    base = np.floor(positions).astype(np.intp)  # (n, 2)
    wu = _tabulated_weights(positions[:, 0] - base[:, 0])[:, middle]  # (n, 2r+1)
    wv = _tabulated_weights(positions[:, 1] - base[:, 1])[:, middle]
    cu = base[:, 0, None] + taps - (base[:, 0].min() - reach)  # grid columns (n, 2r+1)
    cv = base[:, 1, None] + taps - (base[:, 1].min() - reach)
    width = int(cu.max()) + 1
    flat = (cv[:, :, None] * width + cu[:, None, :]).ravel()  # (n * (2r+1)^2,)
    weights = (wv[:, :, None] * wu[:, None, :]).ravel()
    splat = np.bincount(flat, weights=weights)
    rows = (weights * splat[flat]).reshape(positions.shape[0], -1).sum(axis=1)
    return float(np.mean(rows))


def match_precision(energy_t, n, gain, noise_ref, noise_t, misfit, correlation,
                    derivative_noise: float | None = None) -> np.ndarray:  # fmt: skip
    """Predicted standard deviation of the matched pixel along the curve, px of the
    searched half (see the module notes, *Precision*); vectorised over its arguments.

    ``energy_t`` is the signal's derivative energy along the curve in the searched half
    (grey levels^2 / px^2, over ``n`` samples), ``gain`` the brightness ratio of the
    halves, ``noise_ref`` and ``noise_t`` the noise of the reference and searched half,
    ``misfit`` the two patches' difference beyond noise per sample
    (:func:`_measured_misfit`) and ``correlation`` from
    :func:`_interpolated_noise_correlation`; ``derivative_noise`` the variance of the
    searched half's interpolated derivative per unit pixel noise, along any unit
    direction (default the plain spline's, about 2.16 per px^2:
    :attr:`~endomeasure.interpolation.NoiseTransfer.derivative`; less after a
    prefilter). Returns ``inf``
    where ``energy_t`` is not positive. The dense search
    (:mod:`endomeasure.measure.dense`) uses it per pixel.
    """
    energy = np.asarray(energy_t, dtype=np.float64)
    ok = energy > 0
    safe = np.where(ok, energy, 1.0)
    first = (gain**2 * noise_ref**2 + correlation * noise_t**2) / safe
    if derivative_noise is None:
        derivative_noise = noise_transfer().derivative
    second = n * derivative_noise * noise_t**2 / safe
    return np.where(ok, np.sqrt(first * (1.0 + second) + misfit**2 / safe), np.inf)


def _match_precision(
    energy_t: float, n: int, gain: float, noise_ref: float, noise_t: float, misfit: float,
    correlation: float,
) -> float:  # fmt: skip
    """:func:`match_precision` for one match, as a float."""
    return float(match_precision(energy_t, n, gain, noise_ref, noise_t, misfit, correlation))


def _search_direction(search: _Search, index: int) -> np.ndarray | None:
    """Unit direction in the reference half that mimics moving along the curve at sample
    ``index`` (or at the middle of the usable samples if ``index`` is negative)."""
    usable = np.flatnonzero(search.curve.inside & np.isfinite(search.affine).all(axis=(1, 2)))
    if usable.size < 2:
        return None
    k = int(index) if index >= 0 else int(usable[usable.size // 2])
    lo, hi = usable[max(0, np.searchsorted(usable, k) - 2)], usable[-1]
    lo = max(lo, usable[0])
    hi = min(usable[min(usable.size - 1, np.searchsorted(usable, k) + 2)], hi)
    tangent = search.curve.pixels[hi] - search.curve.pixels[lo]
    try:
        back = np.linalg.solve(search.affine[k], tangent)
    except np.linalg.LinAlgError:
        return None
    norm = np.linalg.norm(back)
    return back / norm if np.isfinite(norm) and norm > 0 else None


def _curve_tangent(pixels: np.ndarray, valid: np.ndarray, index: int) -> np.ndarray:
    """Unit tangent of the curve at sample ``index`` (from the valid samples around it)."""
    usable = np.flatnonzero(valid)
    k = int(np.searchsorted(usable, index))
    lo = usable[max(0, k - 2)]
    hi = usable[min(usable.size - 1, k + 2)]
    tangent = pixels[hi] - pixels[lo]
    return tangent / np.linalg.norm(tangent)


def _run_end(valid: np.ndarray, best: int) -> bool:
    """Whether ``best`` is the first or last sample of its run of valid samples."""
    m = valid.size
    return best == 0 or best == m - 1 or not valid[best - 1] or not valid[best + 1]


def _second_peak(ncc: np.ndarray, valid: np.ndarray, best: int) -> float:
    """Highest NCC outside the main lobe (where NCC falls monotonically from the peak)."""
    values = np.where(valid, ncc, -np.inf)
    lo = best
    while lo > 0 and values[lo - 1] <= values[lo] and np.isfinite(values[lo - 1]):
        lo -= 1
    hi = best
    while hi < values.size - 1 and values[hi + 1] <= values[hi] and np.isfinite(values[hi + 1]):
        hi += 1
    rest = np.concatenate([values[:lo], values[hi + 1 :]])
    rest = rest[np.isfinite(rest)]
    return float(rest.max()) if rest.size else -np.inf


def _parabola_offset(y_minus: float, y0: float, y_plus: float) -> float:
    """Vertex of the parabola through (-1, y_minus), (0, y0), (1, y_plus), in (-0.5, 0.5)."""
    denom = y_minus - 2.0 * y0 + y_plus
    if not denom < 0:
        return 0.0
    return float(np.clip(0.5 * (y_minus - y_plus) / denom, -0.5, 0.5))


def _at_parameter(values: np.ndarray, k: int, s: float) -> np.ndarray:
    """Linear interpolation of per-sample ``values`` at curve parameter ``k + s``."""
    j = k + 1 if s >= 0 else k - 1
    return values[k] + abs(s) * (values[j] - values[k])


def _patch_warp(model, pixel, half: Half, depth_mm: float, offsets, affine) -> np.ndarray:
    """Offsets of the patch samples in the other half, shape (n, 2), px.

    Exact for a surface of constant z at ``depth_mm``: every reference sample's ray is
    met with that plane and projected. Over a patch the map between the halves of the
    raytrace model is far from affine (the affine approximation leaves a bias that grows
    with the square of the patch size); the affine offsets ``A delta`` are the fallback
    where a sample cannot be projected.
    """
    rays = model.rays(pixel + offsets, half)
    t = (depth_mm - rays.origins[:, 2]) / rays.directions[:, 2]
    points = rays.origins + t[:, None] * rays.directions
    projected = model.project(points, other_half(half)).pixels
    centre = offsets.shape[0] // 2  # offsets are symmetric, row-major: the middle is (0, 0)
    warped = projected - projected[centre]
    if not np.all(np.isfinite(warped)):
        return offsets @ affine.T
    return warped


def _photometric_design(template: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Columns of the brightness model between the halves, (n, 4): the searched patch is
    ``a T + b + c . delta`` of the reference patch ``T`` at offsets ``delta``: gain,
    offset and a ramp. A ramp of the gain as well (``(d . delta) T``, for vignetting that
    scales the texture's contrast) was tried and left out: on an edge it mimics a shift,
    and in a one-off trial the marks of the default preset's scene and of random design 2
    matched worse with it (design 1's better), which no script reruns."""
    du, dv = offsets[:, 0], offsets[:, 1]
    return np.stack([template, np.ones(du.size), du, dv], axis=-1)


def _refine(
    grey, q0, warped, offsets, template_raw, cols, height, shape: bool = True, noise: float = 0.0
) -> tuple[np.ndarray, np.ndarray] | None:
    """2-D Gauss-Newton refinement of the match (Lucas-Kanade on the warped patch).

    Minimises ``sum (I(q + w(delta) + B delta) - P(T)(delta))^2`` over the pixel ``q``,
    a small linear shape correction ``B`` (2x2: the surface's tilt, which the
    constant-depth warp ``w`` ignores; left out if not ``shape``) and the brightness
    model ``P`` between the halves (:func:`_photometric_design`: gain, offset and a
    ramp; vignetting, illumination fall-off and the apex band differ between the
    halves). With the noise ``noise`` (grey levels) of the searched half, the sum is
    corrected by the expected noise energy of the interpolated samples,
    ``- noise^2 sum V(q + w + B delta)`` (:func:`_spline_noise_variance`; see the notes).

    Returns
    -------
    (q, offsets) : the refined pixel and the final patch offsets in the other half, or
    None if the patch leaves the half, the solve diverges or the pixel moves more than
    the allowed shift from the curve peak.

    Notes
    -----
    Interpolated noise is weaker between pixels (variance 0.57 of the pixels' midway
    between four of them), so the plain sum of squares is smallest where the samples
    fall between pixels, by some ``0.4 n noise^2`` over ``n`` samples: on weak texture
    this competes with the signal's own curvature (the sum of squared derivatives) and
    pulls the match towards half-pixel positions. Subtracting the expectation removes
    that pull.
    """
    du, dv = offsets[:, 0], offsets[:, 1]
    photometric = -_photometric_design(template_raw, offsets)
    q = q0.copy()
    B = np.zeros((2, 2))
    for _ in range(_REFINE_ITERATIONS):
        rel = warped + offsets @ B.T
        pos = q + rel
        if not np.all(_inside(pos, (cols[0] + 0.5, cols[1] - 0.5), height)):
            return None
        values, gu, gv = _sample_spline(grey, pos, cols)
        geometric = [gu, gv, gu * du, gu * dv, gv * du, gv * dv] if shape else [gu, gv]
        jac = np.concatenate([np.stack(geometric, axis=-1), photometric], axis=-1)
        coef = np.linalg.lstsq(-photometric, values, rcond=None)[0]  # best photometric fit
        residual = values + photometric @ coef
        if noise > 0:
            # Gauss-Newton on sum r^2 - noise^2 sum V: the correction's gradient enters
            # the right-hand side (its curvature is left out, like that of r)
            _, grad = _spline_noise_variance(pos)
            corr = [grad[:, 0], grad[:, 1]]
            if shape:
                corr += [grad[:, 0] * du, grad[:, 0] * dv, grad[:, 1] * du, grad[:, 1] * dv]
            rhs = -jac.T @ residual
            rhs[: len(corr)] += 0.5 * noise**2 * np.sum(np.stack(corr, axis=-1), axis=0)
            step = np.linalg.lstsq(jac.T @ jac, rhs, rcond=None)[0]
        else:
            step = np.linalg.lstsq(jac, -residual, rcond=None)[0]
        q = q + step[:2]
        if shape:
            B = B + step[2:6].reshape(2, 2)
        if (
            not np.all(np.isfinite(q))
            or np.linalg.norm(q - q0) > _REFINE_MAX_SHIFT_PX
            or np.abs(B).max() > _REFINE_MAX_SHAPE
        ):
            return None
        if np.linalg.norm(step[:2]) < _REFINE_TOL_PX:
            break
    return q, warped + offsets @ B.T


def _ramp_free(patches: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Remove each patch's mean and least-squares brightness ramp.

    ``patches`` (K, n) sampled at ``offsets`` (n, 2), a symmetric grid, so the constant
    and the two ramps are orthogonal and can be removed one after the other. Comparing
    ramp-free patches makes the correlation blind to the different brightness slopes of
    the two halves (vignetting, the apex band).
    """
    out = patches - patches.mean(axis=-1, keepdims=True)
    for axis in range(2):
        d = offsets[:, axis]
        out = out - np.outer(out @ d / (d @ d), d)
    return out


def _refuse(pixel, half, status, message, **fields) -> Match:
    nan2 = np.full(2, np.nan)
    values = dict(
        match=nan2, candidate=nan2, score=np.nan, signal_score=np.nan, second_ratio=np.nan,
        depth_mm=np.nan, point=np.full(3, np.nan), ray_gap_mm=np.nan, precision_px=np.nan,
        noise_sigma=np.nan, back_px=np.nan, curve=np.empty((0, 2)), curve_depths_mm=np.empty(0),
    )  # fmt: skip
    values.update(fields)
    return Match(pixel, half, status, message, **values)


def _fmt(q: np.ndarray) -> str:
    return f"({q[0]:.1f}, {q[1]:.1f})"


# ----- one point's search, step by step -------------------------------------------------


class _Refused(Exception):
    """A refusal inside :func:`_match_one` (never leaves it): the status and message."""

    def __init__(self, status: MatchStatus, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


@dataclasses.dataclass(frozen=True, eq=False)
class _Query:
    """One point's search: what every step of :func:`_match_one` reads."""

    model: CameraModel
    image: _Image
    pixel: np.ndarray
    half: Half
    settings: MatchSettings

    @functools.cached_property
    def cols(self) -> tuple[int, int]:
        return _half_columns(self.model, self.half)

    @functools.cached_property
    def target(self) -> Half:
        return other_half(self.half)

    @functools.cached_property
    def target_cols(self) -> tuple[int, int]:
        return _half_columns(self.model, self.target)

    @functools.cached_property
    def offsets(self) -> np.ndarray:
        return self.settings.offsets

    @property
    def where(self) -> str:
        return f"point {_fmt(self.pixel)} in the {self.half.label} half"

    @property
    def depths(self) -> str:
        near, far = self.settings.depth_range_mm
        return f"{near:g}-{far:g} mm"

    def refuse(self, status: MatchStatus, message: str) -> _Refused:
        return _Refused(status, f"{self.where}{message}")


class _Peak(NamedTuple):
    """The curve sample that correlates best, with the reference patch it was scored by."""

    best: int
    score: float
    signal: float
    template_raw: np.ndarray  # (n,) bilinear samples of the reference patch
    template_unit: np.ndarray  # (n,) the same, ramp-free and of unit norm


class _Refined(NamedTuple):
    """The sub-pixel match: the pixel, where its patch samples lie and what fits them."""

    pixel: np.ndarray  # (2,) px, in the other half
    warped: np.ndarray  # (n, 2) px, the final patch offsets in the other half
    positions: np.ndarray  # (n, 2) px, pixel + warped
    template_fine: np.ndarray  # (n,) spline samples of the reference patch
    target_noise: float  # grey levels, around the match


def _match_one(query: _Query) -> Match:
    """The search of one point (module notes): each step either refines what is known
    about the point or refuses it, with what is known so far in the diagnostics."""
    fields: dict[str, Any] = {}
    try:
        _check_patch_fits(query)
        noise = _query_noise(query)
        fields.update(noise_sigma=noise)
        search = _forward_search(query)
        precision = _check_texture(query, search, noise, fields)
        peak = _check_peak(query, search, noise, fields)
        if query.settings.check_back:
            _check_back(query, search, peak, fields)
        _check_score(query, peak.score, peak.signal, "best correlation")
        refined = _refine_match(query, search, peak)
        final, signal = _final_score(query, refined, peak, noise)
        fields.update(score=final, signal_score=signal)
        _check_score(query, final, signal, "correlation at the refined match")
        fields["precision_px"] = _refined_precision(query, search, refined, precision, noise)
        return _matched(query, search, refined.pixel, fields)
    except _Refused as refusal:
        return _refuse(query.pixel, query.half, refusal.status, refusal.message, **fields)


def _check_patch_fits(query: _Query) -> None:
    patch = query.settings.patch
    corners = query.pixel + query.offsets[[0, -1]]
    if not np.all(_inside(corners, query.cols, query.image.grey.shape[0])):
        raise query.refuse(
            MatchStatus.OUTSIDE,
            f" is closer than {patch // 2 + 1} px to the edge of its half, so its "
            f"{patch}x{patch} patch does not fit",
        )


def _query_noise(query: _Query) -> float:
    """The image noise at the query point, grey levels: given or estimated, floored."""
    given = query.settings.noise_sigma
    noise = (
        given
        if given is not None
        else _local_noise(query.image.grey, query.pixel, query.cols, query.settings.patch)
    )
    return max(float(noise), query.image.floor)


def _forward_search(query: _Query) -> _Search:
    search = _search(query.model, query.image.grey, query.pixel, query.half, query.settings)
    if search is None or not search.curve.inside.any():
        raise query.refuse(
            MatchStatus.OUTSIDE,
            f" is not seen by the other half at {query.depths} (its ray does not project into it)",
        )
    return search


def _check_texture(query: _Query, search: _Search, noise: float, fields: dict) -> float:
    """The reference patch's predicted precision along the curve, px (the first-order
    estimate of :func:`_localisation_precision`), refused if too poor; without texture
    nothing later is meaningful, so this comes first."""
    curve, valid = search.curve, search.valid
    direction = _search_direction(search, search.best)
    precision = _localisation_precision(
        query.image.grey, query.pixel, query.cols, query.offsets, direction, noise
    )
    # the noise term alone until the match is refined and its misfit measured
    fields.update(
        precision_px=precision, back_px=np.nan,
        curve=curve.pixels[valid], curve_depths_mm=curve.depths_mm[valid],
    )  # fmt: skip
    limit = query.settings.max_precision_px
    if not precision <= limit:
        raise query.refuse(
            MatchStatus.UNTEXTURED,
            " has too little texture along the search direction ("
            + (
                f"it would locate the match to {precision:.2f} px, worse than {limit:g} px)"
                if np.isfinite(precision)
                else "nothing there rises above the image noise)"
            ),
        )
    if search.best < 0:
        raise query.refuse(
            MatchStatus.OUTSIDE,
            f" is not seen by the other half at {query.depths} (no part of its epipolar "
            "curve has room for the patch there)",
        )
    return precision


def _check_peak(query: _Query, search: _Search, noise: float, fields: dict) -> _Peak:
    """Score the curve's best sample and refuse it if a second peak rivals it or it
    lies where the searchable curve ends."""
    grey, offsets, settings = query.image.grey, query.offsets, query.settings
    best = search.best
    score = float(search.ncc[best])
    candidate = search.curve.pixels[best]
    template_raw, template_unit = _template(grey, query.pixel, query.cols, offsets)
    other_pos = candidate + offsets @ search.affine[best].T
    other_raw = _sample(grey, other_pos[:, 0], other_pos[:, 1], query.target_cols)
    signal = _signal_score(
        score, query.pixel + offsets, template_raw, other_pos, other_raw, offsets, noise
    )
    second = _second_peak(search.ncc, search.valid, best)
    ratio = max(second, 0.0) / score if score > 0 else np.nan
    fields.update(candidate=candidate, score=score, signal_score=signal, second_ratio=ratio)
    # ambiguous only if the best is itself credible (a random landscape of low
    # correlations says nothing about repetition); a second peak within the ratio of a
    # credible best is then a second credible candidate, even if noise puts it just under
    # the threshold (requiring the second to pass on its own split repeated texture at
    # the threshold between 'ambiguous' and a failed back search, 'outside')
    if ratio > settings.max_second_ratio and signal >= settings.min_score:
        raise query.refuse(
            MatchStatus.AMBIGUOUS,
            f": a second candidate scores {ratio:.2f} of the best "
            f"(> {settings.max_second_ratio:g}), e.g. repeated texture",
        )
    if _run_end(search.valid, best):
        reason = (
            f"the end of the working depth range ({query.depths})"
            if best in (0, search.ncc.size - 1)
            else "the edge of the other half"
        )
        raise query.refuse(
            MatchStatus.OUTSIDE,
            f": the best candidate lies at {reason}, so the match may be beyond it",
        )
    return _Peak(best, score, signal, template_raw, template_unit)


def _check_back(query: _Query, search: _Search, peak: _Peak, fields: dict) -> None:
    """Search back from the candidate; refuse the point unless it is found again."""
    candidate = search.curve.pixels[peak.best]
    back = _search(query.model, query.image.grey, candidate, query.target, query.settings)
    noise_factor = peak.signal / peak.score if peak.score > 0 else np.nan
    mutual, back_px = _mutual(back, query.pixel, query.settings, noise_factor)
    fields.update(back_px=back_px)
    if not mutual:
        why = (
            f"its best candidate {_fmt(candidate)} matches a different point back"
            if not back_px <= BACK_TOLERANCE_PX
            else f"nothing along its epipolar curve correlates credibly (best "
            f"{peak.score:.2f}, {peak.signal:.2f} corrected for noise, below "
            f"{query.settings.min_score:g})"
        )
        raise query.refuse(
            MatchStatus.OUTSIDE,
            f": {why}, so the point is probably not seen in the other half (occluded or "
            "out of its view)",
        )


def _check_score(query: _Query, score: float, signal: float, what: str) -> None:
    if not signal >= query.settings.min_score:
        raise query.refuse(
            MatchStatus.LOW_SCORE,
            f": {what} {score:.2f} ({signal:.2f} corrected for noise) is below "
            f"{query.settings.min_score:g}",
        )


def _refine_match(query: _Query, search: _Search, peak: _Peak) -> _Refined:
    """Sub-pixel match: a parabola along the curve, then the 2-D refinement
    (:func:`_refine`; its start is kept where it fails)."""
    grey, offsets, settings = query.image.grey, query.offsets, query.settings
    curve, best, ncc = search.curve, peak.best, search.ncc
    s = _parabola_offset(ncc[best - 1], ncc[best], ncc[best + 1])
    q0 = _at_parameter(curve.pixels, best, s)
    affine = _at_parameter(search.affine, best, s)
    depth = float(1.0 / _at_parameter(1.0 / curve.depths_mm, best, s))
    if settings.warp == "plane":
        warped = _patch_warp(query.model, query.pixel, query.half, depth, offsets, affine)
    else:
        warped = offsets @ affine.T  # the identity for warp 'none'
    shape = settings.warp != "none"  # plain NCC: translation only
    # the refinement compares spline-interpolated patches on both sides (see _sample_spline),
    # the reference's under the relative gain field of the two views
    template_fine = _sample_spline(grey, query.pixel + offsets, query.cols)[0]
    template_fine = template_fine * np.exp(offsets @ _relative_gain(query, q0, depth, affine))
    target_noise = max(_local_noise(grey, q0, query.target_cols, settings.patch), query.image.floor)
    refined = _refine(
        grey, q0, warped, offsets, template_fine, query.target_cols, grey.shape[0], shape,
        target_noise,
    )  # fmt: skip
    q, warped = refined if refined is not None else (q0, warped)
    return _Refined(q, warped, q + warped, template_fine, target_noise)


def _relative_gain(query: _Query, q0: np.ndarray, depth: float, affine: np.ndarray) -> np.ndarray:
    """Slope of the log brightness ratio, searched over reference view, at the match start
    ``q0``, per px of reference offset (2,) (module notes, "Relative gain field").

    The window is the widest up to :data:`GAIN_REACH` patch half-widths that fits both
    halves; zero where not even the patch and the smoothing's border fit, or where the
    window is too dark (ten times the quantisation noise) for a ratio.
    """
    grey, settings = query.image.grey, query.settings
    edge = int(np.ceil(GAIN_SMOOTH_PX))  # the border where the smoothing reaches outside
    height = grey.shape[0]
    for reach in range(int(round(GAIN_REACH * (settings.patch // 2))), settings.patch // 2, -1):
        steps = np.arange(-reach, reach + 1, dtype=np.float64)
        window = np.stack(np.meshgrid(steps, steps), axis=-1).reshape(-1, 2)
        if settings.warp == "plane":
            warped = _patch_warp(query.model, query.pixel, query.half, depth, window, affine)
        else:
            warped = window @ affine.T
        views = ((query.pixel + window, query.cols), (q0 + warped, query.target_cols))
        if all(np.all(_inside(pos, (c[0] + 0.5, c[1] - 0.5), height)) for pos, c in views):
            break
    else:
        return np.zeros(2)
    side = steps.size
    smooth = [
        gaussian_filter(_sample(grey, pos[:, 0], pos[:, 1], cols).reshape(side, side),
                        GAIN_SMOOTH_PX, mode="nearest")
        for pos, cols in views
    ]  # fmt: skip
    inner = np.zeros((side, side), dtype=bool)
    inner[edge:-edge, edge:-edge] = True
    floor = 10.0 * max(query.image.floor, 1e-12)
    use = inner & (smooth[0] > floor) & (smooth[1] > floor)
    if use.sum() < settings.patch:
        return np.zeros(2)
    design = np.column_stack([np.ones(int(use.sum())), window.reshape(side, side, 2)[use]])
    ratio = np.log(smooth[1][use] / smooth[0][use])
    return np.linalg.lstsq(design, ratio, rcond=None)[0][1:]


def _final_score(
    query: _Query, refined: _Refined, peak: _Peak, noise: float
) -> tuple[float, float]:
    """NCC and its noise-corrected value (``signal_score``) at the refined match."""
    grey, offsets, pos = query.image.grey, query.offsets, refined.positions
    other_raw = _sample(grey, pos[:, 0], pos[:, 1], query.target_cols)
    final = float(_ncc_rows(other_raw[None], peak.template_unit, offsets)[0])
    signal = _signal_score(
        final, query.pixel + offsets, peak.template_raw, pos, other_raw, offsets, noise
    )
    return final, signal


def _refined_precision(
    query: _Query, search: _Search, refined: _Refined, precision: float, noise: float
) -> float:
    """``precision_px`` of the match: :func:`_match_precision` in the searched half, at
    the final warp, from the reference patch's first-order ``precision`` (module notes)."""
    offsets, pos, warped = query.offsets, refined.positions, refined.warped
    a_fit = np.linalg.lstsq(offsets, warped - warped.mean(axis=0), rcond=None)[0].T
    tangent = _curve_tangent(search.curve.pixels, search.valid, search.best)
    try:
        stretch = 1.0 / float(np.linalg.norm(np.linalg.solve(a_fit, tangent)))
    except np.linalg.LinAlgError:
        stretch = np.nan
    n = offsets.shape[0]
    design = _photometric_design(refined.template_fine, offsets)
    fine = _sample_spline(query.image.grey, pos, query.target_cols)[0]
    coef = np.linalg.lstsq(design, fine, rcond=None)[0]
    gain = float(coef[0])
    misfit = _measured_misfit(
        fine - design @ coef, gain, noise, refined.target_noise, query.pixel + offsets, pos,
        fitted=design.shape[1],
    )  # fmt: skip
    energy_ref = 2.0 * noise**2 / precision**2
    return _match_precision(
        energy_ref / stretch**2, n, gain, noise, refined.target_noise, misfit,
        _interpolated_noise_correlation(pos),
    )  # fmt: skip


def _measured_misfit(
    residual: np.ndarray, gain: float, noise_ref: float, noise_t: float, ref_pos, target_pos,
    fitted: int,
) -> float:  # fmt: skip
    """What the two halves' patches differ by beyond their noise, grey levels per sample.

    ``residual`` (n,): the searched patch minus the reference patch's photometric fit
    (:func:`_photometric_design`, ``fitted`` parameters) at the match. Its expected mean
    square from noise alone is ``(gain^2 s_r^2 V_r + s_t^2 V_t) (n - fitted) / n`` with
    ``V`` the variance of spline-interpolated unit noise at the samples
    (:func:`_spline_noise_variance`); what is left is the misfit the search's model of
    the two views does not explain (blur and aberrations that differ between the halves,
    highlights, the surface's own shape), measured on this match, as a least-squares
    fit's a-posteriori variance is; zero where the residual is no larger than the noise.
    """
    n = residual.size
    expected = (
        (
            gain**2 * noise_ref**2 * float(np.mean(_spline_noise_variance(ref_pos)[0]))
            + noise_t**2 * float(np.mean(_spline_noise_variance(target_pos)[0]))
        )
        * (n - fitted)
        / n
    )
    return float(np.sqrt(max(float(np.mean(residual**2)) - expected, 0.0)))


def _matched(query: _Query, search: _Search, q: np.ndarray, fields: dict) -> Match:
    """The accepted match with its point: the common perpendicular of the two rays."""
    origin, direction = search.curve.origin, search.curve.direction
    ray = query.model.rays(q, query.target)
    perp = common_perpendicular(origin, direction, ray.origins, ray.directions)
    if ray.status != Status.OK or perp.status != Status.OK:
        raise query.refuse(
            MatchStatus.OUTSIDE,
            f": the matched pixel {_fmt(q)} has no ray that meets the point's ray",
        )
    foot = origin + perp.s1 * direction
    return Match(
        query.pixel, query.half, MatchStatus.OK, "", match=q, depth_mm=float(foot[2]),
        point=perp.midpoint, ray_gap_mm=float(perp.gap), **fields,
    )  # fmt: skip


def _mutual(
    back: _Search | None, pixel: np.ndarray, settings: MatchSettings, noise_factor: float
) -> tuple[bool, float]:
    """Whether the back search from the candidate confirms the query pixel.

    Confirmed if its peak is within :data:`BACK_TOLERANCE_PX` of the query, or if the
    back curve passes the query and scores it within the ambiguity ratio of its best,
    in both cases only if it scores the query as a credible match (its NCC times
    ``noise_factor``, the forward search's noise correction, reaching ``min_score``):
    repeated texture is then reported as ambiguous, not as a point seen once, while a
    flat landscape of low correlations, what a point the other half does not see
    meets, confirms nothing.
    """
    if back is None or back.best < 0:
        return False, np.nan
    distance = float(np.linalg.norm(back.curve.pixels[back.best] - pixel))
    if distance <= BACK_TOLERANCE_PX:
        return bool(back.ncc[back.best] * noise_factor >= settings.min_score), distance
    gaps = np.linalg.norm(back.curve.pixels - pixel, axis=-1)
    gaps[~back.valid] = np.inf
    nearest = int(np.argmin(gaps))
    if gaps[nearest] > BACK_TOLERANCE_PX:
        return False, distance
    best = back.ncc[back.best]
    at_query = back.ncc[nearest]
    credible = bool(at_query * noise_factor >= settings.min_score)
    return bool(at_query >= settings.max_second_ratio * best and credible), distance


def find_matches(
    model: CameraModel,
    image: np.ndarray,
    pixels: np.ndarray,
    half: Half | str,
    settings: MatchSettings = MatchSettings(),  # noqa: B008 (immutable)
) -> list[Match]:
    """Find, for each point of one half, the point of the other half that shows the same
    surface point (the search is described in the module notes).

    Parameters
    ----------
    model : CameraModel
        Calibrated model of the probe.
    image : ndarray, shape (H, W) or (H, W, 3)
        The whole split image (uint8, uint16 or float grey levels; colour is averaged).
    pixels : array_like, shape (N, 2), px
        Full-image coordinates of the points in ``half``.
    half : Half or {'left', 'right'}
        The half the points are in.
    settings : MatchSettings, optional
        How to search and when to refuse (e.g. ``MatchSettings(patch=21)``); the
        defaults of :class:`MatchSettings` if not given.

    Returns
    -------
    list of Match
        One per point, in order: ``status`` OK with the match, score, depth, point and
        ray gap, or a refusal with a reason code and a one-line message.

    Raises
    ------
    BadInputError
        For an image that does not fit the model or a point outside its half (settings
        are checked when a :class:`MatchSettings` is made).
    """
    half = Half.parse(half)
    image = _grey(image, model)
    points = np.asarray(pixels, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise BadInputError(f"points must have shape (N, 2), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise BadInputError("a point has NaN or infinite coordinates")
    inside = in_half(points, half, model.config.split, model.config.image_size)
    if not np.all(inside):
        bad = points[np.flatnonzero(~inside)[0]]
        raise BadInputError(
            f"point {_fmt(bad)} is not in the {half.label} half",
            hint=f"the split is at column {model.config.split}",
        )
    return [_match_one(_Query(model, image, q.copy(), half, settings)) for q in points]


def find_match(
    model: CameraModel,
    image: np.ndarray,
    pixel: np.ndarray,
    half: Half | str,
    settings: MatchSettings = MatchSettings(),  # noqa: B008 (immutable)
) -> Match:
    """The match of one point, ``pixel`` (array_like, shape (2,), px, full-image
    coordinates in ``half``); the rest as :func:`find_matches`."""
    pixel = np.asarray(pixel, dtype=np.float64)
    if pixel.shape != (2,):
        raise BadInputError(f"a point needs two coordinates (u, v), got shape {pixel.shape}")
    return find_matches(model, image, pixel[None], half, settings)[0]
