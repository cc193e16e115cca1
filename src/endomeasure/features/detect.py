"""Target detection in both halves of one split image.

``detect_split_image`` crops the image at the split column, detects the board in each
half separately, maps the corners back to full-image pixels and measures each half's
quality. The crop of the right half starts at column ``split``, so a corner at crop
column ``x`` is at full-image ``u = x + split``: an integer shift that keeps the
pixel-centre rule (pixel centres on integers) intact.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError
from endomeasure.features.boards import BoardSpec, ChessboardSpec, parse_board_spec
from endomeasure.features.quality import HalfQuality, edge_width_px, half_quality
from endomeasure.features.split import to_gray_float

__all__ = ["HalfDetection", "ImageDetection", "detect_split_image", "to_gray_u8"]

# A half darker than this mean grey level is too dark to show a board (the detectors'
# adaptive thresholds break down in the quantisation noise of the lowest levels).
TOO_DARK_LEVEL = 15.0
# A half whose grey levels spread less than this has no usable contrast.
MIN_CONTRAST = 20.0
# Narrowest half the detectors are given, px.
MIN_HALF_WIDTH = 16
# Edge profiles reach this fraction of the corner spacing (chessboard squares are uniform
# up to the next grid line).
CHESSBOARD_PROFILE_REACH = 0.4
# The smallest grid searched for when diagnosing a failed chessboard half.
DIAGNOSIS_GRID = (3, 3)
# A diagnosed grid this many corner spacings clear of the half's border is a whole board:
# one more row or column of corners would have fitted, so none is hidden.
DIAGNOSIS_WHOLE_BOARD_CLEARANCE = 1.0


@dataclasses.dataclass(frozen=True)
class HalfDetection:
    """The board's corners found in one half.

    Attributes
    ----------
    half : Half
    ids : ndarray, shape (n,), int64
        Corner ids (``row * cols + col`` on the board), increasing.
    pixels : ndarray, shape (n, 2), px
        Full-image pixel coordinates.
    quality : HalfQuality
    failure : str or None
        Why the half has no corners; None when it has.
    covariance : ndarray, shape (n, 2, 2), px^2, or None
        Each corner's formal covariance from the image noise (the symmetric refinement's,
        :mod:`endomeasure.features.precision`; NaN where it did not converge); None for
        refinements without one.
    """

    half: Half
    ids: np.ndarray
    pixels: np.ndarray
    quality: HalfQuality
    failure: str | None = None
    covariance: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.failure is None


@dataclasses.dataclass(frozen=True)
class ImageDetection:
    """Detections in both halves of one image.

    Attributes
    ----------
    board : str
        Canonical board spec.
    split : int
        First column of the right half.
    image_size : (width, height), px
    halves : tuple of HalfDetection
        Left, then right.
    """

    board: str
    split: int
    image_size: tuple[int, int]
    halves: tuple[HalfDetection, HalfDetection]

    @property
    def left(self) -> HalfDetection:
        return self.halves[Half.LEFT]

    @property
    def right(self) -> HalfDetection:
        return self.halves[Half.RIGHT]

    @property
    def n_ok(self) -> int:
        """Halves with corners."""
        return sum(h.ok for h in self.halves)


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Grey uint8 image (what the OpenCV detectors take) from any supported image.

    Parameters
    ----------
    image : ndarray, shape (height, width[, channels]), uint8, uint16 or float 0..255
    """
    if image.dtype == np.uint8 and image.ndim == 2:
        return np.ascontiguousarray(image)
    gray = to_gray_float(image)
    return np.clip(np.round(gray), 0, 255).astype(np.uint8)


def _diagnose_chessboard(gray: np.ndarray, spec: ChessboardSpec) -> str:
    """Why no full chessboard was found: a partial view, another board, or none at all.

    Runs the sector-based detector for the largest grid of at least 3x3 corners
    (``CALIB_CB_LARGER``). A grid well inside the half is a whole board of another size;
    a grid touching the border is a partial view.
    """
    import cv2

    from endomeasure.features.chessboard import trim_false_lines

    found, corners, meta = cv2.findChessboardCornersSBWithMeta(
        gray, DIAGNOSIS_GRID, cv2.CALIB_CB_LARGER
    )
    if not found or meta is None or corners is None:
        return "no chessboard found"
    grid = trim_false_lines(gray, corners.reshape(meta.shape[0], meta.shape[1], 2))
    corners = grid.reshape(-1, 2)
    small, large = sorted(grid.shape[:2])
    a, b = (large, small) if spec.cols >= spec.rows else (small, large)
    if (small, large) == tuple(sorted((spec.cols, spec.rows))):
        return "a board of the spec's size is visible but its corners could not be ordered"
    spacing = np.median(np.linalg.norm(np.diff(corners, axis=0), axis=1))
    height, width = gray.shape
    clearance = min(
        corners[:, 0].min(),
        corners[:, 1].min(),
        width - 1 - corners[:, 0].max(),
        height - 1 - corners[:, 1].max(),
    )
    if clearance > DIAGNOSIS_WHOLE_BOARD_CLEARANCE * spacing:
        return (
            f"the board does not match the spec: a whole board of {a}x{b} inner corners is "
            f"visible, the spec {spec.canonical()} has {spec.cols}x{spec.rows}"
        )
    return f"partial board: only {a}x{b} of the {spec.cols}x{spec.rows} inner corners are visible"


