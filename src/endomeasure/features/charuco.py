"""ChArUco corners in one half: the board's own ids, so partial views are fine.

Each ChArUco inner corner is identified by the ArUco markers around it, so its id is the
board's own id (``row * (squares_x - 1) + col``, OpenCV's numbering) however much of the
board the half shows and however it is turned. The same id in both halves is therefore
the same physical corner by construction. Detection is ``cv2.aruco.CharucoDetector``
(markers, then corners interpolated from the markers' local homographies).

Refinement (the default ``symmetry``): the centre of point symmetry, as for plain
chessboards (:mod:`endomeasure.features.subpixel`), with the window shrunk to the zone
around the corner that is point-symmetric on a ChArUco board: the white gap between the
corner and the markers plus the markers' black border cell, the same in both white
squares (:func:`symmetric_radius_squares`); the window's shape comes from the local
affine map of the detected neighbours (:func:`charuco_local_steps`). It starts from the
detector's corners; ``cornerSubPix`` (its window inside the gap, 2-3 px) is the
fallback where it does not converge. On the simulator's ChArUco set it is several
times more accurate than ``cornerSubPix`` and the detector's own corners
(``bench/accuracy_charuco.py``; figures in ``docs/accuracy.md``, "ChArUco against the
simulator's truth").

The board layout is OpenCV's current one (``setLegacyPattern(False)``, OpenCV >= 4.6),
the one ``CharucoBoard.generateImage`` draws.
"""

from __future__ import annotations

import numpy as np

from endomeasure.features.boards import CharucoSpec
from endomeasure.features.chessboard import (
    SUBPIX_MAX_HALFWINDOW,
    SUBPIX_MIN_HALFWINDOW,
    SUBPIX_WINDOW_FRACTION,
    refine_corners,
)

__all__ = [
    "CHARUCO_REFINEMENTS",
    "DEFAULT_CHARUCO_REFINEMENT",
    "CharucoResult",
    "charuco_local_steps",
    "detect_charuco",
    "opencv_charuco_board",
    "refine_charuco_symmetric",
    "symmetric_radius_squares",
]

# Fewest corners accepted in a half: fewer cannot constrain anything downstream.
MIN_CHARUCO_CORNERS = 4
# cornerSubPix half-window as a fraction of the white gap between a corner and the markers.
MARKER_GAP_WINDOW_FRACTION = 0.9
# Refinements, compared on the simulator's ChArUco set by bench/accuracy_charuco.py
# (docs/accuracy.md, "ChArUco against the simulator's truth"); symmetry is the best.
CHARUCO_REFINEMENTS = ("opencv", "subpix", "symmetry")
DEFAULT_CHARUCO_REFINEMENT = "symmetry"
# The symmetric window's cut (2 sigma) as a fraction of the symmetric radius (gap + border
# cell): near the best of the sweep (bench/accuracy_charuco.py --sweep, docs/accuracy.md),
# just under 1 to keep a margin for the blur of the markers' bits at the far end.
SYMMETRY_WINDOW_FRACTION = 0.9
# The local affine map of a corner is fitted to the detected corners this many columns
# and rows around it.
STEP_NEIGHBOURHOOD = 2


class CharucoResult:
    """Detected ChArUco corners of one half.

    Attributes
    ----------
    ids : ndarray, shape (n,), int64
        Board ids, increasing.
    pixels : ndarray, shape (n, 2), px
    n_markers : int
        Markers decoded.
    failure : str or None
    covariance : ndarray, shape (n, 2, 2), px^2, or None
        Formal covariance of the symmetric refinement (NaN where it did not converge).
    """

    def __init__(self, ids: np.ndarray, pixels: np.ndarray, n_markers: int, failure: str | None,
                 covariance: np.ndarray | None = None):  # fmt: skip
        self.ids = ids
        self.pixels = pixels
        self.n_markers = n_markers
        self.failure = failure
        self.covariance = covariance

    @property
    def ok(self) -> bool:
        return self.failure is None


