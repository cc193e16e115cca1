"""Target detection in both halves of one split image.

``detect_split_image`` crops the image at the split column, detects the board in each
half separately, maps the corners back to full-image pixels and measures each half's
quality. The crop of the right half starts at column ``split``, so a corner at crop
column ``x`` is at full-image ``u = x + split``: an integer shift that keeps the
pixel-centre rule (pixel centres on integers) intact.

Where a chessboard's colouring leaves its ids open by a half or quarter turn (8x6, 7x7,
8x8 boards), the two halves are made to agree here (:func:`agree_halves`): both halves
see the board from two nearby virtual cameras through the prism, so its in-plane angle
is nearly the same in both, and the ids of the half the colouring fixes less (the right
half on a tie) are turned to the symmetry element whose grid direction is nearest the
other half's. ChArUco ids are the board's own.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError
from endomeasure.features.boards import BoardSpec, ChessboardSpec, parse_board_spec
from endomeasure.features.quality import HalfQuality, edge_width_px, half_quality
from endomeasure.features.split import to_gray_float

__all__ = [
    "HalfDetection",
    "ImageDetection",
    "agree_halves",
    "detect_split_image",
    "match_turn",
    "to_gray_u8",
]

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
# Two halves' grid directions may differ by at most this fraction of the angle between two
# equally valid id assignments (360 degrees / their number): halfway to where the choice
# would flip. The prism's two views of one board differ by a few degrees of roll.
MAX_HALF_DISAGREEMENT_FRACTION = 0.25


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


def match_turn(reference_deg: float, angle_deg: float, turns: tuple[int, ...]) -> tuple[int, float]:
    """The quarter turn of a grid that brings its direction nearest a reference direction.

    Parameters
    ----------
    reference_deg, angle_deg : float, degrees
        Column directions (from +u towards +v) of the reference grid and of this one.
    turns : tuple of int
        The quarter turns allowed (:attr:`ChessboardResult.turns`).

    Returns
    -------
    turn : int
        The allowed ``k`` minimising ``|angle + 90 k - reference|`` (modulo 360).
    disagreement_deg : float, degrees
        That remaining angle, in [0, 180].
    """
    best, best_gap = turns[0], np.inf
    for k in turns:
        gap = abs((angle_deg + 90.0 * k - reference_deg + 180.0) % 360.0 - 180.0)
        if gap < best_gap:
            best, best_gap = k, gap
    return int(best), float(best_gap)


def agree_halves(left, right, cols: int, rows: int) -> tuple:
    """Make the chessboard ids of the two halves of one frame name the same corners.

    Parameters
    ----------
    left, right : ChessboardResult
        Per-half detections (:func:`endomeasure.features.chessboard.detect_chessboard`).
    cols, rows : int
        The board's inner corners.

    Returns
    -------
    left, right : ChessboardResult
        Unchanged when a half failed or when the colouring fixed both halves' ids and
        they agree. Otherwise the half whose ids are the less fixed (the right half on a
        tie) is turned by the allowed quarter turn nearest the other half's grid
        direction (:func:`match_turn`). A half whose direction stays more than
        :data:`MAX_HALF_DISAGREEMENT_FRACTION` of the symmetry angle away is refused
        with the reason: the two views cannot be of one board through the prism, or
        one half read the colours wrong.
    """
    from endomeasure.features.chessboard import ChessboardResult, turn_result

    if not (left.ok and right.ok):
        return left, right
    swap = len(left.turns) > len(right.turns)
    reference, other = (right, left) if swap else (left, right)
    names = ("right", "left") if swap else ("left", "right")
    k, gap = match_turn(reference.angle_deg, other.angle_deg, other.turns)
    repeat = 360.0 / len(other.turns)
    limit = MAX_HALF_DISAGREEMENT_FRACTION * repeat
    if gap > limit:
        if len(other.turns) == 1:
            reason = (
                f"the squares' colours put corner 0 of the board {gap:.0f} degrees away from "
                f"where the {names[0]} half has it: one half misread them, so its ids cannot "
                "be made consistent"
            )
        else:
            reason = (
                f"board turned {gap:.0f} degrees from its view in the {names[0]} half: corner "
                f"ids cannot be made consistent (the board repeats every {repeat:.0f} degrees; "
                f"the halves must agree within {limit:.0f})"
            )
        other = ChessboardResult(np.empty((0, 2)), failure=reason)
    else:
        other = turn_result(other, cols, rows, k)
    return (other, reference) if swap else (reference, other)


def _find_in_half(gray: np.ndarray, spec: BoardSpec, method: str | None):
    """The half's quality and detection result, or a failure reason found before detection."""
    height, width = gray.shape
    if width < MIN_HALF_WIDTH:
        quality = HalfQuality(float("nan"), float("nan"), float("nan"))
        return quality, None, f"half only {width} px wide"
    quality = half_quality(gray)
    # Darkness and contrast only explain a failure; they never pre-empt a detection (a
    # small board on a dark background gives a dark mean but is perfectly detectable).
    if quality.brightness < TOO_DARK_LEVEL and quality.contrast < MIN_CONTRAST:
        return quality, None, f"too dark (mean grey level {quality.brightness:.0f} of 255)"
    if quality.contrast < MIN_CONTRAST:
        return (
            quality,
            None,
            f"no contrast (grey levels spread over {quality.contrast:.0f} of 255)",
        )
    if isinstance(spec, ChessboardSpec):
        from endomeasure.features.chessboard import DEFAULT_CHESSBOARD_METHOD, detect_chessboard

        return quality, detect_chessboard(gray, spec, method or DEFAULT_CHESSBOARD_METHOD), None
    from endomeasure.features.charuco import detect_charuco

    return quality, detect_charuco(gray, spec), None


