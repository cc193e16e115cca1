"""Board-test evaluation: measurement errors on images of a known chessboard.

The paper's Section 3 (its Fig. 4): for every test image of a flat board with known
square size, triangulate every inner corner and measure, against the board's true
geometry,

``x-segment``
    the distance between neighbouring corners ``(r, c)`` and ``(r, c+1)``; true value
    the square size;
``y-segment``
    the same between ``(r, c)`` and ``(r+1, c)``;
``point-plane``
    the signed distance (kind ``depth``, positive towards the probe) of corner
    ``(r, c)`` to the plane through the other three corners of its square,
    ``(r, c+s)``, ``(r+s, c+s)``, ``(r+s, c)``, with ``s = span`` (1 by default, i.e.
    the square's own corners, as in the paper's Fig. 3a); true value 0;
``area``
    the area of the square ``(r, c), (r, c+1), (r+1, c+1), (r+1, c)`` as the sum of
    the two triangles from ``(r, c)`` (kind ``area``); true value the square size
    squared;

then group the errors by distance zone (the mean z of the points involved) and report
the mean error and its standard deviation per zone, kind and model.

Everything here is plain numpy on already triangulated points; it does not know about
models, files or plots (see :mod:`endomeasure.measure.plots`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from endomeasure import defaults
from endomeasure.errors import BadInputError
from endomeasure.measure.kinds import evaluate

__all__ = [
    "BOARD_KINDS",
    "checked_zone_mm",
    "zone_bounds",
    "zone_index",
    "BoardImage",
    "BoardStencils",
    "BoardTestTable",
    "ZoneSummary",
    "board_stencils",
    "board_test_table",
    "stencil_pixels",
    "zone_groups",
    "zone_summary",
]

BOARD_KINDS: dict[str, str] = {
    "x-segment": "length",
    "y-segment": "length",
    "point-plane": "depth",
    "area": "area",
}
"""Board-test measurement -> the measurement kind (:mod:`~endomeasure.measure.kinds`) that
computes it, so predictions of its uncertainty use the very same function."""

_MAX_CORNERS = 4  # widest stencil (point-plane, area); narrower ones are padded with -1


class BoardImage(NamedTuple):
    """The triangulated corners of one test image.

    Attributes
    ----------
    ids : ndarray, shape (N,), int
        Corner ids ``row * cols + col``.
    points : ndarray, shape (N, 3), mm
        Triangulated corners in the model frame (NaN where triangulation failed).
    pixels_left, pixels_right : ndarray, shape (N, 2), px, optional
        The detected corners in each half (for plots and uncertainty predictions).
    """

    ids: np.ndarray
    points: np.ndarray
    pixels_left: np.ndarray | None = None
    pixels_right: np.ndarray | None = None


class BoardStencils(NamedTuple):
    """The corner tuples measured on a full board."""

    kind: np.ndarray  # (M,) str, one of BOARD_KINDS
    corners: np.ndarray  # (M, 4) int corner ids in measurement order, -1 padded
    true: np.ndarray  # (M,) mm or mm^2


class BoardTestTable(NamedTuple):
    """One row per measurement on one model's triangulated test images."""

    image: np.ndarray  # (M,) int, index of the image in the input sequence
    kind: np.ndarray  # (M,) str, one of BOARD_KINDS
    corners: np.ndarray  # (M, 4) int corner ids in measurement order, -1 padded
    true: np.ndarray  # (M,) true value, mm (mm^2 for area)
    measured: np.ndarray  # (M,) measured value
    error: np.ndarray  # (M,) measured - true
    z_mean: np.ndarray  # (M,) mm, mean z of the corners involved
    pixel_mean: np.ndarray  # (M, 2) px, mean left-half pixel of the corners (NaN if unknown)

    def select(self, mask: np.ndarray) -> BoardTestTable:
        """The rows where ``mask`` is True."""
        return BoardTestTable(*(a[mask] for a in self))

    def as_records(self) -> list[dict[str, Any]]:
        """The rows as JSON-ready dicts (corner ids without padding)."""
        out = []
        for i in range(self.image.shape[0]):
            out.append(
                {
                    "image": int(self.image[i]),
                    "kind": str(self.kind[i]),
                    "corners": [int(c) for c in self.corners[i] if c >= 0],
                    "true": float(self.true[i]),
                    "measured": float(self.measured[i]),
                    "error": float(self.error[i]),
                    "z_mean": float(self.z_mean[i]),
                    "pixel_mean": [float(v) for v in self.pixel_mean[i]],
                }
            )
        return out