def opencv_charuco_board(spec: CharucoSpec):
    """The ``cv2.aruco.CharucoBoard`` of a spec (lengths in mm)."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard(
        (spec.squares_x, spec.squares_y), spec.square_mm, spec.marker_mm, dictionary
    )
    board.setLegacyPattern(False)
    return board


def _spacing_halfwindow(
    ids: np.ndarray, pixels: np.ndarray, cols: int, fraction: float
) -> np.ndarray:
    """Per-corner cornerSubPix half-window from the distance to its nearest corner, px.

    Uses the pixel distance to any other detected corner divided by the id distance on
    the board, so a corner whose direct neighbours are missing still gets a window
    scaled to the square size.
    """
    row, col = np.divmod(ids, cols)
    grid = np.stack([col, row], axis=1).astype(float)
    board_distance = np.linalg.norm(grid[:, None] - grid[None], axis=-1)
    pixel_distance = np.linalg.norm(pixels[:, None] - pixels[None], axis=-1)
    np.fill_diagonal(board_distance, np.inf)
    spacing = np.min(
        np.where(np.isfinite(board_distance), pixel_distance / board_distance, np.inf), axis=1
    )
    half = np.floor(fraction * spacing)
    return np.clip(half, SUBPIX_MIN_HALFWINDOW, SUBPIX_MAX_HALFWINDOW).astype(int)


def symmetric_radius_squares(spec: CharucoSpec) -> float:
    """How far from an inner corner the board is point-symmetric, in squares.

    Around a corner the two black squares are plain; in the two white squares the
    marker begins ``gap = (square - marker) / 2`` from the square's edges with a black
    border one marker cell wide (``marker / (bits + 2)``), the same in both. Only the
    marker's inner bits differ, from ``gap + cell`` on.
    """
    bits = 5 if spec.dictionary == "DICT_ARUCO_ORIGINAL" else int(spec.dictionary[5])
    gap = (spec.square_mm - spec.marker_mm) / 2.0
    cell = spec.marker_mm / (bits + 2)
    return (gap + cell) / spec.square_mm


def charuco_local_steps(ids: np.ndarray, pixels: np.ndarray, cols: int) -> np.ndarray:
    """Local affine map of each detected ChArUco corner from its detected neighbours.

    Parameters
    ----------
    ids : ndarray, shape (n,), int
    pixels : ndarray, shape (n, 2), px
    cols : int
        Inner corners per board row.

    Returns
    -------
    ndarray, shape (n, 2, 2), px
        Columns: the step to the next column and to the next row (as
        :func:`endomeasure.features.subpixel.local_steps`), least squares over the
        corners within :data:`STEP_NEIGHBOURHOOD` columns and rows, weighted by the
        inverse board distance; NaN where those neighbours do not span both directions.
    """
    row, col = np.divmod(np.asarray(ids, dtype=np.int64), cols)
    grid = np.stack([col, row], axis=1).astype(np.float64)
    delta = grid[None, :, :] - grid[:, None, :]  # (n, n, 2) board offsets i -> j
    moved = pixels[None, :, :] - pixels[:, None, :]
    near = (np.abs(delta).max(axis=-1) <= STEP_NEIGHBOURHOOD) & (np.abs(delta).sum(-1) > 0)
    weight = np.where(near, 1.0 / np.maximum(np.linalg.norm(delta, axis=-1), 1.0), 0.0)
    wd = delta * weight[..., None]
    normal = np.einsum("nji,njk->nik", wd, delta)  # (n, 2, 2)
    rhs = np.einsum("nji,njk->nik", wd, moved)  # (n, 2, 2): rows d(col), d(row)
    det = normal[:, 0, 0] * normal[:, 1, 1] - normal[:, 0, 1] ** 2
    scale = np.maximum(np.trace(normal, axis1=1, axis2=2), 1e-300) ** 2
    spans = det > 1e-6 * scale
    safe = np.where(spans[:, None, None], normal, np.eye(2))
    steps = np.linalg.solve(safe, rhs).transpose(0, 2, 1)  # columns: col step, row step
    steps[~spans] = np.nan
    return steps


def refine_charuco_symmetric(
    gray: np.ndarray,
    ids: np.ndarray,
    pixels: np.ndarray,
    spec: CharucoSpec,
    *,
    window_fraction: float = SYMMETRY_WINDOW_FRACTION,
    precision: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Refine ChArUco corners to the centre of point symmetry, the window off the bits.

    Parameters
    ----------
    gray : ndarray, shape (height, width), uint8
    ids : ndarray, shape (n,), int
    pixels : ndarray, shape (n, 2), px
        Starting corners (within about a pixel), e.g. the detector's.
    spec : CharucoSpec
    window_fraction : float
        The Gaussian window is cut (at two sigmas) at this fraction of
        :func:`symmetric_radius_squares`.
    precision : bool
        Whether to compute each refined corner's formal covariance.

    Returns
    -------
    pixels : ndarray, shape (n, 2), px
        The start where the fit did not converge or the neighbours gave no local map.
    refined : ndarray, shape (n,), bool
    covariance : ndarray, shape (n, 2, 2), px^2, or None
        The fit's formal covariance from the image noise
        (:func:`endomeasure.features.precision.symmetric_precision`), NaN where not
        refined; None unless ``precision``.
    """
    from endomeasure.features.precision import symmetric_precision
    from endomeasure.features.subpixel import SYMMETRY_TRUNCATE, symmetric_corners

    steps = charuco_local_steps(ids, pixels, spec.cols)
    usable = np.isfinite(steps).all(axis=(1, 2))
    out = np.array(pixels, dtype=np.float64)
    refined = np.zeros(len(out), dtype=bool)
    covariance = np.full((len(out), 2, 2), np.nan) if precision else None
    if not usable.any():
        return out, refined, covariance
    sigma = window_fraction * symmetric_radius_squares(spec) / SYMMETRY_TRUNCATE
    result = symmetric_corners(gray, None, out[usable], sigma_squares=sigma, steps=steps[usable])
    out[usable] = result.pixels
    refined[usable] = result.converged
    if precision and refined.any():
        formal = symmetric_precision(gray, out[refined], steps[refined], sigma_squares=sigma)
        covariance[refined] = formal.covariance
    return out, refined, covariance


