"""Calibration-target descriptions: parsing board specs into board-frame geometry.

Two kinds of flat target are supported, each written as one colon-separated string on
the command line and stored in that canonical form in the session:

``chessboard:COLSxROWS:SQUARE_MM``
    A plain chessboard with ``COLS`` x ``ROWS`` *inner* corners and squares of
    ``SQUARE_MM`` millimetres, e.g. ``chessboard:9x6:1.0``.
``charuco:SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT``
    An OpenCV ChArUco board of ``SQUARES_X`` x ``SQUARES_Y`` squares with ArUco markers
    of ``MARKER_MM`` in the white squares, from the predefined dictionary ``DICT``,
    e.g. ``charuco:12x9:1.0:0.7:DICT_4X4_100``. Its inner corners are
    ``(SQUARES_X - 1) x (SQUARES_Y - 1)``; their ids are the board's own ids.

Board frame (both kinds): corners on z = 0, corner id ``row * cols + col``, corner
``(col, row)`` at ``(col * square, row * square, 0)`` mm, so id 0 is the origin, board
+x runs along the columns and +y along the rows.
"""

from __future__ import annotations

import dataclasses
import re
from functools import cached_property

import numpy as np

from endomeasure.errors import BadInputError

__all__ = [
    "BoardSpec",
    "CharucoSpec",
    "ChessboardSpec",
    "CHARUCO_DICTIONARIES",
    "parse_board_spec",
]

CHESSBOARD_EXAMPLE = "chessboard:9x6:1.0"
CHARUCO_EXAMPLE = "charuco:12x9:1.0:0.7:DICT_4X4_100"

# The predefined ArUco dictionaries by name; each maps to the attribute of cv2.aruco with
# that name. Listed here (not looked up in cv2) so that parsing a spec needs no cv2 import.
CHARUCO_DICTIONARIES = tuple(
    f"DICT_{bits}X{bits}_{count}" for bits in (4, 5, 6, 7) for count in (50, 100, 250, 1000)
) + ("DICT_ARUCO_ORIGINAL",)

# Smallest grid whose orientation and extent a detector can fix.
MIN_INNER_CORNERS = 2


def _board_points(cols: int, rows: int, square_mm: float) -> np.ndarray:
    """Board-frame corner coordinates, shape (rows * cols, 3), mm, in id order."""
    row, col = np.divmod(np.arange(rows * cols), cols)
    return np.stack([col * square_mm, row * square_mm, np.zeros(rows * cols)], axis=-1)


@dataclasses.dataclass(frozen=True)
class ChessboardSpec:
    """A plain chessboard with ``cols`` x ``rows`` inner corners.

    Attributes
    ----------
    cols, rows : int
        Inner corners per row and per column (OpenCV's ``patternSize = (cols, rows)``).
    square_mm : float, mm
        Side of one square.
    """

    cols: int
    rows: int
    square_mm: float

    kind = "chessboard"

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's ``patternSize``: ``(cols, rows)`` inner corners."""
        return (self.cols, self.rows)

    @cached_property
    def object_points(self) -> np.ndarray:
        """Board-frame corners, ndarray shape (n_corners, 3), mm; row i is corner id i."""
        points = _board_points(self.cols, self.rows, self.square_mm)
        points.setflags(write=False)
        return points

    def canonical(self) -> str:
        """The spec as a canonical string, e.g. ``chessboard:9x6:1``."""
        return f"chessboard:{self.cols}x{self.rows}:{self.square_mm:g}"

    def __str__(self) -> str:
        return self.canonical()


@dataclasses.dataclass(frozen=True)
class CharucoSpec:
    """An OpenCV ChArUco board of ``squares_x`` x ``squares_y`` squares.

    Attributes
    ----------
    squares_x, squares_y : int
        Squares along the board's x (columns) and y (rows).
    square_mm, marker_mm : float, mm
        Side of one square and of one ArUco marker (``marker_mm < square_mm``).
    dictionary : str
        Name of a predefined ArUco dictionary, one of :data:`CHARUCO_DICTIONARIES`.
    """

    squares_x: int
    squares_y: int
    square_mm: float
    marker_mm: float
    dictionary: str

    kind = "charuco"

    @property
    def cols(self) -> int:
        """Inner corners per row."""
        return self.squares_x - 1

    @property
    def rows(self) -> int:
        """Inner corners per column."""
        return self.squares_y - 1

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def n_markers(self) -> int:
        """Markers on the board: one in every white square."""
        return (self.squares_x * self.squares_y) // 2

    @cached_property
    def object_points(self) -> np.ndarray:
        """Board-frame inner corners, ndarray shape (n_corners, 3), mm; row i is id i.

        OpenCV numbers ChArUco corners the same way (row-major, x fastest) but puts its
        origin at the board's outer corner; here the origin is inner corner 0.
        """
        points = _board_points(self.cols, self.rows, self.square_mm)
        points.setflags(write=False)
        return points

    def canonical(self) -> str:
        """The spec as a canonical string, e.g. ``charuco:12x9:1:0.7:DICT_4X4_100``."""
        return (
            f"charuco:{self.squares_x}x{self.squares_y}:{self.square_mm:g}:"
            f"{self.marker_mm:g}:{self.dictionary}"
        )

    def __str__(self) -> str:
        return self.canonical()


