"""Finding the split column: the dark band the out-of-focus prism apex casts between halves.

Physics used (and nothing about any one probe's band)
-----------------------------------------------------
The apex sends almost no light to the sensor and what it sends is out of focus, so the
image is the scene seen by each half times a transmission dip about the apex image,

    I(u, v) = b + S(u, v) T(u - a(v)),    T symmetric, T(|x| >= X) = 1,

with ``b`` the sensor's dark level, ``S`` each half's view (discontinuous at ``a``: the
halves see different things), ``a(v)`` the apex image (any column, tilted or bent by the
lens distortion) and ``T`` the band: the same for every image of a probe, whatever the
scene. Its width, depth and shape are estimated, not assumed.

Method
------
1. Per image (:func:`split_evidence`): the mean of each of ``K`` row bands per column
   (a profile) and the standard deviation of that mean from the pixel noise (robust
   spread of vertical pixel differences, which scene content along rows barely touches).
2. Coarse column (:func:`find_split_in_set`): at scales ``s`` from 1.5 px up, the valley
   depth ``min(left, right) - centre`` (box means at ``s`` to ``3 s`` each side against
   the centre ``s`` wide) in units of its noise; a step in the scene is no valley, only a
   column darker than both sides is. Per scale: the median over the images (the band is
   fixed, moving content is not), summed over the row bands; each scale votes with its
   normalised score; the column with the most votes is the band (the band is a valley
   at every scale from its own width up, a gap between two boards only at large ones).
   The whole width is searched; the border columns, with nothing beyond them, are not.
3. Fit (``_BandFit``): the model above on every profile of every image near the band,
   with ``S`` linear on each side of ``a`` per profile (a pixel on a side by the share of
   its box there), ``T`` piecewise linear in ``|x|`` with knots ``X/8`` apart, its dip
   never growing away from the apex (a blurred shadow has one minimum), shared by all
   profiles, and ``b`` shared, never above the darkest row-band mean. A sample's error is
   its pixel noise and ``SCENE_MISFIT`` of its light (so that one bright edge next to
   the band cannot outvote every image). ``a_k`` per row band by a grid search of the
   squared residuals, each capped at ``OUTLIER_SCALES^2``, with each candidate's sides
   refitted without the samples beyond that (scene the model cannot explain); ``T`` and
   ``b`` by linear least squares in turn. The extent ``X`` (how far the dip reaches):
   trial fits on a geometric scan of ``X``; where the fitted dip's half-width ``h``
   makes ``2.5 h / X`` fall through 1 (the largest such ``X``), then ``X = 2.5 h``
   (``EXTENT_PER_HALF_WIDTH``). The first pass follows the band from the middle row band
   outwards; the later ones re-centre every window on the fitted apex line. The fit is
   made twice: on every profile, and on only those with light on both sides of the dip
   (the darker side's light above the scene misfit of the brighter side's): where one
   side is black, a blurred scene edge on the other (a small board on a black
   background) fits a flank of the band at any column, while a board under the band
   shows its true flank; the fit whose band is the more significant valley over every
   profile (the test below, ``MIN_VALLEY_SIGMAS``) is kept.
4. The apex line ``a(v)``: a quadratic through the row bands' ``a_k``, weighted by their
   information (the cost's curvature) with one extra variance for all that brings the
   reduced chi-square to 1 (the bands' systematic scatter), and by a Gaussian in the
   distance from the middle row (``MIDDLE_WEIGHT_WIDTH``); bands off the line by more
   than 3 sigma and 1 px are dropped one at a time. Its value at the middle row is the
   band centre and ``split = floor(centre + 1)`` (the half boundary ``u = split - 0.5``
   within half a pixel of it), as the simulator's truth ``TruthOptics.apex_split``
   defines it.

How it fails
------------
A :class:`~endomeasure.errors.BadInputError` suggesting ``--split`` when no column is a
valley at any scale (a uniform image); when the band fitted is less than
``MIN_VALLEY_SIGMAS`` darker than both its sides (noise, smooth vignetting: no band);
or when it is as wide as allowed (``MAX_BAND_FRACTION``). One image can be fooled by a
dark vertical stripe in the scene; over an image set the median over the images in the
coarse search and the fit's robust costs discount what moves. Figures on random
designs: ``bench/accuracy_split.py`` (``docs/accuracy.md``, section ``split-designs``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from endomeasure.errors import BadInputError

__all__ = [
    "SplitEstimate",
    "SplitEvidence",
    "find_split",
    "find_split_in_set",
    "split_evidence",
    "to_gray_float",
]

MIN_IMAGE_WIDTH = 16
ROW_BANDS = 12
"""Row bands per image: enough to follow a tilted or bent apex image, each band still
averaging H/12 rows of pixel noise."""
SMALLEST_SCALE_PX = 1.5
"""The finest valley scale: a band narrower than this is below the optics' blur."""
MAX_BAND_FRACTION = 0.25
"""Widest band accepted (its whole dip ``2 X``), as a fraction of the image width."""
KNOTS = 8
"""Knots of the band's transmission profile ``T(|x|)`` over ``[0, X)``."""
OUTLIER_SCALES = 5.0
"""A sample further off the band model than this many of its errors is scene the model
cannot explain: it costs this many squared, and no more."""
MIDDLE_WEIGHT_WIDTH = 0.5
"""The split is the apex image at the middle row: row bands count with a Gaussian weight
in their distance from it of this many half-heights (the ends, where vignetting leaves
least light, shape the line's tilt and bend but hardly its middle)."""
LINE_REJECT_SIGMAS = 3.0
"""A row band further than this many sigmas (and 1 px) off the apex line is dropped."""
MIN_VALLEY_SIGMAS = 6.0
"""A band is at least this many standard errors darker than both its sides (the best of
some thousand candidate columns and scales of pure noise reaches about 4)."""
EXTENT_PER_HALF_WIDTH = 2.5
"""The band's dip reaches this many half-widths (at half depth) from the apex: a Gaussian
dip is back within 1.3 % of full light there. The fitted extent ``X`` is where the fitted
dip's half-width is ``X / 2.5``: a shorter ``X`` truncates the dip (its half-width comes
out above ``X / 2.5``), a longer one lets the scene's shading into it (below)."""
SCENE_MISFIT = 0.04
"""How far a profile's scene may depart from the model (linear on each side across the
band's window), as a fraction of its light: added to every sample's pixel noise (without
it one bright board edge next to the band pulls the fit; ``bench/accuracy_split.py
--scene-misfit`` measures other values)."""
MIN_EXTENT_PX = 4.0
EXTENT_SCAN_STEP = 1.25
_TRUNCATED_HALF_NORMAL_MEAN = 0.6573  # E[|z| : |z| < 1.645], z ~ N(0, 1)
_FIT_ROUNDS = 4
_STEP_PX = 0.25  # grid step of the per-band search
_REWEIGHTS = 1  # reweighted fits before a candidate's cost
_SEARCH_MOVES = 4  # times a band's search moves on when its best node is at an end


