"""Dense correspondence of a frame: a depth, its sigma and a status for every left pixel.

For every left-half pixel of a region the surface point it sees is found along its own
ray, for any model (only :meth:`CameraModel.rays` and :meth:`CameraModel.project` are
used), so the ``raytrace`` model's curved epipolar lines need no rectification.

Method
------
1. **Plane sweep (coarse).** Depth levels uniform in inverse depth ``w = 1/z`` over the
   depth range, so dense that a level moves the other half's pixel by at most
   ``coarse_step_px``. The exact other-half pixels of a grid of left pixels (every
   ``grid_px``) on every level form a table (:class:`_CurveTable`); the right half is
   warped into the left half's pixels by each level's map and compared with zero-mean
   normalised cross-correlation (ZNCC, about each window's best plane) over a square
   window (box filters). The best level per pixel and a parabola give the coarse depth.
   It sweeps the prefiltered halves of step 3 (it only gives starts).
2. **Refinement along the curve, per window size.** Square windows of several sides
   (``window_range_px``) are warped by a start surface and shifted together along their
   pixels' curves (points from the table, Catmull-Rom in space and depth, the right half
   sampled by its cubic B-spline in a compiled kernel); the ZNCC peak and a parabola give
   each window's offset, added to the start at the window's centre. The 3D point is the
   left ray's point at that depth, which by construction is where the two rays meet.
3. **Window per pixel** (:func:`_choose_window`): the largest size whose depth interval
   meets those of all smaller sizes (intersection of confidence intervals), so windows
   grow where the surface is smooth on their scale and stay small at a pit or an edge.
   Where no window matched, a second ladder of the larger windows on both halves
   prefiltered by a Gaussian (``prefilter_px``) gets its turn: it measures texture too
   faint against the noise for the plain windows (:meth:`DenseSettings.ladders`).
4. **Passes** (:func:`_adaptive_refinement`): the first starts from the sweep, each later
   one from the previous one's depths, fitted by a local quadratic over a few windows
   (:func:`_smooth_base`); the start's shape error inside a window enters the depth, and
   it shrinks with each pass.
5. **Precision.** The match's standard deviation along the curve (px) is the operator
   search's formula (:func:`~endomeasure.measure.correspondence.match_precision`) from
   the warped window's derivative energy along the curve tangent, both halves' noise (as
   a prefilter passes it on: :class:`~endomeasure.interpolation.NoiseTransfer`) and the
   window's misfit; divided by ``|dq/dw|`` it is the sigma of ``w``, carried to ``z``
   by the unscented transform (:func:`~endomeasure.solvers.uncertainty.unscented`,
   vectorised over pixels); the calibration's share is added when given
   (:func:`_calibration_sigma`).
6. **Refusals** (:class:`DenseStatus`), never a guessed depth, when no window size
   matched (the reason of the largest window the other half saw): the other half sees
   none of the windows (``NOT_SEEN``), the predicted precision is worse than
   :data:`~endomeasure.measure.correspondence.MAX_PRECISION_PX` (``UNTEXTURED``), the
   ZNCC is below :data:`~endomeasure.measure.correspondence.MIN_SCORE` (``LOW_SCORE``),
   or the peak sits at an end of the searched stretch (``AT_RANGE_END``). There is no
   left-right check against a sweep from the right half: measured on the scene images,
   the matches it refused were inside their own 2 sigma nearly as often as the ones it
   kept (``docs/surface.md``), so it cost coverage without catching errors the score,
   the precision, the windows' agreement and the sigma do not.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from endomeasure import defaults
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError
from endomeasure.interpolation import (
    NoiseTransfer,
    gaussian_taps,
    noise_transfer,
    spline_coefficients,
)
from endomeasure.measure.correspondence import (
    MAX_PRECISION_PX,
    MIN_SCORE,
    NoiseLevel,
    match_precision,
    noise_corrected_score,
    noise_level,
)
from endomeasure.measure.epipolar import DEPTH_RANGE_MM

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel

__all__ = [
    "DenseSettings",
    "DenseStatus",
    "DenseSurface",
    "dense_surface",
    "Gates",
    "gates_at",
    "check_region",
    "accuracy_classes",
]

_PROBE_LEVELS = 33
"""Levels of the first pass that measures how far the right pixel moves over the range."""


class DenseStatus(enum.IntEnum):
    """Why a pixel has no depth (0: it has one)."""

    OK = 0
    NOT_SEEN = 1
    UNTEXTURED = 2
    LOW_SCORE = 3
    AT_RANGE_END = 4
    INCONSISTENT = 5  # the former left-right check's; no longer given, kept for older records

    @property
    def label(self) -> str:
        return self.name.lower().replace("_", "-")


@dataclasses.dataclass(frozen=True)
class DenseSettings:
    """Settings of :func:`dense_surface`.

    Attributes
    ----------
    window_px : int
        Side of the plane sweep's square ZNCC window (odd), px.
    window_range_px : (int, int)
        Smallest and largest side of the refinement's windows (odd), px: sizes double
        (``2 s + 1``) from the smallest; each pixel keeps the largest size its smaller
        ones agree with (:func:`_choose_window`).
    depth_range_mm : (float, float)
        Nearest and farthest depth searched, mm.
    coarse_step_px : float
        Largest move of the right pixel between two sweep levels, px.
    fine_steps : int
        Sub-levels per coarse level in the refinement.
    fine_reach : float
        The refinement's peak is the highest within this many coarse levels either side
        of its start, if it lies inside that stretch.
    wide_reach : float
        Else the highest within this many levels (``fine_steps`` per level out to here).
        Over most of the frame the start is within a level of the surface, and a peak
        near it is kept; at the fringe of the measured part the start is carried on from
        farther inside and may be off by more than ``fine_reach`` (the coverage this
        adds: ``docs/surface.md``, "Reach").
    passes : int
        Refinement passes: each starts from the previous one's depths (the first from
        the sweep's), smoothed on each window's scale (:func:`_smooth_base`).
    grid_px : int
        Spacing of the reference pixels whose curves are projected exactly (the table
        the sweep and the refinement interpolate).
    smooth_px : int
        Side of the median that removes outliers from a pass's depths before its start
        surface is fitted (odd).
    prefilter_px : float
        Sigma of the Gaussian with which both halves are prefiltered for a second
        ladder, the larger windows again, where no plain window matched (0: none).
        Where the texture's gradient is faint against the noise, the noise of the
        interpolated derivative dominates the match's error; the prefilter cuts it
        about fifty-fold (1 px) and keeps the texture an endoscope's optics pass at low
        contrast. Where the texture is sharp and strong, the plain windows are more
        precise, and a start surface from the prefiltered depths would cost them
        accuracy: so the plain ladder first.
    prefilter_stride : float
        The prefiltered ladder's searched stretch and its sub-level spacing, in
        multiples of the plain ladder's (the same number of samples, so the same cost):
        its correlation peaks are broader (the prefilter widens them), and its starts
        worse (it works where the plain windows found nothing: dim, faint texture).
    max_precision_px : float
        Worst accepted predicted precision along the curve, px (``UNTEXTURED`` beyond):
        the operator search's :data:`~endomeasure.measure.correspondence.MAX_PRECISION_PX`,
        as its :class:`~endomeasure.measure.correspondence.MatchSettings` has it.
    """

    window_px: int = defaults.DENSE_WINDOW_PX
    window_range_px: tuple[int, int] = defaults.DENSE_WINDOW_RANGE_PX
    depth_range_mm: tuple[float, float] = DEPTH_RANGE_MM
    coarse_step_px: float = 1.0
    fine_steps: int = 4
    fine_reach: float = 1.5
    wide_reach: float = 3.0
    passes: int = 3
    grid_px: int = 4
    smooth_px: int = 5
    prefilter_px: float = 1.0
    prefilter_stride: float = 2.0
    max_precision_px: float = MAX_PRECISION_PX

    def __post_init__(self):
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise BadInputError(
                f"the window must be an odd number >= 3 of px, not {self.window_px}"
            )
        small, large = self.window_range_px
        if small < 3 or small % 2 == 0 or large < small:
            raise BadInputError(
                f"window sizes {small}-{large} px: need an odd smallest >= 3 and largest >= it"
            )
        if not self.max_precision_px > 0:
            raise BadInputError(f"precision limit {self.max_precision_px} px is not > 0")
        if not self.prefilter_px >= 0:
            raise BadInputError(f"prefilter sigma {self.prefilter_px} px is not >= 0")
        near, far = self.depth_range_mm
        if not 0 < near < far:
            raise BadInputError(f"depth range {near}-{far} mm is not 0 < near < far")

    def windows(self) -> list[int]:
        """The refinement's window sides, px, ascending."""
        sizes = [self.window_range_px[0]]
        while 2 * sizes[-1] + 1 <= self.window_range_px[1]:
            sizes.append(2 * sizes[-1] + 1)
        return sizes

    def ladders(self) -> list[list[_Rung]]:
        """The refinement's rungs, ladder by ladder in order of preference: every window
        on the plain halves, then (where none of them matched) the two largest on the
        prefiltered ones (the prefilter is for faint texture, of which a small window
        holds too little). Each ladder's window is chosen by :func:`_choose_window`."""
        sizes = self.windows()
        plain = [_Rung(size, 0.0) for size in sizes]
        if self.prefilter_px <= 0:
            return [plain]
        return [plain, [_Rung(size, self.prefilter_px) for size in sizes[-2:]]]


