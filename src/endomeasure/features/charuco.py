"""ChArUco corners in one half: the board's own ids, so partial views are fine.

Each ChArUco inner corner is identified by the ArUco markers around it, so its id is the
board's own id (``row * (squares_x - 1) + col``, OpenCV's numbering) however much of the
board the half shows and however it is turned. The same id in both halves is therefore
the same physical corner by construction. Detection is ``cv2.aruco.CharucoDetector``
(markers, then corners interpolated from the markers' local homographies); the corners
are then refined with ``cv2.cornerSubPix`` with a half-window matched to the square size
seen in the image. Plain chessboards go one step further, to the centre of point
symmetry (:mod:`endomeasure.features.subpixel`), whose window needs the four squares
around a corner to be plain; here the markers start ``(square - marker) / 2`` from the
corner, so that window would have to shrink to the white gap (not yet measured).

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

__all__ = ["CharucoResult", "detect_charuco", "opencv_charuco_board"]

# Fewest corners accepted in a half: fewer cannot constrain anything downstream.
MIN_CHARUCO_CORNERS = 4
# cornerSubPix half-window as a fraction of the white gap between a corner and the markers.
MARKER_GAP_WINDOW_FRACTION = 0.9


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
    """

    def __init__(self, ids: np.ndarray, pixels: np.ndarray, n_markers: int, failure: str | None):
        self.ids = ids
        self.pixels = pixels
        self.n_markers = n_markers
        self.failure = failure

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


def detect_charuco(gray: np.ndarray, spec: CharucoSpec) -> CharucoResult:
    """Find the ChArUco inner corners visible in a grey image, with the board's ids.

    Parameters
    ----------
    gray : ndarray, shape (height, width), uint8
    spec : CharucoSpec

    Returns
    -------
    CharucoResult
        Pixels in the coordinates of ``gray``, ordered by id.
    """
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
    # The window must stay off the markers, which begin (square - marker) / 2 from the
    # corner's edges; measured: window at 0.9 of that gap 0.08 px RMS, at half the square
    # (the chessboard choice) 0.45 px.
    gap_fraction = (spec.square_mm - spec.marker_mm) / (2.0 * spec.square_mm)
    fraction = min(SUBPIX_WINDOW_FRACTION, MARKER_GAP_WINDOW_FRACTION * gap_fraction)
    halfwindows = _spacing_halfwindow(ids, pixels, spec.cols, fraction)
    refined = np.empty_like(pixels)
    for window in np.unique(halfwindows):
        chosen = halfwindows == window
        refined[chosen] = refine_corners(gray, pixels[chosen], int(window))
    return CharucoResult(ids, refined, n_markers, None)