@dataclasses.dataclass(frozen=True)
class SplitEstimate:
    """Where the band between the halves is.

    Attributes
    ----------
    split : int
        First column of the right half.
    centre_px : float, px
        Band centre in u at the middle row.
    width_px : float, px
        Full width of the band at half its depth.
    contrast : float
        Transmission at the band centre, ``T(0)`` (0: black, 1: no band).
    slope : float
        ``du/dv`` of the apex image at the middle row (0 for a vertical band).
    centre_sigma_px : float, px
        Standard error of ``centre_px``: the row bands' noise and their scatter about
        the apex line.
    images : int
        Images the estimate combines.
    significance : float
        How many standard errors the band is darker than both its sides.
    """

    split: int
    centre_px: float
    width_px: float
    contrast: float
    slope: float = 0.0
    centre_sigma_px: float = float("nan")
    images: int = 1
    significance: float = float("nan")


@dataclasses.dataclass(frozen=True)
class SplitEvidence:
    """What one image tells about the band: row-band column profiles and their noise.

    Attributes
    ----------
    image_size : (width, height), px
    rows : ndarray, shape (K,), px
        Centre row of each row band.
    profiles : ndarray, shape (K, width), grey levels
        Mean of each row band per column.
    noise : ndarray, shape (K, width), grey levels
        Standard deviation of each mean from the pixel noise.
    """

    image_size: tuple[int, int]
    rows: np.ndarray
    profiles: np.ndarray
    noise: np.ndarray


def to_gray_float(image: np.ndarray) -> np.ndarray:
    """A grey image as float64 in 0..255, from grey or colour, 8- or 16-bit input.

    Parameters
    ----------
    image : ndarray, shape (height, width) or (height, width, channels)
        Colour channels in OpenCV's BGR(A) order; uint8, uint16 or float (0..255).
    """
    image = np.asarray(image)
    scale = 255.0 / 65535.0 if image.dtype == np.uint16 else 1.0
    data = image.astype(np.float64) * scale
    if data.ndim == 3:
        if data.shape[2] == 1:
            data = data[..., 0]
        else:
            # ITU-R BT.601 luma, as cv2.cvtColor(..., COLOR_BGR2GRAY).
            data = 0.114 * data[..., 0] + 0.587 * data[..., 1] + 0.299 * data[..., 2]
    return data