class _Rung(NamedTuple):
    """One window of the refinement: its side (px) and the sigma of the Gaussian that
    prefiltered the halves it matches (px, 0: none)."""

    size: int
    blur: float


class DenseSurface(NamedTuple):
    """The dense result over a region of the left half (arrays (h, w) over the region).

    ``depth`` and ``sigma_depth`` are z and its 1-sigma in the model frame (mm, NaN
    where ``status`` is not OK); ``points`` (h, w, 3) mm; ``sigma_point`` the 1-sigma
    of the point along its ray, mm; ``right`` (h, w, 2) the matched right pixel;
    ``precision_px`` the match's sigma along the curve; ``score`` the ZNCC corrected for
    noise; ``grey`` the left image's values; ``status`` :class:`DenseStatus` codes (uint8);
    ``window`` and ``prefilter`` the rung each depth comes from (:meth:`DenseSettings.ladders`).
    """

    region: tuple[int, int, int, int]  # u0, v0, u1, v1: columns u0 <= u < u1
    depth: np.ndarray
    sigma_depth: np.ndarray
    points: np.ndarray
    sigma_point: np.ndarray
    right: np.ndarray
    precision_px: np.ndarray
    score: np.ndarray
    grey: np.ndarray
    status: np.ndarray
    noise: tuple[NoiseLevel, NoiseLevel]  # per half, grey levels
    levels: int  # coarse sweep levels
    window: np.ndarray  # (h, w) uint16: side of the window each depth comes from, px (0: none)
    prefilter: np.ndarray  # (h, w) float32: sigma of the prefilter of that window's halves, px


def check_region(model: CameraModel, region: tuple[int, int, int, int] | None, window: int):
    """The region (u0, v0, u1, v1) clipped to the left half; refused when empty.

    ``None`` is the whole left half. Columns ``u0 <= u < u1``, rows ``v0 <= v < v1``.
    """
    width, height = model.config.image_size
    split = model.config.split
    if region is None:
        region = (0, 0, split, height)
    u0, v0, u1, v1 = (int(x) for x in region)
    if not (u0 < u1 and v0 < v1):
        raise BadInputError(f"region {u0},{v0},{u1},{v1} is empty (need U0 < U1, V0 < V1)")
    if u0 >= split or u1 <= 0 or v1 <= 0 or v0 >= height:
        raise BadInputError(
            f"region {u0},{v0},{u1},{v1} lies outside the left half (columns 0-{split - 1}, "
            f"rows 0-{height - 1})",
            hint="give the region in left-half full-image pixels",
        )
    clipped = (max(0, u0), max(0, v0), min(split, u1), min(height, v1))
    if clipped[2] - clipped[0] < window or clipped[3] - clipped[1] < window:
        raise BadInputError(
            f"region {u0},{v0},{u1},{v1} leaves less than one {window} px window inside the "
            "left half"
        )
    return clipped


# ----- the plane maps ---------------------------------------------------------------------


def _ray_points(rays, w: np.ndarray) -> np.ndarray:
    """Points of rays (..., 3) at inverse depths ``w`` (broadcast), z = 1/w, (..., 3)."""
    t = (1.0 / w - rays.origins[..., 2]) / rays.directions[..., 2]
    return rays.origins + t[..., None] * rays.directions


def _grid(lo: int, hi: int, step: int) -> np.ndarray:
    """Nodes from ``lo`` to ``hi - 1`` inclusive every ``step`` (the last one added)."""
    nodes = np.arange(lo, hi, step, dtype=np.float64)
    return nodes if nodes[-1] == hi - 1 else np.append(nodes, hi - 1)


class _Frame(NamedTuple):
    """The reference window: a rectangle of the left half (columns ``u0 <= u < u1``)."""

    u0: int
    v0: int
    u1: int
    v1: int

    def crop(self, region: tuple[int, int, int, int]) -> tuple[slice, slice]:
        """The rows and columns of the frame's arrays that hold ``region`` (inside it)."""
        u0, v0, u1, v1 = region
        return slice(v0 - self.v0, v1 - self.v0), slice(u0 - self.u0, u1 - self.u0)


class _CurveTable(NamedTuple):
    """Exact other-half pixels of a grid of reference pixels on the sweep's planes.

    ``field`` (K, gh, gw, 2): the projection of grid node ``(gy, gx)``'s ray point at
    inverse depth ``w0 + k dw``, continued beyond the other half's edges
    (:func:`_continued`); ``seen`` (K, gh, gw): the nodes the other half sees; ``mx``
    (w,), ``my`` (h,): each frame column's and row's fractional grid coordinate. Any
    pixel's curve point at any inverse depth inside the range follows by interpolation
    (:func:`~endomeasure.measure._dense_kernels.curve_samples`): the map is smooth in
    both, and ray aiming every pixel at every candidate depth would cost most of a frame.
    """

    field: np.ndarray
    seen: np.ndarray
    mx: np.ndarray
    my: np.ndarray
    w0: float
    dw: float