def _check_board(cols: int, rows: int, square_mm: float, span: int) -> None:
    if cols < 2 or rows < 2:
        raise BadInputError(
            f"a board test needs at least 2x2 inner corners, got {cols}x{rows}",
            hint="use a chessboard with more squares",
        )
    if not (np.isfinite(square_mm) and square_mm > 0):
        raise BadInputError(f"the square size must be a positive number of mm, got {square_mm}")
    if not (1 <= span < min(cols, rows)):
        raise BadInputError(
            f"the point-plane span must be between 1 and {min(cols, rows) - 1} squares, got {span}"
        )


def board_stencils(cols: int, rows: int, square_mm: float, span: int = 1) -> BoardStencils:
    """All measurements of a full ``cols`` x ``rows`` inner-corner grid.

    Parameters
    ----------
    cols, rows : int
        Inner corners per row and per column.
    square_mm : float, mm
    span : int
        Squares between the point and its plane corners in ``point-plane``.

    Returns
    -------
    BoardStencils
        Ordered by kind (as in :data:`BOARD_KINDS`), then row, then column.
    """
    _check_board(cols, rows, square_mm, span)
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    r, c = r.ravel(), c.ravel()

    def cid(rr, cc):
        return rr * cols + cc

    groups = []
    sel = c + 1 < cols
    groups.append(("x-segment", [cid(r[sel], c[sel]), cid(r[sel], c[sel] + 1)], square_mm))
    sel = r + 1 < rows
    groups.append(("y-segment", [cid(r[sel], c[sel]), cid(r[sel] + 1, c[sel])], square_mm))
    s = span
    sel = (r + s < rows) & (c + s < cols)
    rr, cc = r[sel], c[sel]
    groups.append(
        ("point-plane", [cid(rr, cc + s), cid(rr + s, cc + s), cid(rr + s, cc), cid(rr, cc)], 0.0)
    )
    sel = (r + 1 < rows) & (c + 1 < cols)
    rr, cc = r[sel], c[sel]
    groups.append(
        ("area", [cid(rr, cc), cid(rr, cc + 1), cid(rr + 1, cc + 1), cid(rr + 1, cc)], square_mm**2)
    )
    kinds, corners, true = [], [], []
    for kind, ids, value in groups:
        block = np.full((ids[0].size, _MAX_CORNERS), -1, dtype=np.int64)
        block[:, : len(ids)] = np.stack(ids, axis=-1)
        kinds.append(np.full(ids[0].size, kind, dtype=object))
        corners.append(block)
        true.append(np.full(ids[0].size, float(value)))
    return BoardStencils(
        np.concatenate(kinds).astype(str), np.concatenate(corners), np.concatenate(true)
    )


def _lookup(n_corners: int, image: BoardImage) -> np.ndarray:
    """Row of each corner id in ``image`` (-1 if absent), shape (n_corners,)."""
    ids = np.asarray(image.ids, dtype=np.int64).reshape(-1)
    if ids.size and (ids.min() < 0 or ids.max() >= n_corners):
        raise BadInputError(
            f"corner ids must lie in 0..{n_corners - 1} for this board, got "
            f"{ids.min()}..{ids.max()}",
            hint="check that the board spec matches the detections",
        )
    if np.unique(ids).size != ids.size:
        raise BadInputError("a corner id occurs twice in one image")
    row = np.full(n_corners, -1, dtype=np.int64)
    row[ids] = np.arange(ids.size)
    return row