def _half_detection(
    gray: np.ndarray, spec: BoardSpec, half: Half, offset: int, quality, result, failure
) -> HalfDetection:
    empty_ids, empty_pixels = np.empty((0,), dtype=np.int64), np.empty((0, 2))
    if result is None:
        return HalfDetection(half, empty_ids, empty_pixels, quality, failure)
    if not result.ok:
        reason = result.failure
        if isinstance(spec, ChessboardSpec):
            from endomeasure.features.chessboard import NOT_FOUND

            if reason == NOT_FOUND:
                reason = _diagnose_chessboard(gray, spec)
        return HalfDetection(half, empty_ids, empty_pixels, quality, reason)
    if isinstance(spec, ChessboardSpec):
        ids = np.arange(spec.n_corners, dtype=np.int64)
        reach = CHESSBOARD_PROFILE_REACH
    else:
        ids = result.ids
        # Profiles must end before the markers in the white squares.
        reach = 0.9 * (spec.square_mm - spec.marker_mm) / (2.0 * spec.square_mm)
    pixels = result.pixels
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
        half is a result, not an exception. Chessboard ids agree between the halves
        (:func:`agree_halves`).

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
    crops = (np.ascontiguousarray(gray[:, :split]), np.ascontiguousarray(gray[:, split:]))
    found = [_find_in_half(crop, spec, method) for crop in crops]
    if isinstance(spec, ChessboardSpec) and found[0][1] is not None and found[1][1] is not None:
        results = agree_halves(found[0][1], found[1][1], spec.cols, spec.rows)
        found = [(q, r, f) for (q, _, f), r in zip(found, results, strict=True)]
    left, right = (
        _half_detection(crop, spec, half, offset, *parts)
        for crop, half, offset, parts in zip(
            crops, (Half.LEFT, Half.RIGHT), (0, split), found, strict=True
        )
    )
    return ImageDetection(
        board=spec.canonical(), split=int(split), image_size=(width, height), halves=(left, right)
    )