def _curve_table(model, frame: _Frame, levels: np.ndarray, grid_px: int) -> _CurveTable:
    """The table of :class:`_CurveTable` for a reference frame and uniform levels."""
    # uniform nodes from one step before the frame to two after it: the cubic stencil
    gu = frame.u0 + grid_px * np.arange(-1, (frame.u1 - 1 - frame.u0) // grid_px + 3)
    gv = frame.v0 + grid_px * np.arange(-1, (frame.v1 - 1 - frame.v0) // grid_px + 3)
    nodes = np.stack(np.meshgrid(gu, gv), axis=-1).astype(np.float64)  # (gh, gw, 2)
    rays = model.rays(nodes, Half.LEFT)
    field = model.project(_ray_points(rays, levels[:, None, None]), Half.RIGHT).pixels
    seen = np.isfinite(field).all(axis=-1)
    mx = (np.arange(frame.u0, frame.u1) - gu[0]) / grid_px
    my = (np.arange(frame.v0, frame.v1) - gv[0]) / grid_px
    return _CurveTable(np.ascontiguousarray(_continued(field)), seen, mx, my,
                       float(levels[0]), float(levels[1] - levels[0]))  # fmt: skip


def _sees_region(table: _CurveTable, frame: _Frame, region) -> bool:
    """Whether the other half sees some pixel of ``region`` at some level of the sweep
    (its nearest grid node, from the model alone): outside the overlap nothing can be
    measured whatever the image holds."""
    rows, cols = frame.crop(region)
    iy = np.rint(table.my[rows]).astype(np.intp)
    ix = np.rint(table.mx[cols]).astype(np.intp)
    return bool(table.seen.any(axis=0)[np.ix_(iy, ix)].any())


def _continued(field: np.ndarray, depth: int = 2) -> np.ndarray:
    """``field`` (K, gh, gw, 2) with up to ``depth`` missing nodes next to the seen ones
    filled by quadratic extrapolation along rows, then columns: the map is smooth, and the
    interpolation's cubic stencil needs whole neighbourhoods at the other half's edges."""
    out = field.copy()
    for axis in (2, 1):
        for _ in range(depth):
            for step in (1, -1):
                f1, f2, f3 = (np.roll(out, -step * j, axis=axis) for j in (1, 2, 3))
                guess = 3.0 * f1 - 3.0 * f2 + f3
                # np.roll wraps around: the last nodes must not borrow from the first
                index = np.arange(out.shape[axis])
                inside = (index + 3 * step < out.shape[axis]) & (index + 3 * step >= 0)
                shape = [1] * out.ndim
                shape[axis] = -1
                fill = np.isnan(out) & np.isfinite(guess) & inside.reshape(shape)
                out[fill] = guess[fill]
    return out


def _plane_maps(table: _CurveTable):
    """Other-half pixel of every reference pixel on each constant-z plane, one (h, w, 2)
    float32 map per plane in turn (a generator: K full-size maps at once would take
    gigabytes on a large sensor), bilinear between the table's nodes (NaN: not seen)."""
    import cv2

    map_x, map_y = np.meshgrid(table.mx.astype(np.float32), table.my.astype(np.float32))
    for plane, seen in zip(table.field.astype(np.float32), table.seen, strict=True):
        plane = np.where(seen[..., None], plane, np.nan)
        yield cv2.remap(plane, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _levels(model, frame: _Frame, settings: DenseSettings) -> np.ndarray:
    """Inverse depths of the sweep, uniform, ``coarse_step_px`` apart at the fastest pixel."""
    near, far = settings.depth_range_mm
    probe = np.linspace(1.0 / far, 1.0 / near, _PROBE_LEVELS)
    grid = max(settings.grid_px * 8, 16)
    gu = _grid(frame.u0, frame.u1, grid)
    gv = _grid(frame.v0, frame.v1, grid)
    rays = model.rays(np.stack(np.meshgrid(gu, gv), -1), Half.LEFT)
    q = model.project(_ray_points(rays, probe[:, None, None]), Half.RIGHT).pixels
    step = np.linalg.norm(np.diff(q, axis=0), axis=-1)  # (K-1, gh, gw)
    rate = np.nanmax(step) if np.isfinite(step).any() else 0.0
    count = int(np.ceil(rate * (_PROBE_LEVELS - 1) / settings.coarse_step_px)) + 1
    return np.linspace(1.0 / far, 1.0 / near, max(count, 3))


# ----- correlation ------------------------------------------------------------------------


def _depth(x: np.ndarray) -> int:
    """OpenCV's output depth for ``x``: float32 stays float32 (the sweep), else float64."""
    import cv2

    return cv2.CV_32F if x.dtype == np.float32 else cv2.CV_64F


def _box(x: np.ndarray, window: int) -> np.ndarray:
    import cv2

    return cv2.boxFilter(
        x, _depth(x), (window, window), normalize=True, borderType=cv2.BORDER_REFLECT
    )


def _ramp_kernels(window: int):
    """Separable kernels of the window averages of ``x * du`` and ``x * dv`` (offsets from
    the window's centre), and the average of ``du^2`` (= that of ``dv^2``)."""
    r = window // 2
    ramp = np.arange(-r, r + 1, dtype=np.float64) / window
    flat = np.full(window, 1.0 / window)
    return ramp, flat, r * (r + 1) / 3.0


def _trend(x: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Window averages of ``x * du`` and ``x * dv``: the window's linear trend times
    ``mean(du^2)`` (du, dv: column and row offset from the window's centre)."""
    import cv2

    ramp, flat, _ = _ramp_kernels(window)
    border = cv2.BORDER_REFLECT
    return (
        cv2.sepFilter2D(x, _depth(x), ramp, flat, borderType=border),
        cv2.sepFilter2D(x, _depth(x), flat, ramp, borderType=border),
    )


class _RefStats(NamedTuple):
    """The reference windows: mean, linear trend (u, v) and variance about mean + trend."""

    mean: np.ndarray
    trend_u: np.ndarray
    trend_v: np.ndarray
    var: np.ndarray
    grey: np.ndarray


def _detrended(x: np.ndarray, window: int):
    """Mean, trends and variance about the window's best plane of ``x``."""
    mean = _box(x, window)
    tu, tv = _trend(x, window)
    ramp2 = _ramp_kernels(window)[2]
    var = _box(x * x, window) - mean * mean - (tu * tu + tv * tv) / ramp2
    return mean, tu, tv, np.maximum(var, 0.0)


def _ref_stats(grey: np.ndarray, window: int) -> _RefStats:
    return _RefStats(*_detrended(grey, window), grey)


def _zncc(ref: _RefStats, warped: np.ndarray, window: int):
    """ZNCC, about each window's best plane, of the reference windows with the warped
    other half (NaN where any sample of the window is missing), the fit gain
    ``cov / var_other``, ``var_other`` and the other window's mean.

    Both windows lose their mean and linear trend before they are compared: the
    illumination of an endoscope (vignetting, the light sources' fall-off, a specular
    lobe) multiplies the texture by a field that differs between the halves' views of
    a point, and a window's share of that difference is a ramp, which plain ZNCC would
    align with the texture's gradient and so shift the match.
    """
    seen = np.isfinite(warped)
    filled = np.where(seen, warped, 0.0)
    complete = _box(seen.astype(np.float64), window) > 1.0 - 1e-9
    m, tu, tv, var = _detrended(filled, window)
    ramp2 = _ramp_kernels(window)[2]
    cov = (
        _box(ref.grey * filled, window)
        - ref.mean * m
        - (ref.trend_u * tu + ref.trend_v * tv) / ramp2
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = cov / np.sqrt(ref.var * var)
        gain = cov / var
    ncc[~complete] = np.nan
    return ncc, gain, var, m


def _parabola(y_minus, y0, y_plus) -> np.ndarray:
    """Vertex offset in (-0.5, 0.5) of the parabola through three equally spaced values."""
    with np.errstate(invalid="ignore", divide="ignore"):  # scores of -inf: no vertex
        den = y_minus - 2.0 * y0 + y_plus
        s = 0.5 * (y_minus - y_plus) / den
    return np.where(np.isfinite(s) & (den < 0), np.clip(s, -0.5, 0.5), 0.0)


class _Coarse(NamedTuple):
    w: np.ndarray  # (h, w) inverse depth, NaN where none
    status: np.ndarray  # (h, w) uint8


def _coarse(model, grey, table: _CurveTable, frame: _Frame, levels: np.ndarray,
            settings: DenseSettings) -> _Coarse:  # fmt: skip
    """Plane sweep of one reference window: best level per pixel, sub-level parabola."""
    import cv2

    split = model.config.split
    other = grey.copy()
    other[:, :split] = np.nan
    other = other.astype(np.float32)
    # in float32: the sweep only ranks levels and gives the refinement its start
    reference = grey[frame.v0 : frame.v1, frame.u0 : frame.u1].astype(np.float32)
    ref = _ref_stats(reference, settings.window_px)
    shape = (frame.v1 - frame.v0, frame.u1 - frame.u0)
    # streamed over the levels (no (K, h, w) volume): the best level so far, its score and
    # its neighbours' scores, as an argmax over the volume would give them
    best = np.zeros(shape, dtype=np.intp)
    best_key = np.full(shape, -np.inf)
    y0, y_minus, y_plus = (np.full(shape, np.nan) for _ in range(3))
    previous = np.full(shape, np.nan)
    seen = np.zeros(shape, dtype=bool)
    last = levels.size - 1
    for k, plane in enumerate(_plane_maps(table)):
        mx = np.nan_to_num(plane[..., 0], nan=-1e6)
        my = np.nan_to_num(plane[..., 1], nan=-1e6)
        warped = cv2.remap(other, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=float("nan"))  # fmt: skip
        score = _zncc(ref, warped, settings.window_px)[0]
        after_best = best == k - 1
        y_plus[after_best] = score[after_best]
        key = np.nan_to_num(score, nan=-2.0)
        better = key > best_key
        best[better], best_key[better], y0[better] = k, key[better], score[better]
        y_minus[better] = (previous if k else score)[better]
        y_plus[better] = score[better] if k == last else np.nan
        previous = score
        seen |= np.isfinite(score)
    # a neighbour level whose window leaves the other half (the overlap's edge) only loses
    # the parabola (the refinement decides); the peak at a level of the range's ends is
    # not a peak
    end = (best == 0) | (best == levels.size - 1)
    both = np.isfinite(y_minus) & np.isfinite(y_plus)
    frac = best + np.where(both, _parabola(y_minus, y0, y_plus), 0.0)
    w = np.interp(frac, np.arange(levels.size), levels)
    status = np.full(best.shape, DenseStatus.OK, dtype=np.uint8)
    status[end] = DenseStatus.AT_RANGE_END
    status[~seen] = DenseStatus.NOT_SEEN
    w[status != DenseStatus.OK] = np.nan
    return _Coarse(w, status)


_FIT_TAPS = 32
"""The start fit runs on every ``side // _FIT_TAPS``-th pixel (at most about that many
taps per window side) and is interpolated back: the depths it fits are window averages,
correlated over at least 15 px, and a fit over 253 px at every pixel would cost more than
the matching."""


def _smooth_base(w: np.ndarray, smooth_px: int, side: int) -> np.ndarray:
    """A smooth start surface from inverse depths ``w`` (NaN: none), (h, w).

    A median of ``smooth_px`` over the known depths removes outliers; then, around every
    node of a grid, a quadratic surface is fitted by least squares to the known depths of
    the ``side`` x ``side`` window (a normalised-convolution Savitzky-Golay fit: holes carry
    no weight, nothing is filled in) and evaluated there; Catmull-Rom interpolation, exact
    for quadratics, fills in between. A window warped by this surface and shifted by its
    offset is right at its centre when the surface has the right shape over the window,
    whatever its level, so the fit keeps the slope and curvature and leaves no structure
    smaller than its side. Where fewer than a tenth of the window's depths are known,
    the nearest fitted value.
    """
    import cv2
    from scipy.ndimage import distance_transform_edt, median_filter

    valid = np.isfinite(w)
    if valid.sum() < 6:
        return np.full(w.shape, np.nan)
    med = median_filter(np.where(valid, w, np.nanmedian(w)), size=smooth_px, mode="nearest")
    step = max(1, side // _FIT_TAPS)
    # nodes every `step` px from one step before the frame to two after its last pixel
    # (the interpolation's stencil)
    ny, nx = ((n - 1) // step + 4 for n in w.shape)
    rows, cols = step * (np.arange(ny) - 1), step * (np.arange(nx) - 1)
    inside = (rows[:, None] >= 0) & (rows[:, None] < w.shape[0])
    inside = inside & (cols[None, :] >= 0) & (cols[None, :] < w.shape[1])
    r_in = np.clip(rows, 0, w.shape[0] - 1)[:, None]
    c_in = np.clip(cols, 0, w.shape[1] - 1)[None, :]
    mask = (inside & valid[r_in, c_in]).astype(np.float64)
    data = np.where(mask > 0, med[r_in, c_in], 0.0)
    reach = (side // 2) // step
    offsets = np.arange(-reach, reach + 1, dtype=np.float64) / max(reach, 1)
    powers = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]  # du^a dv^b

    def window_sum(x, a, b):  # sum over the window of x * du^a * dv^b (du, dv: offsets)
        # correlation: the kernel's offset is the neighbour's, relative to the centre
        return cv2.sepFilter2D(x, cv2.CV_64F, offsets**a, offsets**b,
                               borderType=cv2.BORDER_CONSTANT)  # fmt: skip

    moments = {(a, b): window_sum(mask, a, b) for a in range(5) for b in range(5 - a)}
    normal = np.stack([np.stack([moments[a1 + a2, b1 + b2] for a2, b2 in powers], -1)
                       for a1, b1 in powers], -2)  # fmt: skip
    rhs = np.stack([window_sum(data, a, b) for a, b in powers], -1)
    enough = moments[0, 0] >= 0.1 * (2 * reach + 1) ** 2
    if not enough.any():
        return np.full(w.shape, np.nan)
    coarse = np.full(enough.shape, np.nan)
    coarse[enough] = np.linalg.solve(normal[enough] + 1e-9 * np.eye(6),
                                     rhs[enough][..., None])[:, 0, 0]  # fmt: skip
    # beyond the known depths' reach: the nearest fitted value (a start, not a depth)
    _, (iy, ix) = distance_transform_edt(~enough, return_indices=True)
    coarse = coarse[iy, ix]
    across_rows = _catmull_rom_matrix(w.shape[0], ny, step)
    across_cols = _catmull_rom_matrix(w.shape[1], nx, step)
    return across_rows @ coarse @ across_cols.T


def _catmull_rom_matrix(n: int, nodes: int, step: int) -> np.ndarray:
    """(n, nodes) weights interpolating values at nodes ``step * (k - 1)`` to the pixels
    ``0..n-1`` (Catmull-Rom; the outermost nodes repeat)."""
    from endomeasure.measure._dense_kernels import catmull_rom_weights

    t = (np.arange(n) + step) / step
    base = np.floor(t).astype(np.intp)
    weights = catmull_rom_weights(t - base)[0]
    out = np.zeros((n, nodes))
    for tap in range(4):
        np.add.at(out, (np.arange(n), np.clip(base - 1 + tap, 0, nodes - 1)), weights[tap])
    return out


class _Candidate(NamedTuple):
    """A match per pixel: inverse depth, its sigma, the right pixel, the noise-corrected
    score, the precision along the curve (px), the status, the window's side (px; 0:
    none matched, ``status`` then says why: :func:`_picked`) and the sigma of its
    halves' prefilter (px)."""

    w: np.ndarray
    sigma_w: np.ndarray
    right: np.ndarray
    score: np.ndarray
    precision: np.ndarray
    status: np.ndarray
    window: np.ndarray
    prefilter: np.ndarray


def _refine(table: _CurveTable, bases: dict, refs: dict, images: dict,
            settings: DenseSettings) -> dict:  # fmt: skip
    """Each rung's match around its start surface ``bases[rung.size]``, on the halves of
    ``images[rung.blur]``.

    The other half is sampled along every pixel's curve at sub-levels within
    ``wide_reach`` coarse levels of the start; the ZNCC peak (within ``fine_reach`` if it
    lies inside that stretch, else within ``wide_reach``) and a parabola give the
    offset, which is added to the start at the pixel (the window was warped by the
    start, so its offset corrects the start where the window is centred). The match at
    that depth is then evaluated (:func:`_match_at`) for its score, precision and sigma.
    """
    n_near = int(np.ceil(settings.fine_reach * settings.fine_steps))
    n_fine = max(n_near, int(np.ceil(settings.wide_reach * settings.fine_steps)))
    offsets = np.arange(-n_fine, n_fine + 1) / settings.fine_steps * table.dw
    out = {}
    for rung, ref in refs.items():
        size, base, image = rung.size, bases[rung.size], images[rung.blur]
        stretch = offsets * (settings.prefilter_stride if rung.blur > 0 else 1.0)
        fine = np.stack([_zncc(ref, image.right.values_along(table, base + dj), size)[0]
                         for dj in stretch])  # fmt: skip
        key = np.nan_to_num(fine, nan=-2.0)
        near = n_fine - n_near + np.argmax(key[n_fine - n_near : n_fine + n_near + 1], axis=0)
        inside = (near > n_fine - n_near) & (near < n_fine + n_near)
        best = np.where(inside, near, np.argmax(key, axis=0))
        rows, cols = np.indices(best.shape)
        y0 = fine[best, rows, cols]
        y_minus = fine[np.maximum(best - 1, 0), rows, cols]
        y_plus = fine[np.minimum(best + 1, offsets.size - 1), rows, cols]
        w = base + np.interp(best + _parabola(y_minus, y0, y_plus), np.arange(offsets.size),
                             stretch)  # fmt: skip
        # a window the right half does not see whole at the peak or beside it has no
        # peak to place: not seen (the overlap's edge); a peak at an end of the searched
        # stretch may lie beyond it
        unseen = ~(np.isfinite(y0) & np.isfinite(y_minus) & np.isfinite(y_plus))
        end = (best == 0) | (best == offsets.size - 1)
        # the match is judged on the windows warped by every pixel's own depth: a pixel
        # without a peak inside the stretch keeps its start there (the smooth surface
        # its neighbours' depths gave), not a sample at the stretch's end, which would
        # bend its neighbours' windows
        w = np.where(unseen | end, base, w)
        q_r, score, precision, sigma_w = _match_at(table, w, ref, image, size)
        status = np.full(w.shape, DenseStatus.OK, dtype=np.uint8)
        status[unseen | ~np.isfinite(score)] = DenseStatus.NOT_SEEN
        status[(status == DenseStatus.OK) & end] = DenseStatus.AT_RANGE_END
        imprecise = ~(precision <= settings.max_precision_px)
        status[(status == DenseStatus.OK) & imprecise] = DenseStatus.UNTEXTURED
        status[(status == DenseStatus.OK) & ~(score >= MIN_SCORE)] = DenseStatus.LOW_SCORE
        out[rung] = _Candidate(w, sigma_w, q_r, score, precision, status,
                               np.full(w.shape, size, dtype=np.uint16),
                               np.full(w.shape, rung.blur, dtype=np.float32))  # fmt: skip
    return out


_ICI_GAMMA = 2.0
"""Half-width of the confidence intervals of the window choice, in sigmas: a window
whose interval misses all the smaller windows' common interval sees more than the
smooth surface they agree on (5 % of the time by noise alone)."""


def _choose_window(candidates: dict) -> np.ndarray:
    """Per pixel, the last rung (the largest window) whose match agrees with every
    earlier one's.

    The intersection of confidence intervals rule (Goldenshluger and Nemirovski; Katkovnik's
    adaptive windows): windows grow while the intervals ``w +- gamma sigma`` of all
    matched rungs so far have a common point. A large window is precise where the
    surface is smooth on its scale; where it is not (a pit, an edge) its depth leaves the
    smaller windows' interval and growth stops. Rungs whose match is refused are skipped.
    ``candidates`` is keyed in the rungs' order, one ladder
    (:meth:`DenseSettings.ladders`). Returns the index into that order (-1: no rung
    matched).
    """
    rungs = list(candidates)
    shape = candidates[rungs[0]].w.shape
    lo, hi = np.full(shape, -np.inf), np.full(shape, np.inf)
    chosen = np.full(shape, -1, dtype=np.intp)
    growing = np.ones(shape, dtype=bool)
    for index, rung in enumerate(rungs):
        c = candidates[rung]
        usable = growing & (c.status == DenseStatus.OK)
        with np.errstate(invalid="ignore"):
            new_lo = np.maximum(lo, c.w - _ICI_GAMMA * c.sigma_w)
            new_hi = np.minimum(hi, c.w + _ICI_GAMMA * c.sigma_w)
            agree = usable & (new_lo <= new_hi)
        growing &= ~(usable & ~agree)
        lo, hi = np.where(agree, new_lo, lo), np.where(agree, new_hi, hi)
        chosen[agree] = index
    return chosen


def _chosen_rung(candidates: dict, ladders: list) -> np.ndarray:
    """Per pixel, the index into ``candidates`` (keyed by rung, ladder after ladder) of
    the first ladder's choice that matched (-1: none)."""
    chosen = np.full(candidates[ladders[0][0]].w.shape, -1, dtype=np.intp)
    first = 0
    for ladder in ladders:
        mine = _choose_window({rung: candidates[rung] for rung in ladder})
        chosen = np.where((chosen < 0) & (mine >= 0), first + mine, chosen)
        first += len(ladder)
    return chosen


# ----- the whole search -------------------------------------------------------------------


def dense_surface(
    model: CameraModel,
    image: np.ndarray,
    region: tuple[int, int, int, int] | None = None,
    settings: DenseSettings | None = None,
    param_cov: np.ndarray | None = None,
    misfit_cov: np.ndarray | None = None,
) -> DenseSurface:
    """Depth, sigma and status of every left pixel of a region (see the module notes).

    Parameters
    ----------
    model : CameraModel
    image : ndarray, shape (H, W), grey levels
        The whole split frame.
    region : (u0, v0, u1, v1), optional
        Left-half pixel rectangle (columns ``u0 <= u < u1``); default the whole half.
    settings : DenseSettings, optional
    param_cov : ndarray, shape (F, F), optional
        Covariance of the model's free parameters (``free_mask`` order).
    misfit_cov : ndarray, shape (4, 4), optional
        The model misfit's covariance of one point's ``u_L, v_L, u_R, v_R``, px^2
        (:meth:`~endomeasure.solvers.misfit.ModelMisfit.covariance`). Their share of each
        depth's sigma is added (:func:`_calibration_sigma`); without both, the sigma is
        the match's alone.

    Returns
    -------
    DenseSurface

    Raises
    ------
    BadInputError
        An image that does not fit the model or a region outside the left half.
    """
    from endomeasure.solvers.uncertainty import unscented

    settings = settings or DenseSettings()
    grey, (u0, v0, u1, v1), search = _prepare(model, image, region, settings)
    # the sweep only gives the refinement its start: on the prefiltered halves, where
    # faint texture still finds its level
    coarse = _coarse(model, search.swept, search.table, search.frame, search.levels, settings)
    match = _adaptive_refinement(search.table, coarse.w, search.refs, search.images,
                                 search.levels, settings)  # fmt: skip
    w, sigma_w, q_r, status = match.w, match.sigma_w, match.right, match.status
    region_px = np.stack(np.meshgrid(np.arange(u0, u1, dtype=np.float64),
                                     np.arange(v0, v1, dtype=np.float64)), -1)  # fmt: skip
    rays = model.rays(region_px, Half.LEFT)

    # ----- crop to the region, sigma of z by the unscented transform of w
    inner = search.frame.crop((u0, v0, u1, v1))
    status = status[inner]
    ok = status == DenseStatus.OK
    w_in, s_in = w[inner], sigma_w[inner]
    depth = np.full(status.shape, np.nan)
    sigma_depth = np.full(status.shape, np.nan)
    if ok.any():
        prop = unscented(
            lambda x: 1.0 / x[..., 0], w_in[ok][:, None], (s_in[ok] ** 2)[:, None, None]
        )
        depth[ok] = 1.0 / w_in[ok]
        sigma_depth[ok] = prop.std
        if param_cov is not None or misfit_cov is not None:
            cal = _calibration_sigma(model, param_cov, misfit_cov, region_px[ok], q_r[inner][ok])
            sigma_depth[ok] = np.hypot(sigma_depth[ok], cal)
    o, d = rays.origins, rays.directions
    with np.errstate(invalid="ignore"):
        t = (depth - o[..., 2]) / d[..., 2]
        points = o + t[..., None] * d
        sigma_point = sigma_depth / np.abs(d[..., 2])
    nan_where = ~ok
    right_px = np.where(nan_where[..., None], np.nan, q_r[inner])
    return DenseSurface(
        region=(u0, v0, u1, v1),
        depth=depth,
        sigma_depth=sigma_depth,
        points=points,
        sigma_point=np.where(ok, sigma_point, np.nan),
        right=right_px,
        precision_px=np.where(
            np.isfinite(match.precision[inner]), match.precision[inner], np.nan
        ),  # fmt: skip
        score=match.score[inner],
        grey=grey[v0:v1, u0:u1],
        status=status,
        noise=search.noise,
        levels=int(search.levels.size),
        window=np.where(ok, match.window[inner], 0).astype(np.uint16),
        prefilter=np.where(ok, match.prefilter[inner], 0.0).astype(np.float32),
    )


class _Search(NamedTuple):
    """What every match of one frame shares: the reference frame (the region and the
    largest window's margin), the sweep's levels, the curve table, the halves as each
    prefilter leaves them, each rung's reference windows and the noise per half."""

    frame: _Frame
    levels: np.ndarray
    table: _CurveTable
    swept: np.ndarray  # the whole frame as the sweep sees it (prefiltered)
    images: dict  # blur -> _Image
    refs: dict  # _Rung -> _RefStats
    noise: tuple[NoiseLevel, NoiseLevel]


def _prepare(model, image, region, settings: DenseSettings):
    """The frame's grey levels (float), the region checked and clipped, and the
    :class:`_Search` of the frame."""
    image = np.asarray(image)
    width, height = model.config.image_size
    if image.ndim != 2 or image.shape != (height, width):
        raise BadInputError(
            f"image of shape {image.shape} is not the model's {width}x{height} grey frame"
        )
    grey = image.astype(np.float64)
    split = model.config.split
    r = settings.windows()[-1] // 2
    u0, v0, u1, v1 = check_region(model, region, settings.window_px)
    noise = (noise_level(grey[:, :split]), noise_level(grey[:, split:]))
    frame = _Frame(max(0, u0 - r), max(0, v0 - r), min(split, u1 + r), min(height, v1 + r))
    levels = _levels(model, frame, settings)
    table = _curve_table(model, frame, levels, settings.grid_px)
    if not _sees_region(table, frame, (u0, v0, u1, v1)):
        near, far = settings.depth_range_mm
        raise BadInputError(
            f"region {u0},{v0},{u1},{v1} lies outside the overlap: the right half sees "
            f"none of it at {near:.1f}-{far:.1f} mm",
            hint="choose a region of the left half that the right half sees too",
        )
    rungs = [rung for ladder in settings.ladders() for rung in ladder]
    blurs = {rung.blur for rung in rungs}
    filtered = {blur: _prefiltered(grey, split, blur) for blur in blurs | {settings.prefilter_px}}
    images = {blur: _image(filtered[blur], split, blur, noise, frame) for blur in blurs}
    refs = {rung: _ref_stats(images[rung.blur].grey, rung.size) for rung in rungs}
    search = _Search(frame, levels, table, filtered[settings.prefilter_px], images, refs, noise)
    return grey, (u0, v0, u1, v1), search


class Gates(NamedTuple):
    """What the refinement's gates say of the matches at a given surface, per pixel of
    the region (h, w): ``passed`` where some rung's match passes the precision and the
    score gates, ``precision_px`` the best precision of those matches (NaN: no window
    seen whole) and ``sigma_w`` its sigma of the inverse depth (1/mm)."""

    passed: np.ndarray
    precision_px: np.ndarray
    sigma_w: np.ndarray


def gates_at(
    model: CameraModel,
    image: np.ndarray,
    inverse_depth: np.ndarray,
    region: tuple[int, int, int, int] | None = None,
    settings: DenseSettings | None = None,
) -> Gates:
    """The gates on every rung's match at a given surface instead of a searched one.

    ``inverse_depth`` (H, split): ``1 / z`` in the model frame for every left-half pixel
    (NaN where the surface is unknown: windows reaching there are not seen whole). Given
    the model's depth of the true matches, ``passed`` is where an exact search would find
    a depth with these windows and gates: the coverage the texture allows against the
    noise, a bound no start or search can beat (``bench/accuracy_dense.py``).
    """
    settings = settings or DenseSettings()
    _, region, search = _prepare(model, image, region, settings)
    f = search.frame
    w = np.asarray(inverse_depth, dtype=np.float64)[f.v0 : f.v1, f.u0 : f.u1]
    passed = np.zeros(w.shape, dtype=bool)
    best, best_sigma = np.full(w.shape, np.inf), np.full(w.shape, np.nan)
    for rung, ref in search.refs.items():
        _, score, precision, sigma_w = _match_at(search.table, w, ref,
                                                 search.images[rung.blur], rung.size)  # fmt: skip
        with np.errstate(invalid="ignore"):
            passed |= (precision <= settings.max_precision_px) & (score >= MIN_SCORE)
            better = np.isfinite(score) & (precision < best)
        best, best_sigma = np.where(better, precision, best), np.where(better, sigma_w, best_sigma)
    inner = f.crop(region)
    return Gates(passed[inner], np.where(np.isfinite(best), best, np.nan)[inner],
                 best_sigma[inner])  # fmt: skip


_START_SPAN = 4
"""A window's start surface is fitted over this many window sides (:func:`_smooth_base`):
its shape error inside the window adds to the match's error, and a fit over about
``_START_SPAN ** 2`` windows' depths averages their scatter down. Chosen with
:attr:`DenseSettings.passes` in development on the default preset; the random designs
check both: the "matching alone" columns of ``bench/accuracy_dense.py --designs``."""


def _picked(candidates: dict, chosen: np.ndarray) -> _Candidate:
    """Each pixel's fields from its chosen rung (``chosen``: index into the rungs).

    The chosen window agrees with the smaller ones only within their intervals, so its
    smoothing of what it cannot follow (a pit narrower than the window) may reach their
    sigma, far beyond its own. Its departure from each smaller matched window beyond
    that window's noise, ``(w_k - w_j)^2 - sigma_j^2`` (negative on average where the
    surface is smooth: the nested windows share their noise), estimates that bias; the
    largest is added to the sigma in quadrature.
    """
    rungs = list(candidates)
    pick = np.maximum(chosen, 0)

    def gather(field):
        stack = np.stack([getattr(candidates[rung], field) for rung in rungs])
        index = pick[None, ..., None] if stack.ndim == pick.ndim + 2 else pick[None]
        return np.take_along_axis(stack, index, axis=0)[0]

    w, sigma_w = gather("w"), gather("sigma_w")
    bias2 = np.zeros(w.shape)
    for index, rung in enumerate(rungs[:-1]):
        c = candidates[rung]
        smaller = (index < chosen) & (c.status == DenseStatus.OK)
        with np.errstate(invalid="ignore"):
            excess = (w - c.w) ** 2 - c.sigma_w**2
        bias2 = np.where(smaller & (excess > bias2), excess, bias2)
    matched = chosen >= 0
    # no rung matched: the reason of the last rung whose window the other half saw (the
    # later, larger windows have the most evidence; a window that outgrows the overlap
    # says nothing about the pixel); not seen only when no window was
    reason = np.full(chosen.shape, DenseStatus.NOT_SEEN, dtype=np.uint8)
    for rung in rungs:
        said = candidates[rung].status
        reason = np.where((said != DenseStatus.NOT_SEEN) & (said != DenseStatus.OK), said, reason)
    status = np.where(matched, DenseStatus.OK, reason).astype(np.uint8)
    window = np.where(matched, gather("window"), 0)
    prefilter = np.where(matched, gather("prefilter"), 0.0)
    return _Candidate(w, np.sqrt(sigma_w**2 + bias2), gather("right"), gather("score"),
                      gather("precision"), status, window, prefilter)  # fmt: skip


def _adaptive_refinement(table, coarse_w, refs: dict, images: dict, levels,
                         settings: DenseSettings) -> _Candidate:  # fmt: skip
    """``settings.passes`` refinement passes, every rung each, the rung by ICI.

    The first pass starts from the sweep's depths, each later one from the previous
    pass's chosen depths; every size's start is that surface smoothed over
    :data:`_START_SPAN` of its windows. The start's shape error inside a window enters
    the depth at the window's centre whole; it shrinks with every pass as the depths
    it is fitted to improve (how much: ``docs/surface.md``).
    """
    sizes = sorted({rung.size for rung in refs})
    start = coarse_w
    for _ in range(settings.passes):
        bases = {size: _smooth_base(start, settings.smooth_px, _START_SPAN * size + 1)
                 for size in sizes}  # fmt: skip
        if not np.isfinite(bases[sizes[0]]).any():  # no depth anywhere: the range's middle
            bases = dict.fromkeys(sizes, np.full(coarse_w.shape, levels.mean()))
        candidates = _refine(table, bases, refs, images, settings)
        chosen = _chosen_rung(candidates, settings.ladders())
        match = _picked(candidates, chosen)
        start = np.where(chosen >= 0, match.w, np.nan)
    return match


class _Along(NamedTuple):
    """The other half along curves: the curve point q (h, w, 2), dq/dw (h, w, 2), the
    spline's value (h, w) and gradient (h, w, 2) there (NaN: not seen)."""

    q: np.ndarray
    dq_dw: np.ndarray
    values: np.ndarray
    gradient: np.ndarray


class _RightHalf(NamedTuple):
    """The right half's spline interpolant."""

    coeffs: np.ndarray
    origin: np.ndarray
    split: int
    width: int
    height: int

    def along(self, table: _CurveTable, w: np.ndarray) -> _Along:
        """The right half at each pixel's curve point of inverse depth ``w`` (h, w)."""
        from endomeasure.measure._dense_kernels import curve_samples

        return _Along(*curve_samples(*self._kernel_args(table, w)))

    def values_along(self, table: _CurveTable, w: np.ndarray) -> np.ndarray:
        """:meth:`along`'s values alone (h, w)."""
        from endomeasure.measure._dense_kernels import curve_values

        return curve_values(*self._kernel_args(table, w))

    def _kernel_args(self, table: _CurveTable, w: np.ndarray) -> tuple:
        return (table.field, table.seen, table.mx, table.my, table.w0, table.dw,
                np.ascontiguousarray(w, dtype=np.float64), self.coeffs, float(self.origin[0]),
                float(self.origin[1]), float(self.split), float(self.width - 1),
                float(self.height - 1))  # fmt: skip


class _Image(NamedTuple):
    """The split frame as one prefilter leaves it: the reference frame's grey levels, the
    right half's spline, the raw image's noise per half, and how the prefilter and the
    spline pass that noise on to a sample and its derivative."""

    grey: np.ndarray
    right: _RightHalf
    noise: tuple[NoiseLevel, NoiseLevel]
    transfer: NoiseTransfer


def _prefiltered(grey: np.ndarray, split: int, blur: float) -> np.ndarray:
    """The whole frame ``grey`` convolved with a Gaussian of ``blur`` px (0: itself), each
    half on its own (no light crosses the apex band)."""
    import cv2

    if blur <= 0:
        return grey
    kernel = np.asarray(gaussian_taps(blur))
    return np.concatenate([
        cv2.sepFilter2D(np.ascontiguousarray(grey[:, cols]), cv2.CV_64F, kernel, kernel,
                        borderType=cv2.BORDER_REFLECT)
        for cols in (slice(0, split), slice(split, grey.shape[1]))
    ], axis=1)  # fmt: skip


def _image(grey: np.ndarray, split: int, blur: float, noise, frame: _Frame) -> _Image:
    """The :class:`_Image` of the whole frame ``grey``, already prefiltered by a Gaussian
    of ``blur`` px (:func:`_prefiltered`)."""
    height, width = grey.shape
    coeffs, origin = spline_coefficients(
        grey, np.array([[split, 0], [width - 1, height - 1]], float), cols=(split, width - 1)
    )
    return _Image(grey[frame.v0 : frame.v1, frame.u0 : frame.u1],
                  _RightHalf(coeffs, origin, split, width, height), noise,
                  noise_transfer(gaussian_taps(blur)))  # fmt: skip


def _match_at(table: _CurveTable, w, ref, image: _Image, window: int):
    """The match at inverse depth ``w`` with square windows of side ``window`` on the
    halves of ``image``: the right pixel, the noise-corrected ZNCC, the precision along
    the curve (px) and the sigma of ``w``."""
    along = image.right.along(table, w)
    rate = np.linalg.norm(along.dq_dw, axis=-1)  # px per unit inverse depth
    with np.errstate(invalid="ignore", divide="ignore"):
        tangent = along.dq_dw / rate[..., None]
    ncc, gain, var_r, mean_r = _zncc(ref, along.values, window)
    # each window's noise at its own signal level (the sensor's noise grows with it), as
    # the raw image has it; per sample, as the prefilter and the spline pass it on
    noise_l = image.noise[0].sigma(ref.mean)
    noise_r = image.noise[1].sigma(mean_r)
    transfer = image.transfer
    on_grid = float(transfer.gain(0.0)) ** 2
    n = window**2
    frac = np.nan_to_num(along.q - np.floor(along.q))
    interpolated = _box(transfer.gain(frac[..., 0]) * transfer.gain(frac[..., 1]), window)
    # the noise-corrected score as the operator search's (so that MIN_SCORE means the
    # same); the windows' variances per degree of freedom (n - 3 about their plane)
    dof = n / (n - 3)
    score = noise_corrected_score(ncc, (ref.var * dof, noise_l**2 * on_grid),
                                  (var_r * dof, noise_r**2 * interpolated))  # fmt: skip
    g = np.nan_to_num(np.einsum("...i,...i->...", along.gradient, tangent))
    # the derivative's energy left once the windows lose their mean and trend (the part
    # of the signal the correlation uses); the derivative of the interpolated noisy image
    # carries noise energy of its own over the n - 3 remaining degrees of freedom
    energy = n * _detrended(g, window)[3]
    energy -= (n - 3) * transfer.derivative * noise_r**2
    with np.errstate(invalid="ignore", divide="ignore"):
        # the fit ref ~ gain * other + plane; its residual beyond the noise (over its
        # n - 4 degrees of freedom) is the misfit
        residual = ref.var * (1.0 - np.clip(ncc, -1, 1) ** 2) / gain**2
        expected = (noise_l**2 / gain**2 + noise_r**2) * on_grid * (n - 4) / n
        misfit = np.sqrt(np.maximum(residual - expected, 0.0))
        # the first-order term: the raw noise's, times the share a prefilter's correlated
        # noise (covariance k * k) keeps of it for this derivative
        share = transfer.correlated_share(g, window)
        precision = match_precision(energy, n, 1.0 / np.abs(gain), noise_l * np.sqrt(share),
                                    noise_r, misfit, share,
                                    derivative_noise=transfer.derivative)  # fmt: skip
        sigma_w = precision / rate
    return along.q, score, precision, sigma_w


_CALIBRATION_NODES = 400
"""Matches at which the calibration's share of the depth sigma is computed exactly; it
varies smoothly over the image, and is interpolated in between."""


def _calibration_sigma(model, param_cov, misfit_cov, left, right) -> np.ndarray:
    """The calibration's share of each match's depth sigma, mm.

    The unscented transform, through triangulating the match's pixel pair, of the free
    parameters' covariance (the rays move with the parameters; the match is image data)
    and of the model misfit's pixel offsets ``u_L, v_L, u_R, v_R`` of one point (4 x 4,
    px^2; what the residuals hold beyond noise, which a point's depth carries like a
    matching error). Computed at :data:`_CALIBRATION_NODES` matches spread over the list
    and interpolated linearly (nearest outside their hull): both vary smoothly."""
    from scipy.interpolate import griddata
    from scipy.linalg import block_diag
    from scipy.spatial import QhullError

    from endomeasure.solvers.triangulate import triangulate
    from endomeasure.solvers.uncertainty import unscented

    free = np.flatnonzero(model.free_mask)
    param_cov = np.zeros((0, 0)) if param_cov is None else np.asarray(param_cov, float)
    misfit_cov = np.zeros((4, 4)) if misfit_cov is None else np.asarray(misfit_cov, float)
    n_par = param_cov.shape[0]
    step = max(1, left.shape[0] // _CALIBRATION_NODES)
    nodes_l, nodes_r = left[::step], right[::step]

    def depth_of(x):  # (M, K, F + 4) -> (M, K)
        lead = x.shape[:2]
        params = None
        if n_par:
            params = np.broadcast_to(model.params, (*lead, model.params.size)).copy()
            params[..., free] = x[..., :n_par]
        tri = triangulate(model, x[..., n_par : n_par + 2], x[..., n_par + 2 :], params=params)
        return np.where(tri.status == 0, tri.points[..., 2], np.nan)

    # the pixels are inputs, not captured: the transform's retries pass a subset of rows
    mean = np.broadcast_to(model.params[free] if n_par else np.zeros(0), (len(nodes_l), n_par))
    x0 = np.concatenate([mean, nodes_l, nodes_r], axis=1)
    sigma = unscented(depth_of, x0, block_diag(param_cov, misfit_cov)).std
    good = np.isfinite(sigma)
    if not good.any():
        return np.zeros(left.shape[0])
    near = griddata(nodes_l[good], sigma[good], left, method="nearest")
    try:  # nodes on one line (a thin region) have no hull: the nearest node's then
        out = griddata(nodes_l[good], sigma[good], left, method="linear")
    except (QhullError, ValueError):
        return near
    return np.where(np.isfinite(out), out, near)


def accuracy_classes(surface: DenseSurface, bands_percent: tuple[float, float]) -> np.ndarray:
    """Per pixel 0 green, 1 yellow, 2 red: the 2-sigma depth error within the first band
    (percent of z), within the second, or beyond it / no depth."""
    with np.errstate(invalid="ignore"):
        rel = 200.0 * surface.sigma_depth / surface.depth
    out = np.full(surface.status.shape, 2, dtype=np.uint8)
    ok = surface.status == DenseStatus.OK
    out[ok & (rel <= bands_percent[1])] = 1
    out[ok & (rel <= bands_percent[0])] = 0
    return out