def board_test_table(
    cols: int,
    rows: int,
    square_mm: float,
    images: Sequence[BoardImage],
    *,
    span: int = 1,
) -> BoardTestTable:
    """Measure every board-test stencil on every image whose corners are all triangulated.

    Parameters
    ----------
    cols, rows : int
        Inner corners of the board.
    square_mm : float, mm
    images : sequence of BoardImage
    span : int
        See :func:`board_stencils`.

    Returns
    -------
    BoardTestTable
        Stencils with a missing or non-finite corner are left out.
    """
    st = board_stencils(cols, rows, square_mm, span)
    n_corners = cols * rows
    parts: list[BoardTestTable] = []
    for index, image in enumerate(images):
        pts = np.asarray(image.points, dtype=np.float64).reshape(-1, 3)
        if pts.shape[0] != np.size(image.ids):
            raise BadInputError(
                f"image {index}: {np.size(image.ids)} corner ids but {pts.shape[0]} points"
            )
        row = _lookup(n_corners, image)
        finite = np.all(np.isfinite(pts), axis=1)
        usable = np.zeros(n_corners, dtype=bool)
        usable[np.asarray(image.ids, dtype=np.int64)] = finite
        pix = (
            np.full((pts.shape[0], 2), np.nan)
            if image.pixels_left is None
            else np.asarray(image.pixels_left, dtype=np.float64).reshape(-1, 2)
        )
        for kind, measure_kind in BOARD_KINDS.items():
            sel = st.kind == kind
            corners = st.corners[sel]
            n_used = int(np.sum(corners[0] >= 0)) if corners.size else 0
            ids = corners[:, :n_used]
            ok = np.all(usable[ids], axis=1)
            if not ok.any():
                continue
            ids = ids[ok]
            p = pts[row[ids]]  # (m, n_used, 3)
            measured = evaluate(measure_kind, p)
            true = st.true[sel][ok]
            parts.append(
                BoardTestTable(
                    np.full(ids.shape[0], index, dtype=np.int64),
                    np.full(ids.shape[0], kind).astype(str),
                    corners[ok],
                    true,
                    measured,
                    measured - true,
                    p[..., 2].mean(axis=1),
                    pix[row[ids]].mean(axis=1),
                )
            )
    if not parts:
        return BoardTestTable(
            np.zeros(0, dtype=np.int64), np.zeros(0, dtype=str), np.zeros((0, _MAX_CORNERS), int),
            *(np.zeros(0) for _ in range(4)), np.zeros((0, 2)),
        )  # fmt: skip
    return BoardTestTable(*(np.concatenate(cols_) for cols_ in zip(*parts, strict=True)))


def stencil_pixels(
    table: BoardTestTable, images: Sequence[BoardImage], kind: str
) -> tuple[np.ndarray, np.ndarray]:
    """The detected pixels of the corners of every ``kind`` row of ``table``.

    Parameters
    ----------
    table : BoardTestTable
    images : sequence of BoardImage
        The images the table was made from, with ``pixels_left`` and ``pixels_right``.
    kind : str
        One of :data:`BOARD_KINDS`.

    Returns
    -------
    pixels_left, pixels_right : ndarray, shape (M, n, 2), px
        In measurement order, for the M rows of that kind (in table order), ready for
        :func:`endomeasure.measure.predict.predict_measurement_error` with kind
        ``BOARD_KINDS[kind]``.
    """
    rows = np.flatnonzero(table.kind == kind)
    if rows.size == 0:
        return np.zeros((0, 0, 2)), np.zeros((0, 0, 2))
    n = int(np.sum(table.corners[rows[0]] >= 0))
    left = np.full((rows.size, n, 2), np.nan)
    right = np.full((rows.size, n, 2), np.nan)
    for index in np.unique(table.image[rows]):
        image = images[index]
        if image.pixels_left is None or image.pixels_right is None:
            raise BadInputError(f"image {index} has no pixels for an uncertainty prediction")
        # ids beyond the table's own are harmless here: size the lookup to cover both
        n_ids = int(max(np.max(image.ids, initial=-1), np.max(table.corners))) + 1
        lookup = _lookup(n_ids, image)
        sel = np.flatnonzero(table.image[rows] == index)
        at = lookup[table.corners[rows[sel], :n]]
        if np.any(at < 0):
            raise BadInputError(f"image {index} lacks pixels of corners the table measures")
        left[sel] = np.asarray(image.pixels_left, dtype=np.float64)[at]
        right[sel] = np.asarray(image.pixels_right, dtype=np.float64)[at]
    return left, right


