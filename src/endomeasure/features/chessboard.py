"""Chessboard corners in one half: OpenCV detection, canonical ids, sub-pixel refinement.

The detector and refinement were chosen by measured accuracy against exactly known
corners (``bench/bench_detect.py accuracy``; figures in ``docs/accuracy.md``). All
candidates stay selectable by name so that the comparison can be re-run:

``sb``
    ``cv2.findChessboardCornersSB`` with no flags (sector-based detector, its own
    sub-pixel fit).
``sb-accuracy``
    ``findChessboardCornersSB`` with ``CALIB_CB_ACCURACY`` (up-sampled image, slower).
``sb-accuracy-exhaustive``
    Adds ``CALIB_CB_EXHAUSTIVE | CALIB_CB_NORMALIZE_IMAGE``.
``classic-subpixN``
    ``cv2.findChessboardCorners`` (adaptive threshold, normalised image) followed by
    ``cv2.cornerSubPix`` with an N x N half-window (``N`` px each side).
``classic-subpix``
    The same with a half-window adapted to the square size seen in the image.
``sb-subpix``
    ``findChessboardCornersSB`` for finding, then ``cornerSubPix`` with the adapted
    half-window for refining.
``sb-classic-subpix``
    As ``sb-subpix``, falling back to ``findChessboardCorners`` when the sector-based
    finder finds nothing; refinement as ``sb-subpix``. The sector-based finder is the
    more robust, ``cornerSubPix`` with a window matched to the square size several times
    more accurate than its own sub-pixel fit (with or without ``CALIB_CB_ACCURACY``),
    but biased by blur, 8-bit edges and perspective.
``sb-saddle``
    SB finds, a quadratic surface fitted around each corner refines (its saddle point;
    :func:`endomeasure.features.subpixel.saddle_corners`). Kept for the comparison.
``sb-symmetry``
    SB finds, ``cornerSubPix`` starts, the centre of point symmetry refines
    (:func:`endomeasure.features.subpixel.symmetric_corners`, with a per-corner
    illumination gradient).
``sb-classic-symmetry`` (the default)
    As ``sb-symmetry`` with the ``findChessboardCorners`` fallback finder: the most
    accurate on the simulator's renders (``docs/accuracy.md``, "Refinement on the
    simulator's renders").

Canonical ids (so that the same id in both halves is the same physical corner and
detections match the simulator's truth): OpenCV may return the grid starting at any end
(180-degree ambiguity, and for square grids also transposed). The grid is re-ordered so
that columns increase along +u and rows along +v as seen in the image, which makes id 0
the inner corner nearest the top-left. This is unique for boards rotated in-plane by
less than 45 degrees (always the case in our data); at rotations near 90 degrees the
choice would depend on noise, so such a half is refused with a reason.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from endomeasure.features.boards import ChessboardSpec

__all__ = [
    "CHESSBOARD_METHODS",
    "DEFAULT_CHESSBOARD_METHOD",
    "ChessboardResult",
    "adaptive_subpix_halfwindow",
    "canonical_grid",
    "detect_chessboard",
    "refine_corners",
    "refine_symmetric",
    "refine_symmetric_precise",
    "saddle_scores",
    "trim_false_lines",
]

CHESSBOARD_METHODS = (
    "sb",
    "sb-accuracy",
    "sb-accuracy-exhaustive",
    "classic-subpix",
    "classic-subpix3",
    "classic-subpix5",
    "classic-subpix7",
    "classic-subpix11",
    "sb-subpix",
    "sb-classic-subpix",
    "sb-saddle",
    "sb-symmetry",
    "sb-classic-symmetry",
)
DEFAULT_CHESSBOARD_METHOD = "sb-classic-symmetry"

# The in-plane angle (of the board's column direction against +u) beyond which the
# canonical order is refused: at 90 degrees two orders are equally good.
MAX_CANONICAL_ANGLE_DEG = 70.0
# cornerSubPix: stop after this many iterations or when a corner moves less than this.
SUBPIX_MAX_ITERATIONS = 100
SUBPIX_EPSILON_PX = 1e-4
# The adapted half-window is this fraction of the shortest corner spacing, so the window
# never reaches the grid lines that do not pass through the corner.
SUBPIX_WINDOW_FRACTION = 0.5
SUBPIX_MIN_HALFWINDOW, SUBPIX_MAX_HALFWINDOW = 2, 15
NOT_FOUND = "no chessboard found"
# Grid lines whose median X-junction score is lower are not corners (a real X scores
# about 1, a square's edge against the white margin 0.5).
MIN_SADDLE_SCORE = 0.75


@dataclasses.dataclass(frozen=True)
class ChessboardResult:
    """Corners of one chessboard in one image (crop) in canonical order.

    Attributes
    ----------
    pixels : ndarray, shape (rows * cols, 2), px
        Corner ``id`` in row ``id``; coordinates of the image the detector was given.
    failure : str or None
        Why nothing was found (then ``pixels`` is empty).
    covariance : ndarray, shape (rows * cols, 2, 2), px^2, or None
        Formal covariance of each corner from the image noise
        (:mod:`endomeasure.features.precision`), for the symmetric refinement only; NaN
        where that fit did not converge.
    """

    pixels: np.ndarray
    failure: str | None = None
    covariance: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.failure is None


def canonical_grid(grid: np.ndarray) -> tuple[np.ndarray, float]:
    """Re-order a detected corner grid into the canonical order.

    Parameters
    ----------
    grid : ndarray, shape (rows, cols, 2), px
        Corners as the detector returned them, reshaped to its grid.

    Returns
    -------
    grid : ndarray, shape (rows, cols, 2), px
        Columns increase along +u, rows along +v (id 0 nearest the top-left).
    angle_deg : float
        In-plane angle of the canonical column direction from +u, degrees.

    Notes
    -----
    Candidates are the orderings that keep the grid shape and do not mirror it: the
    identity and the 180-degree turn, plus the two 90-degree turns when the grid is
    square. The winner maximises ``e_col . (1, 0) + e_row . (0, 1)``, with ``e_col`` and
    ``e_row`` the unit mean steps along columns and rows. A mirror ordering never wins for
    a non-mirrored view; if the detector returned a mirrored grid (its row and column
    steps form a left-handed pair in the image), it is flipped along its columns first.
    """
    grid = np.asarray(grid, dtype=np.float64)

    def steps(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        col = np.diff(g, axis=1).reshape(-1, 2).mean(axis=0)
        row = np.diff(g, axis=0).reshape(-1, 2).mean(axis=0)
        return col / np.linalg.norm(col), row / np.linalg.norm(row)

    e_col, e_row = steps(grid)
    # Image axes (u right, v down): a non-mirrored order has cross(e_col, e_row) > 0.
    if e_col[0] * e_row[1] - e_col[1] * e_row[0] < 0:
        grid = grid[:, ::-1]
    candidates = [grid, grid[::-1, ::-1]]
    if grid.shape[0] == grid.shape[1]:
        turned = np.rot90(grid, k=1, axes=(0, 1))
        candidates += [turned, turned[::-1, ::-1]]
    best, best_score = grid, -np.inf
    for candidate in candidates:
        e_col, e_row = steps(candidate)
        score = e_col[0] + e_row[1]
        if score > best_score:
            best, best_score = candidate, score
    e_col, _ = steps(best)
    angle = float(np.degrees(np.arctan2(e_col[1], e_col[0])))
    return np.ascontiguousarray(best), angle


def adaptive_subpix_halfwindow(grid: np.ndarray) -> int:
    """cornerSubPix half-window for a grid: a fraction of its shortest corner spacing, px.

    Parameters
    ----------
    grid : ndarray, shape (rows, cols, 2), px
    """
    spacing_col = np.linalg.norm(np.diff(grid, axis=1), axis=-1).min()
    spacing_row = np.linalg.norm(np.diff(grid, axis=0), axis=-1).min()
    half = int(np.floor(SUBPIX_WINDOW_FRACTION * min(spacing_col, spacing_row)))
    return int(np.clip(half, SUBPIX_MIN_HALFWINDOW, SUBPIX_MAX_HALFWINDOW))


def refine_corners(gray: np.ndarray, pixels: np.ndarray, halfwindow: int) -> np.ndarray:
    """Refine corner pixels with ``cv2.cornerSubPix``.

    Parameters
    ----------
    gray : ndarray, shape (height, width), uint8 or float32
    pixels : ndarray, shape (n, 2), px
    halfwindow : int, px
        Half side of the search window.

    Returns
    -------
    ndarray, shape (n, 2), px (float64)
    """
    import cv2

    corners = np.ascontiguousarray(pixels, dtype=np.float32).reshape(-1, 1, 2)
    criteria = (
        cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
        SUBPIX_MAX_ITERATIONS,
        SUBPIX_EPSILON_PX,
    )
    refined = cv2.cornerSubPix(gray, corners, (halfwindow, halfwindow), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64)


def refine_symmetric(gray: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Refine a corner grid: ``cornerSubPix`` first, then the centre of point symmetry.

    The pixels of :func:`refine_symmetric_precise`, without their covariance.
    """
    return refine_symmetric_precise(gray, grid, precision=False)[0]