_HINT = "give the first column of the right half with --split COLUMN"


def split_evidence(image: np.ndarray, path: str | None = None) -> SplitEvidence:
    """Row-band column profiles of one image, for :func:`find_split_in_set`.

    Parameters
    ----------
    image : ndarray, shape (height, width[, channels])
    path : str, optional
        Named in the error message.

    Raises
    ------
    BadInputError
        An image too small to split.
    """
    from scipy.ndimage import gaussian_filter1d

    gray = to_gray_float(image)
    height, width = gray.shape
    if width < MIN_IMAGE_WIDTH or height < 2:
        raise BadInputError(
            f"image of {width}x{height} px is too small to split", path=path, hint=_HINT
        )
    bands = min(ROW_BANDS, height // 2)
    edges = np.linspace(0, height, bands + 1).round().astype(int)
    profiles = np.empty((bands, width))
    noise = np.empty((bands, width))
    differences = np.abs(np.diff(gray, axis=0))
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        profiles[k] = gray[lo:hi].mean(axis=0)
        sigma = _pixel_noise(differences[lo : max(lo + 1, min(hi, height - 1))])
        variance = gaussian_filter1d(sigma**2, 3.0, mode="nearest")
        # rounding to grey levels averages out only as far as the noise dithers it:
        # the mean of rounded values is off by up to exp(-2 pi^2 sigma^2) / pi levels
        bias = np.exp(-2.0 * np.pi**2 * variance) / np.pi
        noise[k] = np.sqrt(variance / (hi - lo) + bias**2)
    rows = 0.5 * (edges[:-1] + edges[1:] - 1)
    return SplitEvidence((width, height), rows, profiles, noise)


def _pixel_noise(differences: np.ndarray) -> np.ndarray:
    """Per-column pixel noise sigma from absolute differences of vertical neighbours
    (shape (n, W)): their mean over the smallest 90 % (scene edges are in the rest),
    divided by that truncated mean of a half-normal, 0.6573, and by sqrt(2)."""
    n = differences.shape[0]
    kept = max(1, int(np.ceil(0.9 * n)))
    smallest = np.partition(differences, kept - 1, axis=0)[:kept]
    return smallest.mean(axis=0) / (_TRUNCATED_HALF_NORMAL_MEAN * np.sqrt(2.0))


def find_split(image: np.ndarray, path: str | None = None) -> SplitEstimate:
    """Find the split column of one image from the dark band between the halves.

    Parameters
    ----------
    image : ndarray, shape (height, width[, channels])
    path : str, optional
        Named in the error message.

    Returns
    -------
    SplitEstimate

    Raises
    ------
    BadInputError
        No significant band (see the module notes).
    """
    return find_split_in_set([split_evidence(image, path)], path=path)


def find_split_in_set(evidence: Sequence[SplitEvidence], path: str | None = None) -> SplitEstimate:
    """Find the split column from the images of one probe (the band is fixed, the scene
    moves).

    Parameters
    ----------
    evidence : sequence of SplitEvidence
        From :func:`split_evidence`, all of one image size.
    path : str, optional
        Named in the error message (a folder or file the images came from).

    Raises
    ------
    BadInputError
        No evidence, evidence of different image sizes, or no significant band.
    """
    if not evidence:
        raise BadInputError("no images to find the split in", path=path, hint=_HINT)
    sizes = {tuple(e.image_size) for e in evidence}
    if len(sizes) > 1:
        raise BadInputError(
            f"the images differ in size ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))})",
            path=path,
            hint=_HINT,
        )
    width, height = evidence[0].image_size
    profiles = np.stack([e.profiles for e in evidence])
    noise = np.stack([e.noise for e in evidence])
    rows = evidence[0].rows
    coarse = _coarse_column(profiles, noise)
    if coarse is None:
        raise BadInputError(
            "no dark band between the halves found (no column is darker than both sides)",
            path=path,
            hint=_HINT,
        )
    # two fits: every profile, and only those with light on both sides (_BandFit.two_sided);
    # the one whose band the valley test over every profile finds the darker is kept
    best = None
    for two_sided in (False, True):
        fit, line = _fit_band(profiles, noise, rows, coarse, width, two_sided)
        half_width = fit.half_width()
        significance = (
            _valley_significance(profiles, noise, line.columns(rows), half_width)
            if line is not None and np.isfinite(half_width)
            else 0.0
        )
        if best is None or significance > best[0]:
            best = (significance, fit, line, half_width)
    significance, fit, line, half_width = best
    if not significance >= MIN_VALLEY_SIGMAS:
        raise BadInputError(
            "no dark band between the halves found (the band fitted is not darker than"
            f" both sides: {significance:.1f} sigma, needs {MIN_VALLEY_SIGMAS:g})",
            path=path,
            hint=_HINT,
        )
    if fit.extent >= 0.999 * fit.max_extent:
        raise BadInputError(
            f"the dark region found is {2 * fit.extent:.0f} px wide, too wide for the prism band",
            path=path,
            hint=_HINT,
        )
    centre, slope, centre_sigma = line.at((height - 1) / 2.0)
    return SplitEstimate(
        split=int(np.floor(centre + 1.0)),
        centre_px=float(centre),
        width_px=float(2.0 * half_width),
        contrast=float(fit.transmission(np.zeros(1))[0]),
        slope=float(slope),
        centre_sigma_px=float(centre_sigma),
        images=len(evidence),
        significance=significance,
    )


def _valley_significance(profiles, noise, apex: np.ndarray, half_width: float) -> float:
    """How much darker the fitted band is than both its sides, in standard errors: the
    valley scores of the profiles at their row band's apex column (the line shifted by up
    to a half-width where that scores best), at the valley scale
    nearest the band's half-width, each clipped to ``+-OUTLIER_SCALES`` (scene content
    near the band in one profile moves the sum by no more than that), summed and divided
    by the square root of their count (about N(0, 1) where there is no band)."""
    width = profiles.shape[-1]
    scales = _scales(width)
    scale = float(scales[int(np.argmin(np.abs(np.log(scales / max(half_width, 1e-9)))))])
    score = np.clip(_valley_scores(profiles, noise, scale), -OUTLIER_SCALES, OUTLIER_SCALES)
    best = -np.inf
    # the line moved by up to a half-width as a whole: the score is no test of the last
    # pixel of the centre (a shift among a few columns adds about 1 sigma to pure noise)
    reach = int(np.ceil(half_width))
    for shift in range(-reach, reach + 1):
        columns = np.clip(np.round(apex).astype(int) + shift, 0, width - 1)
        picked = score[:, np.arange(len(apex)), columns]
        best = max(best, float(picked.sum() / np.sqrt(picked.size)))
    return best


# ------------------------------------------------------------------ coarse column


def _box_mean(profiles: np.ndarray, size: int) -> np.ndarray:
    from scipy.ndimage import uniform_filter1d

    return uniform_filter1d(profiles, size, axis=-1, mode="nearest")


def _scales(width: int) -> np.ndarray:
    # a valley of scale s spans about 6 s; none wider than the band may be
    largest = MAX_BAND_FRACTION * width / 6.0
    count = max(1, int(np.floor(np.log(largest / SMALLEST_SCALE_PX) / np.log(np.sqrt(2.0)))) + 1)
    return SMALLEST_SCALE_PX * np.sqrt(2.0) ** np.arange(count)


def _valley_scores(profiles: np.ndarray, noise: np.ndarray, scale: float) -> np.ndarray:
    """``(min(left, right) - centre) / its noise`` per column, shape as ``profiles``;
    0 where a side reaches past the image border."""
    half = max(1, int(round(scale / 2.0)))
    centre_n = 2 * half + 1
    side_n = max(2, int(round(2.0 * scale))) + 1
    offset = half + int(round(0.5 * scale)) + side_n // 2 + 1
    centre = _box_mean(profiles, centre_n)
    sides = _box_mean(profiles, side_n)
    width = profiles.shape[-1]
    score = np.zeros_like(profiles)
    if 2 * offset >= width:
        return score
    left = sides[..., : width - 2 * offset]
    right = sides[..., 2 * offset :]
    middle = slice(offset, width - offset)
    depth = np.minimum(left, right) - centre[..., middle]
    sigma = noise[..., middle] * np.sqrt(1.0 / centre_n + 1.0 / side_n)
    score[..., middle] = depth / sigma
    return score


def _coarse_column(profiles: np.ndarray, noise: np.ndarray) -> int | None:
    """The column most scales vote for as a valley (None: no valley anywhere); the middle
    of the run of columns that share the most votes (the maximum filters make runs)."""
    from scipy.ndimage import maximum_filter1d

    width = profiles.shape[-1]
    votes = np.zeros(width)
    for scale in _scales(width):
        # median over images: the band is in every image, moving content is not
        score = np.clip(np.median(_valley_scores(profiles, noise, scale), axis=0), 0.0, None)
        reach = int(np.ceil(scale)) + 2  # a tilted band moves between row bands
        # log: a row band's vote saturates, so that a few rows of scene cannot outvote
        # the band's whole height
        total = np.log1p(maximum_filter1d(score, 2 * reach + 1, axis=-1)).sum(axis=0)
        best = total.max()
        if best > 0:
            votes += maximum_filter1d(total / best, 2 * int(scale / 2.0) + 1)
    top = votes.max()
    if not top > 0:
        return None
    column = int(np.argmax(votes))
    end = column
    while end + 1 < width and votes[end + 1] >= top * (1.0 - 1e-12):
        end += 1
    return (column + end) // 2


# --------------------------------------------------------------------- the band fit


def _hats(distance: np.ndarray, spacing: float) -> np.ndarray:
    """Linear B-splines of ``|x|`` at knots ``0, h, ..., (KNOTS - 1) h``, shape (..., KNOTS)."""
    t = distance[..., None] / spacing - np.arange(KNOTS)
    return np.clip(1.0 - np.abs(t), 0.0, None)


def _extra_variance(basis: np.ndarray, values: np.ndarray, variance: np.ndarray) -> float:
    """The variance ``tau^2`` to add to every value's own for a weighted least-squares fit
    to have a reduced chi-square of 1 (0 if it has one already): the bands' systematic
    scatter about the line, which their own noise-derived variances do not include."""
    dof = len(values) - basis.shape[1]
    if dof <= 0:
        return 0.0

    def reduced_chi2(tau2: float) -> float:
        w = 1.0 / (variance + tau2)
        coefficients = np.linalg.lstsq(basis * np.sqrt(w)[:, None], values * np.sqrt(w),
                                       rcond=None)[0]  # fmt: skip
        return float(np.sum(w * (values - basis @ coefficients) ** 2)) / dof

    if reduced_chi2(0.0) <= 1.0:
        return 0.0
    lo, hi = 0.0, float(np.var(values)) + float(np.max(variance)) + 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if reduced_chi2(mid) > 1.0 else (lo, mid)
    return 0.5 * (lo + hi)


def _monotone_dip(normal: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Knot values ``c`` minimising ``c' N c - 2 c' r`` with ``c_0 >= c_1 >= ... >= 0``
    (a dip that only shrinks away from the apex: a blurred shadow has one minimum).

    ``c = L d`` with ``L`` upper-triangular ones and ``d >= 0``: a non-negative least
    squares problem in ``d``.
    """
    from scipy.optimize import nnls

    lift = np.triu(np.ones((KNOTS, KNOTS)))
    reduced = lift.T @ normal @ lift
    factor = np.linalg.cholesky(reduced)
    d, _ = nnls(factor.T, np.linalg.solve(factor, lift.T @ rhs))
    return np.minimum(lift @ d, 1.0)  # no darker than black


@dataclasses.dataclass
class _Line:
    """The apex image ``u = c0 + c1 t + c2 t^2``, ``t = (v - v0) / scale``, with its
    covariance."""

    coefficients: np.ndarray
    covariance: np.ndarray
    v0: float
    scale: float

    def at(self, v: float) -> tuple[float, float, float]:
        t = (v - self.v0) / self.scale
        basis = np.array([1.0, t, t * t])[: len(self.coefficients)]
        value = float(basis @ self.coefficients)
        slope = 0.0
        if len(self.coefficients) > 1:
            slope = float(self.coefficients[1] + 2 * t * self.coefficients[2:].sum()) / self.scale
        sigma = float(np.sqrt(max(basis @ self.covariance @ basis, 0.0)))
        return value, slope, sigma

    def columns(self, rows: np.ndarray) -> np.ndarray:
        t = (rows - self.v0) / self.scale
        return np.polyval(self.coefficients[::-1], t)


class _BandFit:
    """The band model fitted to every profile near the coarse column (module notes, 3)."""

    def __init__(self, profiles, noise, rows, column: int, extent: float, width: int,
                 two_sided: bool = False):  # fmt: skip
        self.profiles = profiles  # (M, K, W)
        self.two_sided = two_sided  # only profiles lit on both sides (_two_sided)
        # no darker than any row band's mean: the sensor's dark level is below every
        # value it records (the band alone cannot tell a dark level from a deep band)
        self.darkest = float(profiles.min())
        self.dark = self.darkest
        # pixel noise, and the scene's departure from the model in proportion to its
        # light (so that one bright edge near the band cannot outvote every image)
        self.noise = np.hypot(noise, SCENE_MISFIT * np.maximum(profiles - self.dark, 0.0))
        self.rows = rows
        self.width = width
        self.extent = float(np.clip(extent, MIN_EXTENT_PX, self.max_extent))
        self.centres = np.full(len(rows), float(column))  # window centres per row band
        self.apex = self.centres.copy()
        self.information = np.zeros(len(rows))
        self.knots = 0.9 * np.exp(-0.5 * (3.0 * np.arange(KNOTS) / KNOTS) ** 2)

    @property
    def max_extent(self) -> float:
        return 0.5 * MAX_BAND_FRACTION * self.width

    # -- the model
    @property
    def spacing(self) -> float:
        return self.extent / KNOTS

    def transmission(self, x: np.ndarray) -> np.ndarray:
        # the linear B-splines of ``_hats`` are linear interpolation between the knots
        nodes = self.spacing * np.arange(KNOTS + 1)
        return 1.0 - np.interp(np.abs(x), nodes, np.append(self.knots, 0.0), right=0.0)

    def _window(self, k: int, search: float) -> np.ndarray:
        # the dip, half its extent again for the side levels, and the search
        reach = 1.5 * self.extent + search
        lo = max(0, int(np.floor(self.centres[k] - reach)))
        hi = min(self.width, int(np.ceil(self.centres[k] + reach)) + 1)
        return np.arange(lo, hi)

    def _residuals(self, k: int, columns: np.ndarray, apex: np.ndarray, weight: np.ndarray,
                   t: np.ndarray | None = None):  # fmt: skip
        """Residuals in noise units for each candidate apex column, shape (G, M, n), and
        the side levels ``S`` (G, M, n): per profile ``S = a + b x`` on each side of the
        apex by weighted least squares (``weight`` (M, n): inverse variance, 0 to ignore)."""
        p = self.profiles[:, k, columns] - self.dark  # (M, n)
        s = self.noise[:, k, columns]
        x = columns[None, :] - apex[:, None]  # (G, n)
        t = self.transmission(x) if t is None else t
        # the share of each pixel's box left of the apex: the cost is continuous in it
        left = np.clip(0.5 - x, 0.0, 1.0)
        sides = np.stack([left, x * left, 1.0 - left, x * (1.0 - left)], axis=-1)  # (G, n, 4)
        design = sides * t[..., None]
        g, n = x.shape
        outer = (design[..., :, None] * design[..., None, :]).reshape(g, n, 16)
        normal = np.matmul(weight, outer).reshape(g, -1, 4, 4)  # (G, M, 4, 4)
        normal += (1e-9 * np.trace(normal, axis1=-2, axis2=-1)[..., None, None] + 1e-12) * np.eye(4)
        rhs = np.matmul(weight * p, design)  # (G, M, 4)
        coef = np.linalg.solve(normal, rhs[..., None])[..., 0]
        level = np.matmul(coef, np.swapaxes(sides, 1, 2))  # (G, M, n)
        return (p[None] - level * t[:, None, :]) / s[None], level

    def _robust_fit(self, k: int, columns: np.ndarray, apex: np.ndarray):
        """Residuals (G, M, n) in noise units and inverse-variance weights (0 for a sample
        more than ``OUTLIER_SCALES`` off: scene the band model cannot explain) for each
        candidate apex column, by reweighted least squares."""
        s = self.noise[:, k, columns]
        t = self.transmission(columns[None, :] - apex[:, None])
        kept = self._two_sided(k, columns) if self.two_sided else np.ones(len(s))
        weight = np.broadcast_to(kept[:, None] / s**2,
                                 (len(apex), *s.shape))  # fmt: skip
        for _ in range(_REWEIGHTS):
            r, _ = self._residuals(k, columns, apex, weight, t)
            weight = np.where(np.abs(r) < OUTLIER_SCALES, weight, 0.0)
        r, _ = self._residuals(k, columns, apex, weight, t)
        return r, weight

    def _two_sided(self, k: int, columns: np.ndarray) -> np.ndarray:
        """1 for the profiles (M,) whose window has light on both sides of the dip, 0 for
        the others: where the darker side's light (so its whole dip) is within the scene
        misfit allowed on the brighter side (``SCENE_MISFIT``), that side tells nothing and
        a blurred scene edge on the other looks like a flank of the band at any column
        along it (a board's edge on a black background): the fit placed the band there."""
        p = self.profiles[:, k, columns] - self.dark
        x = columns - self.centres[k]
        left, right = x < -self.extent, x > self.extent
        if not (left.any() and right.any()):
            return np.ones(len(p))
        floor = self.noise[:, k, columns].mean(axis=1)
        lo = np.maximum(
            np.minimum(np.median(p[:, left], axis=1), np.median(p[:, right], axis=1)), 0.0
        )
        hi = np.maximum(np.median(p[:, left], axis=1), np.median(p[:, right], axis=1))
        return (SCENE_MISFIT * hi <= lo + floor).astype(float)

    # -- the steps
    def _cost(self, k, columns, grid) -> np.ndarray:
        """Robust cost per candidate: squared residuals, each capped at ``OUTLIER_SCALES^2``."""
        r, _ = self._robust_fit(k, columns, grid)
        return np.minimum(r**2, OUTLIER_SCALES**2).sum(axis=(1, 2))

    def _locate(self, search: float, track: bool = False) -> None:
        """Each row band's apex column: the least cost on a grid of ``+-search`` about its
        window centre. ``track``: from the middle band outwards, each band's centre
        started at the apex of the band inside it (a tilted or bent apex image)."""
        order = np.argsort(np.abs(self.rows - np.mean(self.rows)), kind="stable")
        for n, k in enumerate(order):
            if track and n >= 1:
                inner = order[:n][int(np.argmin(np.abs(self.rows[order[:n]] - self.rows[k])))]
                self.centres[k] = self.apex[k] = self.apex[inner]
            # a coarse grid over the search (moved on while its best node is at an end),
            # then the fine step about its best node
            step = max(_STEP_PX, search / 12.0)
            for _ in range(_SEARCH_MOVES):
                columns = self._window(k, search)
                grid = self.centres[k] + np.arange(-search, search + 1e-9, step)
                j = int(np.argmin(self._cost(k, columns, grid)))
                best = grid[j]
                if 0 < j < len(grid) - 1:
                    break
                self.centres[k] = self.apex[k] = float(np.clip(best, 0, self.width - 1))
            if step > _STEP_PX:
                grid = best + np.arange(-2.0 * step, 2.0 * step + 1e-9, _STEP_PX)
                grid = grid[np.abs(grid - self.centres[k]) <= search + 1e-9]
            cost = self._cost(k, columns, grid)
            j = int(np.argmin(cost))
            if 0 < j < len(grid) - 1:
                curvature = (cost[j - 1] - 2 * cost[j] + cost[j + 1]) / _STEP_PX**2
                shift = 0.5 * (cost[j - 1] - cost[j + 1]) / (curvature * _STEP_PX**2)
                shift = float(np.clip(shift, -1.0, 1.0)) if curvature > 0 else 0.0
                self.apex[k] = grid[j] + shift * _STEP_PX
                self.information[k] = max(curvature, 0.0) / 2.0
            else:  # at the edge of the search: no minimum inside
                self.apex[k] = grid[j]
                self.information[k] = 0.0

    def _update_shape(self, search: float) -> None:
        """``T`` (monotone dip) and the dark level ``b`` by linear least squares at the
        current apex columns and side levels."""
        pieces = []
        for k in range(len(self.rows)):
            columns = self._window(k, search)
            apex = self.apex[k : k + 1]
            _, weight = self._robust_fit(k, columns, apex)
            _, level = self._residuals(k, columns, apex, weight)
            pieces.append((k, columns, columns - self.apex[k], level[0], weight[0]))
        rows_a, rows_y, rows_w = [], [], []
        for k, columns, x, level, weight in pieces:
            p = self.profiles[:, k, columns]
            basis = _hats(np.abs(x), self.spacing)  # (n, KNOTS)
            # p - b - S = -S sum_j c_j phi_j(|x|)
            rows_a.append((-level[..., None] * basis[None]).reshape(-1, KNOTS))
            rows_y.append((p - self.dark - level).reshape(-1))
            rows_w.append(weight.reshape(-1))
        a = np.concatenate(rows_a)
        y = np.concatenate(rows_y)
        w = np.concatenate(rows_w)
        normal = (a.T * w) @ a
        if not np.all(np.isfinite(normal)) or np.trace(normal) <= 0:
            return
        normal += 1e-9 * np.trace(normal) * np.eye(KNOTS)
        self.knots = _monotone_dip(normal, (a.T * w) @ y)
        # dark level: what the band leaves when the sides' light is removed
        num = den = 0.0
        for k, columns, x, level, weight in pieces:
            p = self.profiles[:, k, columns]
            num += float(np.sum(weight * (p - level * self.transmission(x))))
            den += float(np.sum(weight))
        if den > 0:
            self.dark = min(num / den, self.darkest)

    def half_width(self, fraction: float = 0.5) -> float:
        """``|x|`` where the dip falls to ``fraction`` of its depth (linear between knots)."""
        x = np.linspace(0.0, self.extent, 8 * KNOTS + 1)
        dip = 1.0 - self.transmission(x)
        if dip[0] <= 0:
            return float("nan")
        below = np.nonzero(dip < fraction * dip[0])[0]
        if below.size == 0:
            return self.extent
        i = int(below[0])
        a, b = dip[i - 1], dip[i]
        return float(x[i - 1] + (a - fraction * dip[0]) / (a - b) * (x[i] - x[i - 1]))

    def _fit_line(self) -> _Line | None:
        """The apex image through the row bands' columns (module notes, 4)."""
        keep = self.information > 0
        if not keep.any():
            return None
        sigma2 = 1.0 / np.where(keep, self.information, 1.0)
        v0 = float(np.mean(self.rows))
        scale = float(max(np.ptp(self.rows), 1.0) / 2.0)
        t = (self.rows - v0) / scale
        line = None
        for _ in range(len(self.rows)):
            order = min(3, int(keep.sum()))
            basis = np.stack([t**i for i in range(order)], axis=1)[keep]
            apex, s2 = self.apex[keep], sigma2[keep]
            spread = _extra_variance(basis, apex, s2)
            w = np.exp(-0.5 * (t[keep] / MIDDLE_WEIGHT_WIDTH) ** 2) / (s2 + spread)
            covariance = np.linalg.pinv((basis.T * w) @ basis)
            coefficients = covariance @ ((basis.T * w) @ apex)
            line = _Line(coefficients, covariance, v0, scale)
            off = np.abs(apex - basis @ coefficients)
            # the bands' scatter as their median offset says, so that one far band cannot
            # widen the limit that would drop it
            robust = (1.4826 * np.median(off)) ** 2
            limit = np.maximum(LINE_REJECT_SIGMAS * np.sqrt(s2 + min(spread, robust)), 1.0)
            if not (off > limit).any() or keep.sum() <= order:
                break
            # drop the worst band only, then refit
            worst = np.flatnonzero(keep)[int(np.argmax(off / limit))]
            keep[worst] = False
        return line

    def trial(self, rounds: int, search: float) -> float:
        """Locate and fit the shape ``rounds`` times at fixed windows; the ratio
        ``EXTENT_PER_HALF_WIDTH * half-width / X`` of the fitted dip (module notes, 3)."""
        for _ in range(rounds):
            self._locate(search)
            self._update_shape(search)
        half = self.half_width()
        return EXTENT_PER_HALF_WIDTH * half / self.extent if np.isfinite(half) else 0.0

    def run(self) -> _Line | None:
        line = None
        for round_ in range(_FIT_ROUNDS):
            search = max(3.0, 0.5 * self.extent)
            self._locate(search, track=round_ == 0)
            self._update_shape(search)
            half = self.half_width()
            if np.isfinite(half):
                self.extent = float(np.clip(EXTENT_PER_HALF_WIDTH * half, MIN_EXTENT_PX,
                                            self.max_extent))  # fmt: skip
            line = self._fit_line()
            if line is None:
                return None
            self.centres = np.clip(line.columns(self.rows), 0.0, self.width - 1.0)
        self._locate(max(2.0, 0.5 * self.extent))
        return self._fit_line()


def _fit_band(profiles, noise, rows, column: int, width: int,
              two_sided: bool = False) -> tuple[_BandFit, _Line | None]:  # fmt: skip
    """The band fit at the extent where the fitted dip's half-width is consistent with it:
    the largest extent of a geometric scan at which the ratio of
    :meth:`_BandFit.trial` falls through 1 (interpolated), then refined."""
    extents = []
    x = MIN_EXTENT_PX
    while x <= 0.5 * MAX_BAND_FRACTION * width:
        extents.append(x)
        x *= EXTENT_SCAN_STEP
    if not extents:
        extents = [0.5 * MAX_BAND_FRACTION * width]
    ratios = []
    for extent in extents:
        trial = _BandFit(profiles, noise, rows, column, extent, width, two_sided)
        ratios.append(trial.trial(2, max(3.0, 0.5 * extent)))
    chosen = extents[int(np.argmax(ratios))]
    for j in range(len(extents) - 1, 0, -1):
        if ratios[j - 1] >= 1.0 > ratios[j]:
            t = (ratios[j - 1] - 1.0) / (ratios[j - 1] - ratios[j])
            chosen = float(np.exp(np.log(extents[j - 1]) + t * np.log(EXTENT_SCAN_STEP)))
            break
    fit = _BandFit(profiles, noise, rows, column, chosen, width, two_sided)
    return fit, fit.run()