BoardSpec = ChessboardSpec | CharucoSpec

_SIZE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def _bad(spec: str, what: str, example: str) -> BadInputError:
    return BadInputError(
        f"bad board spec {spec!r}: {what}",
        hint=f"write it like {example!r}",
    )


def _parse_size(spec: str, text: str, label: str, example: str) -> tuple[int, int]:
    match = _SIZE.match(text)
    if match is None:
        raise _bad(spec, f"{label} must look like 9x6, not {text!r}", example)
    return int(match.group(1)), int(match.group(2))


def _parse_mm(spec: str, text: str, label: str, example: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise _bad(
            spec, f"{label} must be a number of millimetres, not {text!r}", example
        ) from None
    if not np.isfinite(value) or value <= 0.0:
        raise _bad(spec, f"{label} must be a positive number of millimetres, not {text!r}", example)
    return value


def _parse_dictionary(spec: str, text: str) -> str:
    name = text.strip().upper()
    if not name.startswith("DICT_"):
        name = "DICT_" + name
    if name not in CHARUCO_DICTIONARIES:
        raise _bad(
            spec,
            f"unknown ArUco dictionary {text!r} (known: DICT_4X4_50 ... DICT_7X7_1000, "
            "DICT_ARUCO_ORIGINAL)",
            CHARUCO_EXAMPLE,
        )
    return name


def parse_board_spec(spec: str | BoardSpec) -> BoardSpec:
    """Parse a board spec string into a :class:`ChessboardSpec` or :class:`CharucoSpec`.

    Parameters
    ----------
    spec : str
        ``chessboard:COLSxROWS:SQUARE_MM`` (inner corners) or
        ``charuco:SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT``. Case and spaces
        around the fields do not matter. A spec object is returned unchanged.

    Returns
    -------
    ChessboardSpec or CharucoSpec

    Raises
    ------
    BadInputError
        The spec is malformed; the message says which field and gives a correct example.
    """
    if isinstance(spec, (ChessboardSpec, CharucoSpec)):
        return spec
    if not isinstance(spec, str):
        raise _bad(str(spec), "a board spec is a string", CHESSBOARD_EXAMPLE)
    fields = [field.strip() for field in spec.split(":")]
    kind = fields[0].lower()
    if kind == "chessboard":
        if len(fields) != 3:
            raise _bad(
                spec,
                "a chessboard spec has 3 fields (chessboard:COLSxROWS:SQUARE_MM), "
                f"not {len(fields)}",
                CHESSBOARD_EXAMPLE,
            )
        cols, rows = _parse_size(
            spec, fields[1], "the inner-corner count COLSxROWS", CHESSBOARD_EXAMPLE
        )
        if cols < MIN_INNER_CORNERS or rows < MIN_INNER_CORNERS:
            raise _bad(
                spec,
                f"a chessboard needs at least {MIN_INNER_CORNERS}x{MIN_INNER_CORNERS} "
                "inner corners",
                CHESSBOARD_EXAMPLE,
            )
        square = _parse_mm(spec, fields[2], "SQUARE_MM", CHESSBOARD_EXAMPLE)
        return ChessboardSpec(cols=cols, rows=rows, square_mm=square)
    if kind == "charuco":
        if len(fields) != 5:
            raise _bad(
                spec,
                "a charuco spec has 5 fields "
                f"(charuco:SQUARES_XxSQUARES_Y:SQUARE_MM:MARKER_MM:DICT), not {len(fields)}",
                CHARUCO_EXAMPLE,
            )
        squares_x, squares_y = _parse_size(
            spec, fields[1], "the square count SQUARES_XxSQUARES_Y", CHARUCO_EXAMPLE
        )
        if squares_x < MIN_INNER_CORNERS + 1 or squares_y < MIN_INNER_CORNERS + 1:
            raise _bad(
                spec,
                f"a charuco board needs at least {MIN_INNER_CORNERS + 1}x"
                f"{MIN_INNER_CORNERS + 1} squares",
                CHARUCO_EXAMPLE,
            )
        square = _parse_mm(spec, fields[2], "SQUARE_MM", CHARUCO_EXAMPLE)
        marker = _parse_mm(spec, fields[3], "MARKER_MM", CHARUCO_EXAMPLE)
        if marker >= square:
            raise _bad(
                spec,
                f"the marker ({marker:g} mm) must be smaller than the square ({square:g} mm)",
                CHARUCO_EXAMPLE,
            )
        dictionary = _parse_dictionary(spec, fields[4])
        n_markers = (squares_x * squares_y) // 2
        capacity = (
            1024 if dictionary == "DICT_ARUCO_ORIGINAL" else int(dictionary.rsplit("_", 1)[1])
        )
        if n_markers > capacity:
            raise _bad(
                spec,
                f"the board has {n_markers} markers but {dictionary} holds only {capacity}",
                CHARUCO_EXAMPLE,
            )
        return CharucoSpec(
            squares_x=squares_x,
            squares_y=squares_y,
            square_mm=square,
            marker_mm=marker,
            dictionary=dictionary,
        )
    raise _bad(
        spec, f"unknown board kind {fields[0]!r} (chessboard or charuco)", CHESSBOARD_EXAMPLE
    )