class ZoneSummary(NamedTuple):
    """Mean error and standard deviation per (model, kind, zone); one row each."""

    model: np.ndarray  # (K,) str
    kind: np.ndarray  # (K,) str
    zone_start: np.ndarray  # (K,) mm, zone = [start, start + width)
    zone_end: np.ndarray  # (K,) mm
    n: np.ndarray  # (K,) int, measurements in the zone
    mean_error: np.ndarray  # (K,) mm or mm^2
    std_error: np.ndarray  # (K,) sample standard deviation (ddof=1); NaN if n < 2
    true: np.ndarray  # (K,) the kind's true value (for relative errors)

    def as_records(self) -> list[dict[str, Any]]:
        keys = self._fields
        return [
            {
                k: (
                    str(getattr(self, k)[i])
                    if k in ("model", "kind")
                    else int(getattr(self, k)[i])
                    if k == "n"
                    else float(getattr(self, k)[i])
                )
                for k in keys
            }
            for i in range(self.model.shape[0])
        ]


def zone_index(z: np.ndarray | float, zone_mm: float) -> np.ndarray:
    """The distance zone ``k`` of each depth ``z`` (mm): zones are ``[k w, (k+1) w)`` for
    integers k, aligned to multiples of the width ``w = zone_mm`` so that they agree
    between models and runs (:func:`zone_bounds`)."""
    return np.floor(np.asarray(z, dtype=np.float64) / zone_mm)


def checked_zone_mm(zone_mm: float) -> float:
    """A zone width, checked: a positive finite number of mm (BadInputError if not)."""
    zone_mm = float(zone_mm)
    if not (np.isfinite(zone_mm) and zone_mm > 0):
        raise BadInputError(f"the zone width must be a positive number of mm, not {zone_mm}")
    if zone_mm < defaults.MIN_ZONE_MM:
        raise BadInputError(
            f"the zone width {zone_mm:g} mm is below {defaults.MIN_ZONE_MM:g} mm: the test "
            "images are about 1 mm apart, so such zones hold one image or none",
            hint="give --zone-mm of 1 mm or more",
        )
    return zone_mm


def zone_bounds(k, zone_mm: float) -> tuple[float, float]:
    """``(start, end)`` of distance zone ``k`` (:func:`zone_index`), mm."""
    return float(k * zone_mm), float((k + 1) * zone_mm)


def zone_groups(table: BoardTestTable, zone_mm: float, valid: np.ndarray):
    """The rows of each (kind, distance zone) of a table, in summary order.

    Zones of the rows' mean z (:func:`zone_index`). Yields ``(kind, k, rows)`` with ``k``
    the zone, ``rows`` a boolean mask within ``valid``, kinds as in :data:`BOARD_KINDS`,
    zones ascending.
    """
    zone = zone_index(table.z_mean, zone_mm)
    for kind in BOARD_KINDS:
        sel = valid & (table.kind == kind)
        for k in np.unique(zone[sel]):
            yield kind, k, sel & (zone == k)


def zone_summary(
    tables: Mapping[str, BoardTestTable], zone_mm: float = defaults.ZONE_MM
) -> ZoneSummary:
    """Group board-test errors by distance zone, kind and model.

    Parameters
    ----------
    tables : mapping of model name -> BoardTestTable
    zone_mm : float, mm
        Zone width along z (:func:`zone_groups`).

    Returns
    -------
    ZoneSummary
        Rows ordered by model (as given), kind (as in :data:`BOARD_KINDS`), zone.
    """
    zone_mm = checked_zone_mm(zone_mm)
    cols: dict[str, list] = {k: [] for k in ZoneSummary._fields}
    for model, table in tables.items():
        valid = np.isfinite(table.error) & np.isfinite(table.z_mean)
        for kind, k, rows in zone_groups(table, zone_mm, valid):
            e = table.error[rows]
            cols["model"].append(model)
            cols["kind"].append(kind)
            start, end = zone_bounds(k, zone_mm)
            cols["zone_start"].append(start)
            cols["zone_end"].append(end)
            cols["n"].append(e.size)
            cols["mean_error"].append(float(np.mean(e)))
            cols["std_error"].append(float(np.std(e, ddof=1)) if e.size > 1 else np.nan)
            cols["true"].append(float(table.true[rows][0]))
    return ZoneSummary(
        np.array(cols["model"], dtype=str),
        np.array(cols["kind"], dtype=str),
        np.array(cols["zone_start"], dtype=float),
        np.array(cols["zone_end"], dtype=float),
        np.array(cols["n"], dtype=np.int64),
        np.array(cols["mean_error"], dtype=float),
        np.array(cols["std_error"], dtype=float),
        np.array(cols["true"], dtype=float),
    )