def refine_symmetric_precise(
    gray: np.ndarray, grid: np.ndarray, *, precision: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Refine a corner grid to the centres of point symmetry, with each corner's covariance.

    ``cornerSubPix`` gives the start; the symmetric comparison follows the curvature of
    the grid lines, estimated per corner from a quadratic fit to its 5 x 5 started
    neighbours (:func:`endomeasure.features.subpixel.local_quadratic`).

    Parameters
    ----------
    gray : ndarray, shape (height, width), uint8
    grid : ndarray, shape (rows, cols, 2), px
        Detected corners in canonical order.
    precision : bool
        Whether to compute the covariance.

    Returns
    -------
    pixels : ndarray, shape (rows * cols, 2), px
        Where the symmetric fit does not converge (a corner whose window would leave the
        image, a singular fit), the ``cornerSubPix`` pixel.
    covariance : ndarray, shape (rows * cols, 2, 2), px^2, or None
        The fit's formal covariance from the image noise it sees (estimated per corner
        from the fit's residuals, :func:`endomeasure.features.precision.symmetric_precision`);
        NaN where the fit did not converge.
    """
    from endomeasure.features.precision import symmetric_precision
    from endomeasure.features.subpixel import local_quadratic, symmetric_corners

    started = refine_corners(gray, grid.reshape(-1, 2), adaptive_subpix_halfwindow(grid))
    # The grid's local quadratic map bends the symmetric comparison along the grid lines
    # that lens distortion curves (docs/accuracy.md, "Detection": it removes a mirrored
    # u-bias of the two halves).
    steps, curvature = local_quadratic(started.reshape(grid.shape))
    result = symmetric_corners(gray, None, started, steps=steps, curvature=curvature)
    if not precision:
        return result.pixels, None
    covariance = np.full((len(started), 2, 2), np.nan)
    ok = result.converged
    if ok.any():
        formal = symmetric_precision(gray, result.pixels[ok], steps[ok], curvature[ok])
        covariance[ok] = formal.covariance
    return result.pixels, covariance


class _LargerBoard(Exception):
    """The sector-based finder saw a larger grid than the spec (a different board)."""

    def __init__(self, shape: tuple[int, int]):
        super().__init__(shape)
        self.shape = shape


def _find_raw(gray: np.ndarray, spec: ChessboardSpec, method: str) -> np.ndarray | None:
    """Run the OpenCV finder of a method; corners (rows, cols, 2) in its order, or None.

    The sector-based finder runs with ``CALIB_CB_LARGER`` so that it reports the whole
    grid it sees: otherwise it happily returns an 8x6 part of a 9x6 board, with every id
    off by one column. A larger grid raises :class:`_LargerBoard`.
    """
    import cv2

    if method.startswith("classic"):
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, spec.pattern_size, flags=flags)
        if not found or corners is None or len(corners) != spec.n_corners:
            return None
        return corners.reshape(spec.rows, spec.cols, 2).astype(np.float64)
    flags = cv2.CALIB_CB_LARGER
    if method.startswith("sb-accuracy"):
        flags |= cv2.CALIB_CB_ACCURACY
    if method == "sb-accuracy-exhaustive":
        flags |= cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners, meta = cv2.findChessboardCornersSBWithMeta(gray, spec.pattern_size, flags)
    if not found or corners is None or meta is None:
        return None
    # meta's shape is the found grid as (lines, corners per line) in the corners' order.
    shape = tuple(int(n) for n in meta.shape[:2])
    grid = corners.reshape(shape[0], shape[1], 2).astype(np.float64)
    # CALIB_CB_LARGER sometimes extrapolates a line of "corners" along the board's outer
    # edge, where the outer squares meet the white margin: drop lines that are not X's.
    grid = trim_false_lines(gray, grid)
    shape = grid.shape[:2]
    if sorted(shape) != sorted(spec.pattern_size):
        raise _LargerBoard(shape)
    if shape != (spec.rows, spec.cols):
        grid = np.swapaxes(grid, 0, 1)
    return grid


def saddle_scores(gray: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """How much each grid point looks like a chessboard X-junction, 0..1.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    grid : ndarray, shape (rows, cols, 2), px

    Returns
    -------
    ndarray, shape (rows, cols)
        ``|(I1 + I3) - (I2 + I4)| / (2 (max - min))`` over the four quadrant samples
        ``p + (+-a +- b) / 4`` (a, b the local grid steps; I1, I3 and I2, I4 diagonal
        pairs): 1 for an X-junction, 0.5 where a square meets the board's margin.
    """
    from scipy.ndimage import map_coordinates

    step_col = np.gradient(grid, axis=1)
    step_row = np.gradient(grid, axis=0)
    signs = ((1, 1), (-1, 1), (-1, -1), (1, -1))
    image = gray.astype(np.float64)
    samples = []
    for sa, sb in signs:
        points = grid + 0.25 * (sa * step_col + sb * step_row)
        coords = [points[..., 1].ravel(), points[..., 0].ravel()]
        samples.append(map_coordinates(image, coords, order=1, mode="nearest"))
    q = np.stack(samples).reshape(4, *grid.shape[:2])
    spread = q.max(axis=0) - q.min(axis=0)
    score = np.abs(q[0] + q[2] - q[1] - q[3]) / np.maximum(2 * spread, 1e-9)
    return np.where(spread > 0, score, 0.0)


def trim_false_lines(gray: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Drop outer rows and columns of a grid whose points are not X-junctions.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    grid : ndarray, shape (rows, cols, 2), px

    Returns
    -------
    ndarray, shape (rows', cols', 2)
    """
    while min(grid.shape[:2]) > 2:
        scores = saddle_scores(gray, grid)
        edges = {
            "top": np.median(scores[0]),
            "bottom": np.median(scores[-1]),
            "left": np.median(scores[:, 0]),
            "right": np.median(scores[:, -1]),
        }
        worst = min(edges, key=edges.get)
        if edges[worst] >= MIN_SADDLE_SCORE:
            break
        grid = {
            "top": grid[1:],
            "bottom": grid[:-1],
            "left": grid[:, 1:],
            "right": grid[:, :-1],
        }[worst]
    return grid


def detect_chessboard(
    gray: np.ndarray, spec: ChessboardSpec, method: str = DEFAULT_CHESSBOARD_METHOD
) -> ChessboardResult:
    """Find all inner corners of a chessboard in a grey image, canonical ids, refined.

    Parameters
    ----------
    gray : ndarray, shape (height, width), uint8
        One half of a split image (or any image).
    spec : ChessboardSpec
    method : str
        One of :data:`CHESSBOARD_METHODS`.

    Returns
    -------
    ChessboardResult
        ``pixels`` shape (spec.n_corners, 2) in the coordinates of ``gray``; or a
        failure reason (the diagnosis of a partial or mismatched board is left to the
        caller, which knows the whole half).
    """
    if method not in CHESSBOARD_METHODS:
        raise ValueError(f"unknown chessboard method {method!r}; one of {CHESSBOARD_METHODS}")
    try:
        if method in ("sb-classic-subpix", "sb-classic-symmetry"):
            raw = _find_raw(gray, spec, "sb")
            if raw is None:
                raw = _find_raw(gray, spec, "classic")
        else:
            raw = _find_raw(gray, spec, method)
    except _LargerBoard as larger:
        small, large = sorted(larger.shape)
        a, b = (large, small) if spec.cols >= spec.rows else (small, large)
        return ChessboardResult(
            np.empty((0, 2)),
            failure=(
                f"the board does not match the spec: a grid of {a}x{b} inner corners is "
                f"visible, the spec {spec.canonical()} has {spec.cols}x{spec.rows}"
            ),
        )
    if raw is None:
        return ChessboardResult(np.empty((0, 2)), failure=NOT_FOUND)
    grid, angle = canonical_grid(raw)
    if abs(angle) > MAX_CANONICAL_ANGLE_DEG:
        return ChessboardResult(
            np.empty((0, 2)),
            failure=(
                f"board turned {angle:.0f} degrees in the image: corner ids would be ambiguous "
                f"(more than {MAX_CANONICAL_ANGLE_DEG:.0f} degrees)"
            ),
        )
    pixels = grid.reshape(-1, 2)
    if method.endswith("symmetry"):
        pixels, covariance = refine_symmetric_precise(gray, grid)
        return ChessboardResult(pixels, covariance=covariance)
    if method == "sb-saddle":
        from endomeasure.features.subpixel import saddle_corners

        return ChessboardResult(saddle_corners(gray, grid).pixels)
    if "subpix" in method:
        suffix = method.rsplit("subpix", 1)[1]
        halfwindow = int(suffix) if suffix else adaptive_subpix_halfwindow(grid)
        pixels = refine_corners(gray, pixels, halfwindow)
    return ChessboardResult(pixels)