def _detect_half(
    gray: np.ndarray, spec: BoardSpec, half: Half, offset: int, method: str | None
) -> HalfDetection:
    empty_ids, empty_pixels = np.empty((0,), dtype=np.int64), np.empty((0, 2))
    height, width = gray.shape
    if width < MIN_HALF_WIDTH:
        quality = HalfQuality(float("nan"), float("nan"), float("nan"))
        return HalfDetection(half, empty_ids, empty_pixels, quality, f"half only {width} px wide")
    quality = half_quality(gray)
    # Darkness and contrast only explain a failure; they never pre-empt a detection (a
    # small board on a dark background gives a dark mean but is perfectly detectable).
    if quality.brightness < TOO_DARK_LEVEL and quality.contrast < MIN_CONTRAST:
        failure = f"too dark (mean grey level {quality.brightness:.0f} of 255)"
        return HalfDetection(half, empty_ids, empty_pixels, quality, failure)
    if quality.contrast < MIN_CONTRAST:
        return HalfDetection(
            half,
            empty_ids,
            empty_pixels,
            quality,
            f"no contrast (grey levels spread over {quality.contrast:.0f} of 255)",
        )
    if isinstance(spec, ChessboardSpec):
        from endomeasure.features.chessboard import (
            DEFAULT_CHESSBOARD_METHOD,
            NOT_FOUND,
            detect_chessboard,
        )

        result = detect_chessboard(gray, spec, method or DEFAULT_CHESSBOARD_METHOD)
        if not result.ok:
            reason = result.failure
            if reason == NOT_FOUND:
                reason = _diagnose_chessboard(gray, spec)
            return HalfDetection(half, empty_ids, empty_pixels, quality, reason)
        ids = np.arange(spec.n_corners, dtype=np.int64)
        pixels = result.pixels
        reach = CHESSBOARD_PROFILE_REACH
    else:
        from endomeasure.features.charuco import detect_charuco

        result = detect_charuco(gray, spec)
        if not result.ok:
            return HalfDetection(half, empty_ids, empty_pixels, quality, result.failure)
        ids, pixels = result.ids, result.pixels
        # Profiles must end before the markers in the white squares.
        reach = 0.9 * (spec.square_mm - spec.marker_mm) / (2.0 * spec.square_mm)
    width_px = edge_width_px(gray.astype(np.float64), ids, pixels, spec.cols, reach)
    quality = dataclasses.replace(quality, edge_width_px=width_px)
    full = pixels + np.array([offset, 0.0])
    return HalfDetection(half, ids, full, quality, None, result.covariance)


def detect_split_image(
    image: np.ndarray, board: str | BoardSpec, split: int, *, method: str | None = None
) -> ImageDetection:
    """Detect a board's corners in both halves of a split image.

    Parameters
    ----------
    image : ndarray, shape (height, width[, channels])
        uint8, uint16 or float (0..255); colour in OpenCV's BGR order.
    board : str or BoardSpec
    split : int
        First column of the right half.
    method : str, optional
        Chessboard method (see :data:`endomeasure.features.chessboard.CHESSBOARD_METHODS`);
        the measured best by default. Ignored for ChArUco boards.

    Returns
    -------
    ImageDetection
        Per half: ids, full-image pixels, quality, or the reason for failure. A failed
        half is a result, not an exception.

    Raises
    ------
    BadInputError
        The split lies outside the image.
    """
    spec = parse_board_spec(board)
    gray = to_gray_u8(np.asarray(image))
    height, width = gray.shape
    if not 0 < split < width:
        raise BadInputError(
            f"split column {split} is outside the image (width {width} px)",
            hint="give a column between 1 and the image width minus 1, or --split auto",
        )
    left = _detect_half(np.ascontiguousarray(gray[:, :split]), spec, Half.LEFT, 0, method)
    right = _detect_half(np.ascontiguousarray(gray[:, split:]), spec, Half.RIGHT, split, method)
    return ImageDetection(
        board=spec.canonical(), split=int(split), image_size=(width, height), halves=(left, right)
    )
