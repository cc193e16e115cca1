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

The two ``sb-classic`` methods have a last fallback when both finders fail: the
sector-based finder on the image up-sampled 2x (bicubic), its corners mapped back. It
only finds; the refinement runs on the original image. It rescues boards of squares a
few pixels wide in the dim field near the apex band (``docs/rotation.md``).

A grid of the spec's size is only kept when it is the whole board: one grid step beyond
each of its outer lines the board's edge must be seen (the outer squares meeting the
margin), not a further line of X-junctions (:func:`board_edges`). Otherwise a 7x6 part
of an 8x6 board, found by the classic finder or after a real line was trimmed, would be
stored with every id shifted by a column. A half whose board edge is hidden (outside the
half, in the prism band's shadow) is refused as a partial board for the same reason.

Corner ids at any in-plane rotation (so that the same id in both halves is the same
physical corner and detections match the simulator's truth). OpenCV may return the grid
starting at any corner, mirrored or transposed. :func:`orient_grid` makes it
right-handed in the image, then chooses among the quarter turns that map the grid of
inner corners onto itself (the half turn; all four for a square grid) the one that the
board's colouring singles out: the square between corners 0, 1, ``cols`` and
``cols + 1`` is black (the board frame of ``features/boards.py`` and the simulator). A
half turn swaps the colours when ``cols + rows`` is odd (9x6), a quarter turn of a
square grid when its side is odd (7x7), so the colour fixes the ids of a 9x6 board
completely, those of a 7x7 board up to a half turn, and those of 8x6 or 8x8 boards not
at all. What the colouring leaves open (the result's ``turns``) is decided by the image:
columns nearest to +u and rows to +v (id 0 nearest the top-left), and, for the two
halves of one frame, by :func:`endomeasure.features.detect.agree_halves`, which turns the
right half's ids so that its grid direction agrees with the left half's.
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
    "board_turns",
    "canonical_grid",
    "colour_preserving_turns",
    "detect_chessboard",
    "board_edges",
    "orient_grid",
    "refine_corners",
    "refine_symmetric",
    "refine_symmetric_precise",
    "saddle_scores",
    "square_colour_vote",
    "trim_false_lines",
    "turn_grid",
    "turn_result",
    "turned_ids",
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

# The board's colouring is read when at least this fraction of the pairs of neighbouring
# inner squares agree on which parity is the dark one (a real board: all of them; glare
# or a stain may spoil a few, a misdetected grid half of them).
COLOUR_VOTE_DECISIVE = 0.9
# Where a square's grey level is sampled: its centre and the points this fraction of the
# way from the centre to each of its corners (well inside the square under blur).
COLOUR_SAMPLE_FRACTION = 0.5
# cornerSubPix: stop after this many iterations or when a corner moves less than this.
SUBPIX_MAX_ITERATIONS = 100
SUBPIX_EPSILON_PX = 1e-4
# The adapted half-window is this fraction of the shortest corner spacing, so the window
# never reaches the grid lines that do not pass through the corner.
SUBPIX_WINDOW_FRACTION = 0.5
SUBPIX_MIN_HALFWINDOW, SUBPIX_MAX_HALFWINDOW = 2, 15
# The last-resort finder's up-sampling factor (small squares).
FALLBACK_UPSAMPLE = 2
NOT_FOUND = "no chessboard found"
# Grid lines whose median X-junction score is lower are not corners (a real X scores
# about 1, a square's edge against the white margin 0.5).
MIN_SADDLE_SCORE = 0.75
# The board's edge beyond a grid is judged when at least this fraction of the extrapolated
# line is inside the image. It is seen as an edge when its median saddle score is at most
# EDGE_MAX_SCORE and its grey-level spread at least EDGE_MIN_CONTRAST times the spread at
# the grid's corners (the margin meets squares of the board's contrast; the dark prism
# band has little). On the demo session's 140 whole boards (560 edges) every edge is
# inside, with scores 0.47-0.52 and spread ratios 0.50-1.2; faded corners in the band's
# shadow score 0.56-0.77 with ratios near 0.3, and are told apart from neither.
EDGE_INSIDE_FRACTION = 0.5
EDGE_MAX_SCORE = 0.6
EDGE_MIN_CONTRAST = 0.4


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
    angle_deg : float, degrees
        In-plane angle of the grid's column direction (id 0 -> 1) from +u, in
        (-180, 180]; NaN when nothing was found.
    turns : tuple of int
        Quarter turns of these ids (:func:`turn_grid`) that the board cannot tell apart
        from them: (0,) when the colouring fixes the ids, (0, 2) or (0, 1, 2, 3)
        otherwise.
    """

    pixels: np.ndarray
    failure: str | None = None
    covariance: np.ndarray | None = None
    angle_deg: float = float("nan")
    turns: tuple[int, ...] = (0,)

    @property
    def ok(self) -> bool:
        return self.failure is None


def _unit_steps(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit mean steps of a grid (rows, cols, 2) along its columns and along its rows."""
    col = np.diff(grid, axis=1).reshape(-1, 2).mean(axis=0)
    row = np.diff(grid, axis=0).reshape(-1, 2).mean(axis=0)
    return col / np.linalg.norm(col), row / np.linalg.norm(row)


def _column_angle(grid: np.ndarray) -> float:
    """Angle of a grid's column direction from +u (towards +v), degrees, (-180, 180]."""
    e_col, _ = _unit_steps(grid)
    return float(np.degrees(np.arctan2(e_col[1], e_col[0])))


def _right_handed(grid: np.ndarray) -> np.ndarray:
    """The grid, flipped along its columns if its steps form a mirrored pair in the image.

    Image axes (u right, v down): a board seen from its printed side (board z away from
    the camera) has ``cross(e_col, e_row) > 0``.
    """
    e_col, e_row = _unit_steps(grid)
    if e_col[0] * e_row[1] - e_col[1] * e_row[0] < 0:
        return grid[:, ::-1]
    return grid


def board_turns(cols: int, rows: int) -> tuple[int, ...]:
    """Quarter turns that map a grid of ``cols`` x ``rows`` inner corners onto itself."""
    return (0, 1, 2, 3) if cols == rows else (0, 2)


def colour_preserving_turns(cols: int, rows: int) -> tuple[int, ...]:
    """The turns of :func:`board_turns` that also keep the board's colouring.

    Notes
    -----
    Inner square ``(r, c)`` (between corners ``(r, c)`` and ``(r + 1, c + 1)``) is black
    when ``r + c`` is even. The half turn takes it to ``(rows - 2 - r, cols - 2 - c)``,
    parity ``r + c + rows + cols``; a quarter turn of an ``n x n`` grid to
    ``(c, n - 2 - r)``, parity ``r + c + n``. So the half turn keeps the colours when
    ``cols + rows`` is even, a quarter turn when ``n`` is even.
    """
    turns = [0]
    if cols == rows and cols % 2 == 0:
        turns += [1, 3]
    if (cols + rows) % 2 == 0:
        turns.append(2)
    return tuple(sorted(turns))


def turn_grid(grid: np.ndarray, k: int) -> np.ndarray:
    """Re-label a right-handed grid so that its column direction turns by ``k`` x 90 deg.

    Parameters
    ----------
    grid : ndarray, shape (rows, cols, 2), px
        Right-handed (:func:`orient_grid`); odd ``k`` needs a square grid.
    k : int
        Quarter turns, positive from +u towards +v (clockwise as the image is shown).

    Returns
    -------
    ndarray, same shape
        ``k = 1``: ``new[r, c] = grid[c, n - 1 - r]`` (the new columns run along the old
        rows, the new rows against the old columns); ``k = 2``: ``grid[::-1, ::-1]``.
    """
    k %= 4
    if k % 2 and grid.shape[0] != grid.shape[1]:
        raise ValueError(f"a quarter turn needs a square grid, not {grid.shape[:2]}")
    for _ in range(k):
        grid = np.swapaxes(grid, 0, 1)[::-1]
    return np.ascontiguousarray(grid)


def turned_ids(cols: int, rows: int, k: int) -> np.ndarray:
    """Which old id each new id names after :func:`turn_grid` by ``k`` quarter turns.

    Returns
    -------
    ndarray, shape (rows * cols,), int64
        ``old = turned_ids(...)[new]``: the corner that had id ``old`` has id ``new``.
    """
    ids = np.arange(rows * cols, dtype=np.int64).reshape(rows, cols, 1)
    return turn_grid(ids, k).reshape(-1)


def _upright(grid: np.ndarray, turns: tuple[int, ...]) -> tuple[np.ndarray, int]:
    """Of the given turns of a right-handed grid, the one nearest columns +u, rows +v.

    Maximises ``e_col . (1, 0) + e_row . (0, 1)``; ties go to the first turn listed.
    """
    best, best_k, best_score = grid, 0, -np.inf
    for k in turns:
        candidate = turn_grid(grid, k)
        e_col, e_row = _unit_steps(candidate)
        score = e_col[0] + e_row[1]
        if score > best_score + 1e-12:
            best, best_k, best_score = candidate, k, score
    return best, best_k


def canonical_grid(grid: np.ndarray) -> tuple[np.ndarray, float]:
    """Re-order a detected corner grid into the image's upright order.

    Parameters
    ----------
    grid : ndarray, shape (rows, cols, 2), px
        Corners as the detector returned them, reshaped to its grid.

    Returns
    -------
    grid : ndarray, shape (rows, cols, 2), px
        Columns nearest to +u, rows to +v (id 0 nearest the top-left), whatever the
        board's colouring says (:func:`orient_grid` reads it).
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
    grid = _right_handed(np.asarray(grid, dtype=np.float64))
    rows, cols = grid.shape[:2]
    best, _ = _upright(grid, board_turns(cols, rows))
    return best, _column_angle(best)


def square_colour_vote(gray: np.ndarray, grid: np.ndarray) -> tuple[float, float]:
    """How clearly the image says which inner squares of a grid are the dark ones.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    grid : ndarray, shape (rows, cols, 2), px

    Returns
    -------
    even_dark, odd_dark : float
        Fractions of the pairs of neighbouring inner squares in which the square of even
        parity (``r + c`` even, inner square ``(r, c)`` between corners ``(r, c)`` and
        ``(r + 1, c + 1)``) is strictly the darker, and in which the odd one is; NaN
        when the grid has no two neighbouring inner squares. Comparing neighbours, not
        one threshold, is immune to vignetting and uneven light across the board.
    """
    from scipy.ndimage import map_coordinates

    quads = np.stack([grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]])
    centre = quads.mean(axis=0)
    points = np.concatenate(
        [centre[None], centre[None] + COLOUR_SAMPLE_FRACTION * (quads - centre[None])]
    )
    coords = [points[..., 1].ravel(), points[..., 0].ravel()]
    samples = map_coordinates(gray.astype(np.float64), coords, order=1, mode="nearest")
    level = samples.reshape(points.shape[:-1]).mean(axis=0)
    r, c = np.indices(level.shape)
    first_even = (r + c) % 2 == 0
    pairs = [
        (level[:, :-1], level[:, 1:], first_even[:, :-1]),
        (level[:-1, :], level[1:, :], first_even[:-1, :]),
    ]
    first = np.concatenate([a.ravel() for a, _, _ in pairs])
    second = np.concatenate([b.ravel() for _, b, _ in pairs])
    even_first = np.concatenate([e.ravel() for _, _, e in pairs])
    if first.size == 0:
        return float("nan"), float("nan")
    even, odd = np.where(even_first, first, second), np.where(even_first, second, first)
    return float(np.mean(even < odd)), float(np.mean(odd < even))


def orient_grid(
    gray: np.ndarray, grid: np.ndarray, cols: int, rows: int
) -> tuple[np.ndarray, float, tuple[int, ...]]:
    """Corner ids for a detected grid at any in-plane rotation, from its colouring.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    grid : ndarray, shape (rows, cols, 2), px
        Corners in the detector's order, reshaped to the spec's grid.
    cols, rows : int
        The board's inner corners.

    Returns
    -------
    grid : ndarray, shape (rows, cols, 2), px
        Right-handed; the square between ids 0, 1, ``cols``, ``cols + 1`` black where the
        colouring can say so; of the orders left, the upright one (:func:`canonical_grid`).
    angle_deg : float
        Angle of the returned column direction from +u, degrees.
    turns : tuple of int
        The quarter turns of the returned ids that are as valid
        (:attr:`ChessboardResult.turns`): :func:`colour_preserving_turns` when the
        colouring was read, every :func:`board_turns` when it was not (fewer than
        :data:`COLOUR_VOTE_DECISIVE` of the neighbouring squares agree).
    """
    grid = _right_handed(np.asarray(grid, dtype=np.float64))
    geometric = board_turns(cols, rows)
    keeping = colour_preserving_turns(cols, rows)
    allowed = residual = geometric
    if keeping != geometric:
        even_dark, odd_dark = square_colour_vote(gray, grid)
        if even_dark >= COLOUR_VOTE_DECISIVE:
            allowed = residual = keeping
        elif odd_dark >= COLOUR_VOTE_DECISIVE:
            allowed, residual = tuple(k for k in geometric if k not in keeping), keeping
    best, _ = _upright(grid, allowed)
    return best, _column_angle(best), residual


def turn_result(result: ChessboardResult, cols: int, rows: int, k: int) -> ChessboardResult:
    """The same detection with its ids turned by ``k`` quarter turns (:func:`turn_grid`)."""
    if not result.ok or k % 4 == 0:
        return result
    order = turned_ids(cols, rows, k)
    covariance = None if result.covariance is None else result.covariance[order]
    angle = (result.angle_deg + 90.0 * k + 180.0) % 360.0 - 180.0
    return dataclasses.replace(
        result,
        pixels=result.pixels[order],
        covariance=covariance,
        angle_deg=float(180.0 if angle == -180.0 else angle),
    )


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


def _find_upsampled(gray: np.ndarray, spec: ChessboardSpec) -> np.ndarray | None:
    """The sector-based finder on the image up-sampled by :data:`FALLBACK_UPSAMPLE`.

    ``cv2.resize`` aligns pixel areas, so up-sampled pixel ``x'`` is at original
    ``(x' + 0.5) / f - 0.5`` (pixel centres on integers in both).
    """
    import cv2

    f = FALLBACK_UPSAMPLE
    larger = cv2.resize(gray, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
    raw = _find_raw(larger, spec, "sb")
    return None if raw is None else (raw + 0.5) / f - 0.5


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
    return _saddle_and_spread(gray, grid)[0]


def _saddle_and_spread(gray: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`saddle_scores` and the spread ``max - min`` of the four quadrant samples
    (grey levels), each shape (rows, cols)."""
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
    return np.where(spread > 0, score, 0.0), spread


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


def _extrapolated_line(grid: np.ndarray, axis: int, start: bool) -> np.ndarray:
    """The points one grid step beyond the first (``start``) or last line along ``axis``:
    quadratic from the three outer lines (it follows perspective and distortion), linear
    with two."""
    lines = np.moveaxis(grid, axis, 0)
    if not start:
        lines = lines[::-1]
    if lines.shape[0] >= 3:
        return 3 * lines[0] - 3 * lines[1] + lines[2]
    return 2 * lines[0] - lines[1]


def board_edges(gray: np.ndarray, grid: np.ndarray) -> dict[str, str]:
    """What lies one grid step beyond each outer line of a grid of inner corners.

    A whole board has its outer edge there: the outer squares meet the margin, a saddle
    score near 0.5 (:func:`saddle_scores`) with the contrast of the board. A board larger
    than the grid has another line of X-junctions (a score near 1). Outside the image,
    or where the contrast is gone (the dark prism band, a vignetted corner), nothing can
    be told.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    grid : ndarray, shape (rows, cols, 2), px

    Returns
    -------
    dict of str to str
        For ``'top'``, ``'bottom'``, ``'left'``, ``'right'`` (in the grid's own order):
        ``'edge'``, ``'corners'`` (the board continues) or ``'unseen'``.
    """
    height, width = gray.shape[:2]
    _, outer_spread = _saddle_and_spread(gray, grid)
    contrast = float(np.median(outer_spread))
    found = {}
    for name, axis, start in (("top", 0, True), ("bottom", 0, False),
                              ("left", 1, True), ("right", 1, False)):  # fmt: skip
        beyond = _extrapolated_line(grid, axis, start)
        outer = np.moveaxis(grid, axis, 0)[0 if start else -1]
        inside = (
            (beyond[:, 0] >= 1) & (beyond[:, 0] <= width - 2)
            & (beyond[:, 1] >= 1) & (beyond[:, 1] <= height - 2)
        )  # fmt: skip
        if inside.mean() < EDGE_INSIDE_FRACTION:
            found[name] = "unseen"
            continue
        # the extrapolated line with its neighbour, so that the local steps are defined
        pair = np.stack([beyond, outer] if start else [outer, beyond])
        scores, spread = _saddle_and_spread(gray, pair if axis == 0 else np.swapaxes(pair, 0, 1))
        index = 0 if start else -1
        line = (scores[index], spread[index]) if axis == 0 else (scores[:, index], spread[:, index])
        score, line_spread = (float(np.median(v[inside])) for v in line)
        if score >= MIN_SADDLE_SCORE:
            found[name] = "corners"
        elif score <= EDGE_MAX_SCORE and line_spread >= EDGE_MIN_CONTRAST * contrast:
            found[name] = "edge"
        else:  # faded corners or a faint edge: neither can be told
            found[name] = "unseen"
    return found


def _not_the_whole_board(gray: np.ndarray, raw: np.ndarray, spec: ChessboardSpec) -> str | None:
    """Why a found grid of the spec's size may be a part of a larger board (its ids would
    be shifted), or None when all four edges of the board are seen beyond it."""
    edges = board_edges(gray, raw)
    more = [side for side, what in edges.items() if what == "corners"]
    if more:
        return (
            f"board larger than the spec: the corners continue beyond the {spec.cols}x"
            f"{spec.rows} grid ({', '.join(more)} side of the grid found)"
        )
    unseen = [side for side, what in edges.items() if what == "unseen"]
    if unseen:
        return (
            f"partial board: the board's edge beyond the {', '.join(unseen)} side of the "
            f"{spec.cols}x{spec.rows} grid is not visible, so a larger board cannot be ruled out"
        )
    return None


def detect_chessboard(
    gray: np.ndarray, spec: ChessboardSpec, method: str = DEFAULT_CHESSBOARD_METHOD
) -> ChessboardResult:
    """Find all inner corners of a chessboard in a grey image, ids at any rotation, refined.

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
        ``pixels`` shape (spec.n_corners, 2) in the coordinates of ``gray``, ids by
        :func:`orient_grid` (with the turns the board leaves open); or a failure reason
        (the diagnosis of a partial or mismatched board is left to the
        caller, which knows the whole half).
    """
    if method not in CHESSBOARD_METHODS:
        raise ValueError(f"unknown chessboard method {method!r}; one of {CHESSBOARD_METHODS}")
    try:
        if method in ("sb-classic-subpix", "sb-classic-symmetry"):
            raw = _find_raw(gray, spec, "sb")
            if raw is None:
                raw = _find_raw(gray, spec, "classic")
            if raw is None:
                raw = _find_upsampled(gray, spec)
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
    partial = _not_the_whole_board(gray, raw, spec)
    if partial is not None:  # a part of a larger board would be stored with shifted ids
        return ChessboardResult(np.empty((0, 2)), failure=partial)
    grid, angle, turns = orient_grid(gray, raw, spec.cols, spec.rows)
    found = {"angle_deg": angle, "turns": turns}
    pixels = grid.reshape(-1, 2)
    if method.endswith("symmetry"):
        pixels, covariance = refine_symmetric_precise(gray, grid)
        return ChessboardResult(pixels, covariance=covariance, **found)
    if method == "sb-saddle":
        from endomeasure.features.subpixel import saddle_corners

        return ChessboardResult(saddle_corners(gray, grid).pixels, **found)
    if "subpix" in method:
        suffix = method.rsplit("subpix", 1)[1]
        halfwindow = int(suffix) if suffix else adaptive_subpix_halfwindow(grid)
        pixels = refine_corners(gray, pixels, halfwindow)
    return ChessboardResult(pixels, **found)