def detect_charuco(
    gray: np.ndarray, spec: CharucoSpec, refinement: str = DEFAULT_CHARUCO_REFINEMENT
) -> CharucoResult:
    """Find the ChArUco inner corners visible in a grey image, with the board's ids.

    Parameters
    ----------
    gray : ndarray, shape (height, width), uint8
    spec : CharucoSpec
    refinement : str
        One of :data:`CHARUCO_REFINEMENTS`: ``opencv`` (the detector's own corners),
        ``subpix`` (``cornerSubPix`` with a window inside the white gap), ``symmetry``
        (the centre of point symmetry from the detector's corners, ``subpix`` where it
        does not converge).

    Returns
    -------
    CharucoResult
        Pixels in the coordinates of ``gray``, ordered by id.
    """
    if refinement not in CHARUCO_REFINEMENTS:
        raise ValueError(
            f"unknown ChArUco refinement {refinement!r}; known: {', '.join(CHARUCO_REFINEMENTS)}"
        )
    import cv2

    detector = cv2.aruco.CharucoDetector(opencv_charuco_board(spec))
    corners, ids, _marker_corners, marker_ids = detector.detectBoard(gray)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    empty = np.empty((0,), dtype=np.int64), np.empty((0, 2))
    if n_markers == 0:
        return CharucoResult(*empty, 0, f"no {spec.dictionary} markers of the board found")
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        found = 0 if ids is None else len(ids)
        return CharucoResult(
            *empty,
            n_markers,
            f"only {found} ChArUco corners from {n_markers} markers (needs {MIN_CHARUCO_CORNERS})",
        )
    ids = ids.reshape(-1).astype(np.int64)
    pixels = corners.reshape(-1, 2).astype(np.float64)
    valid = (ids >= 0) & (ids < spec.n_corners)
    ids, pixels = ids[valid], pixels[valid]
    order = np.argsort(ids)
    ids, pixels = ids[order], pixels[order]
    if refinement == "opencv":
        return CharucoResult(ids, pixels, n_markers, None)
    # The window must stay off the markers, which begin (square - marker) / 2 from the
    # corner's edges: the chessboard's half-square window reaches them and fails.
    gap_fraction = (spec.square_mm - spec.marker_mm) / (2.0 * spec.square_mm)
    fraction = min(SUBPIX_WINDOW_FRACTION, MARKER_GAP_WINDOW_FRACTION * gap_fraction)
    halfwindows = _spacing_halfwindow(ids, pixels, spec.cols, fraction)
    refined = np.empty_like(pixels)
    for window in np.unique(halfwindows):
        chosen = halfwindows == window
        refined[chosen] = refine_corners(gray, pixels[chosen], int(window))
    if refinement == "symmetry":
        # from the detector's corners: cornerSubPix's small window occasionally walks
        # off a corner by more than the symmetric fit's reach
        symmetric, converged, covariance = refine_charuco_symmetric(
            gray, ids, pixels, spec, precision=True
        )
        refined = np.where(converged[:, None], symmetric, refined)
        return CharucoResult(ids, refined, n_markers, None, covariance)
    return CharucoResult(ids, refined, n_markers, None)
