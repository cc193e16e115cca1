"""One model's board test over the test images of several boards, and its prediction.

:mod:`endomeasure.measure.board_test` measures one board's images from triangulated
corners. This module does the rest of the paper's Sections 3 and 4 for a camera model:
gather the test images of every known board (:func:`board_sets`), triangulate their
corners and assemble one table and a per-board zone summary (:func:`run_board_test`),
predict every measurement's bias and std (:func:`board_predictions`) and compare the
predictions with the actual errors per board, kind and zone (:func:`prediction_zones`).

How a zone's prediction is compared with the actual errors
-----------------------------------------------------------
Each measurement i of a zone has its own predicted bias ``b_i`` and std ``s_i`` (they
vary over the field). The actual errors of the zone are draws from the mixture of these
distributions, whose mean is ``mean(b_i)`` and whose standard deviation is
``sqrt(mean(s_i^2) + var(b_i))``: that is the predicted zone std compared with the
sample std of the actual errors. The band check asks for each error whether
``|e_i - b_i| <= BAND_SIGMAS s_i``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.errors import BadInputError
from endomeasure.measure.board_test import (
    BOARD_KINDS,
    BoardImage,
    BoardTestTable,
    ZoneSummary,
    board_test_table,
    stencil_pixels,
    zone_bounds,
    zone_groups,
    zone_summary,
)

if TYPE_CHECKING:
    from endomeasure.measure.predict import ImageNoise, ImageNoiseByImage

__all__ = [
    "BAND_SIGMAS",
    "BoardSet",
    "ModelBoardTest",
    "RigidFit",
    "board_predictions",
    "board_sets",
    "ideal_board_pixels",
    "prediction_zones",
    "rigid_fit",
    "run_board_test",
    "TestImageNoise",
    "measured_image_noise",
    "test_image_noise",
    "within_band",
]

BAND_SIGMAS = 2.0
"""Half-width of the band an actual error is checked against, in predicted std."""

_TEST_HINT = "run `endomeasure detect SESSION IMAGES --board SPEC --set test` first"


@dataclasses.dataclass(frozen=True)
class BoardSet:
    """The test images of one board: geometry and the detected corners in both halves."""

    board: str
    cols: int
    rows: int
    square_mm: float
    images: list[str]
    ids: list[np.ndarray]  # per image (N_i,) int
    left: list[np.ndarray]  # per image (N_i, 2) px
    right: list[np.ndarray]  # per image (N_i, 2) px


def board_sets(
    boards: Mapping[str, Mapping[str, Any]],
    detections: Iterable,
    test_images: Iterable[str],
    where: str | None = None,
) -> list[BoardSet]:
    """Every test image with a known board detected in both halves (their common ids).

    Parameters
    ----------
    boards : mapping of board name to its attributes (``cols``, ``rows``, ``square_mm``)
        Boards without these are skipped.
    detections : iterable of Detection
        The session's detections (``image``, ``board``, ``half``, ``ids``, ``pixels``).
    test_images : iterable of str
    where : str, optional
        The session path, for the errors.
    """
    test_images = set(test_images)
    if not test_images:
        raise BadInputError("the session holds no test images", path=where, hint=_TEST_HINT)
    by_board: dict[str, dict[str, dict[Half, Any]]] = {}
    for det in detections:
        if det.image in test_images and det.ok:
            by_image = by_board.setdefault(det.board, {})
            by_image.setdefault(det.image, {})[Half.parse(det.half)] = det
    sets = []
    for name, a in boards.items():
        if not all(k in a for k in ("cols", "rows", "square_mm")):
            continue
        bs = BoardSet(name, int(a["cols"]), int(a["rows"]), float(a["square_mm"]), [], [], [], [])
        for image, halves in sorted(by_board.get(name, {}).items()):
            if Half.LEFT not in halves or Half.RIGHT not in halves:
                continue
            dl, dr = halves[Half.LEFT], halves[Half.RIGHT]
            ids, il, ir = np.intersect1d(dl.ids, dr.ids, return_indices=True)
            if ids.size == 0:
                continue
            bs.images.append(image)
            bs.ids.append(ids.astype(np.int64))
            bs.left.append(np.asarray(dl.pixels, dtype=np.float64)[il])
            bs.right.append(np.asarray(dr.pixels, dtype=np.float64)[ir])
        if bs.images:
            sets.append(bs)
    if not sets:
        raise BadInputError(
            "no test image has a known board detected in both halves", path=where, hint=_TEST_HINT
        )
    return sets


@dataclasses.dataclass
class ModelBoardTest:
    """One model's board test: corners, measurement table and the per-zone summary."""

    model: str
    board: list[str]  # per image
    images: list[str]
    square_mm: list[float]  # per image
    corner_image: np.ndarray  # (C,) int, index into images
    corner_id: np.ndarray  # (C,) int
    corner_left: np.ndarray  # (C, 2) px
    corner_right: np.ndarray  # (C, 2) px
    corner_xyz: np.ndarray  # (C, 3) mm
    corner_gap: np.ndarray  # (C,) mm
    corner_rms: np.ndarray  # (C,) px
    corner_status: np.ndarray  # (C,) uint8
    table: BoardTestTable  # image = index into images
    summary: ZoneSummary  # one row per (board, kind, zone)
    summary_board: np.ndarray  # (K,) str, the board of each summary row

    @classmethod
    def from_fields(cls, fields: Mapping[str, Any]) -> ModelBoardTest:
        """From plain values (:func:`endomeasure.io.records.board_test_fields`)."""
        values = dict(fields)
        values["table"] = BoardTestTable(**values["table"])
        values["summary"] = ZoneSummary(**values["summary"])
        return cls(**values)

    def image_pixels(self, index: int):
        """(ids, left, right, xyz) of one image."""
        sel = self.corner_image == index
        return (
            self.corner_id[sel],
            self.corner_left[sel],
            self.corner_right[sel],
            self.corner_xyz[sel],
        )


def _zone_summary_by_board(table, model: str, board_of_row: np.ndarray, zone_mm: float):
    parts, boards = [], []
    for board in dict.fromkeys(board_of_row.tolist()):
        s = zone_summary({model: table.select(board_of_row == board)}, zone_mm)
        parts.append(s)
        boards.append(np.full(s.model.shape[0], board).astype(str))
    if not parts:
        return zone_summary({model: table}, zone_mm), np.zeros(0, dtype=str)
    summary = ZoneSummary(*(np.concatenate(c) for c in zip(*parts, strict=True)))
    return summary, np.concatenate(boards)


def run_board_test(model_name: str, model, sets: list[BoardSet], zone_mm: float) -> ModelBoardTest:
    """Triangulate every corner of every test image with one model and measure the boards."""
    from endomeasure.solvers.triangulate import triangulate

    images, boards, squares, tables = [], [], [], []
    corners: dict[str, list] = {k: [] for k in ("image", "id", "l", "r", "xyz", "gap", "rms", "st")}
    for bs in sets:
        # one triangulation call for all images of the board
        tri = triangulate(model, np.concatenate(bs.left), np.concatenate(bs.right), "ml")
        bounds = np.cumsum([0] + [ids.size for ids in bs.ids])
        board_images = []
        for k, image in enumerate(bs.images):
            sl = slice(bounds[k], bounds[k + 1])
            corners["image"].append(np.full(bs.ids[k].size, len(images)))
            images.append(image)
            boards.append(bs.board)
            squares.append(bs.square_mm)
            for key, value in (("id", bs.ids[k]), ("l", bs.left[k]), ("r", bs.right[k]),
                               ("xyz", tri.points[sl]), ("gap", tri.gap[sl]),
                               ("rms", tri.rms[sl]), ("st", tri.status[sl])):  # fmt: skip
                corners[key].append(value)
            board_images.append(BoardImage(bs.ids[k], tri.points[sl], bs.left[k], bs.right[k]))
        t = board_test_table(bs.cols, bs.rows, bs.square_mm, board_images)
        offset = len(images) - len(bs.images)
        tables.append(t._replace(image=t.image + offset))
    table = BoardTestTable(*(np.concatenate(c) for c in zip(*tables, strict=True)))
    board_of_row = (
        np.asarray(boards, dtype=str)[table.image] if table.image.size else np.zeros(0, str)
    )
    summary, summary_board = _zone_summary_by_board(table, model_name, board_of_row, zone_mm)
    c = {k: np.concatenate(v) for k, v in corners.items()}
    return ModelBoardTest(
        model_name, boards, images, squares, c["image"], c["id"], c["l"], c["r"], c["xyz"],
        c["gap"], c["rms"], c["st"].astype(np.uint8), table, summary, summary_board,
    )  # fmt: skip


# ----- predictions ------------------------------------------------------------------------------


class RigidFit(NamedTuple):
    """A rigid transform fitted between two point sets: ``b ~ (a - centre_a) R^T + centre_b``."""

    rotation: np.ndarray  # (3, 3)
    centre_a: np.ndarray  # (3,)
    centre_b: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``points`` (..., 3) of the first set's frame in the second's."""
        return (points - self.centre_a) @ self.rotation.T + self.centre_b


def rigid_fit(a: np.ndarray, b: np.ndarray) -> RigidFit:
    """The rotation and translation mapping points ``a`` onto ``b`` in least squares.

    ``a``, ``b``: shape (N, 3), N >= 3, corresponding points.

    Notes
    -----
    Kabsch's SVD solution with the reflection removed (W. Kabsch, Acta Cryst. A32, 1976).
    """
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return RigidFit(vt.T @ np.diag([1.0, 1.0, d]) @ u.T, ca, cb)


def ideal_board_pixels(model, grid: np.ndarray, xyz: np.ndarray, ql, qr):
    """Pixels of the ideal board at its estimated pose, in both halves.

    The paper's Section 4 predicts at the "calibration target positions calculated for
    the test set": the board's corners ``grid`` (N, 3), mm, board frame, are fitted to
    the triangulated corners ``xyz`` (N, 3), mm (:func:`rigid_fit`) and projected.
    Corners that do not project keep their detected pixels ``ql``, ``qr`` (N, 2), px.
    """
    ok = np.all(np.isfinite(xyz), axis=1)
    if ok.sum() < 3:
        return ql, qr
    ideal = rigid_fit(grid[ok], xyz[ok]).apply(grid)
    out = []
    for half, q in (("left", ql), ("right", qr)):
        proj = model.project(ideal, half)
        good = (proj.status == Status.OK)[:, None]
        out.append(np.where(good, proj.pixels, q))
    return out[0], out[1]


def _grid_of(grids: Mapping[str, np.ndarray], bt: ModelBoardTest, k: int, ids) -> np.ndarray:
    """Board-frame coordinates (N, 3), mm, of corners ``ids`` of test image ``k``."""
    return np.asarray(grids[bt.board[k]])[np.asarray(ids, dtype=np.int64)]


MIN_IMAGE_RUNS = 10
"""Runs of three neighbouring corners an image half needs for its own noise figure
(:func:`test_image_noise`): from fewer, the figure's own scatter (about 1 / sqrt(2 runs)
relative, some 20 % at 10) would be a noise source of its own."""


class TestImageNoise(NamedTuple):
    """The detection noise of each test image, measured on the image itself."""

    std: np.ndarray
    """(I, 4) px: standard deviation of ``u_L, v_L, u_R, v_R`` in test image i (u and v
    apart: the depth follows u alone, and a prism's anamorphic magnification or an
    interlaced sensor need not treat them alike)."""
    rho: np.ndarray
    """(I, 2): correlation of a corner's u_L with its u_R and of its v_L with its v_R
    (what the two views of one corner share: its blur, its squares' foreshortening)."""


def test_image_noise(bt: ModelBoardTest, model, grids: Mapping[str, np.ndarray]) -> TestImageNoise:
    """The detection noise of each test image, measured on the image itself.

    The detected corners minus the ideal board at its estimated pose
    (:func:`ideal_board_pixels`) hold the detection noise, the pose's error and the
    model's misfit; the last two are smooth over the board and cancel in the second
    differences of neighbouring corners
    (:func:`~endomeasure.solvers.verdict.second_differences`), which leave the noise that
    is independent from corner to corner: ``E[D^2] = 6 sigma^2`` per coordinate, and the
    two halves' D of the same runs correlate as the noise of a corner's two views does
    (:func:`_shrunk_correlations`). Images with fewer than :data:`MIN_IMAGE_RUNS` runs
    take the median of the others (NaN when none has enough).
    """
    from endomeasure.solvers.verdict import second_differences

    std = np.full((len(bt.images), 4), np.nan)
    products = np.full((len(bt.images), 3, 2), np.nan)  # sum D_L D_R, D_L^2, D_R^2
    runs = np.zeros(len(bt.images))
    for k in range(len(bt.images)):
        ids, ql, qr, xyz = bt.image_pixels(k)
        grid = _grid_of(grids, bt, k, ids)
        il, ir = ideal_board_pixels(model, grid, xyz, ql, qr)
        ok = np.all(np.isfinite(xyz), axis=1)  # the others keep no ideal pixel
        dl = second_differences(grid[ok], (ql - il)[ok])
        dr = second_differences(grid[ok], (qr - ir)[ok])
        if dl.shape[0] < MIN_IMAGE_RUNS:
            continue
        products[k] = np.sum(dl * dr, axis=0), np.sum(dl * dl, axis=0), np.sum(dr * dr, axis=0)
        runs[k] = dl.shape[0]
        std[k] = np.sqrt(np.concatenate(products[k, 1:]) / (6 * runs[k]))
    finite = np.all(np.isfinite(std), axis=1)
    if finite.any():
        std[~finite] = np.median(std[finite], axis=0)
    return TestImageNoise(std, _shrunk_correlations(products, runs))


def measured_image_noise(bt: ModelBoardTest, model, grids: Mapping[str, np.ndarray], source: str):
    """:func:`test_image_noise` as the image noise of a prediction (an
    ``ImageNoiseByImage`` described by ``source``), or None when no image has enough
    neighbouring corners to measure it (the caller falls back to another figure)."""
    from endomeasure.measure.predict import ImageNoiseByImage

    measured = test_image_noise(bt, model, grids)
    if not np.all(np.isfinite(measured.std)):
        return None
    return ImageNoiseByImage(measured.std, source, measured.rho)


CORRELATION_VARIANCE_FACTOR = 1.94
"""Variance of a correlation estimated from R runs of second differences, times R, for
small correlations: ``1 + 2 sum_k rho_k^2`` over the lags k of the runs' own
autocorrelation (-2/3 between neighbouring runs of one line, +1/6 two apart), since
runs share corners."""


def _shrunk_correlations(products: np.ndarray, runs: np.ndarray) -> np.ndarray:
    """Each image's correlation of its two halves' second differences, shrunk towards
    the whole set's in proportion to its sampling variance (empirical Bayes).

    From some 40 runs an image's own estimate scatters by about 0.2, as much as the
    correlations themselves vary: alone it would add noise to every prediction. The
    pooled estimate is kept where the images' spread is no larger than their sampling
    scatter, each image's own where it is much larger. ``products`` (I, 3, 2): sums of
    D_L D_R, D_L^2, D_R^2 per coordinate (NaN for images without enough runs).
    """
    own = np.isfinite(products[:, 0, 0])
    rho = np.zeros((products.shape[0], 2))
    if not own.any():
        return rho
    p = products[own]
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled = np.nan_to_num(p[:, 0].sum(0) / np.sqrt(p[:, 1].sum(0) * p[:, 2].sum(0)))
        single = np.nan_to_num(p[:, 0] / np.sqrt(p[:, 1] * p[:, 2]))
    sampling = CORRELATION_VARIANCE_FACTOR / runs[own]  # (I',)
    between = np.maximum(np.var(single, axis=0) - np.mean(sampling), 0.0)  # (2,)
    weight = between / (between + sampling[:, None])
    rho[:] = pooled
    rho[own] = np.clip(pooled + weight * (single - pooled), -1.0, 1.0)
    return rho


def board_predictions(
    bt: ModelBoardTest,
    model,
    grids: Mapping[str, np.ndarray],
    noise: ImageNoise | ImageNoiseByImage,
    *,
    param_cov: np.ndarray | None = None,
    misfit=None,
    at: str = "board",
    **options,
) -> dict:
    """Predicted bias, std and its parts for every row of a board test's table.

    ``grids``: each board's corner coordinates by corner id (N, 3), mm, board frame (the
    ``object_points`` of its parsed spec), for ``at='board'``.

    ``noise``: an :class:`~endomeasure.measure.predict.ImageNoise`, or an
    :class:`~endomeasure.measure.predict.ImageNoiseByImage` over ``bt.images`` (e.g.
    :func:`test_image_noise`). ``param_cov``, ``misfit`` and ``options`` (``method``,
    ...): as in :func:`~endomeasure.measure.predict.predict_measurement_error`; rows go in
    batches of :data:`~endomeasure.measure.predict.ROW_BATCH`.

    ``at='board'`` predicts at the pixels of the ideal board at its estimated pose
    (:func:`ideal_board_pixels`), ``at='detections'`` at the detected pixels. The first
    estimates the error distribution better: a prediction at noisy pixels is itself
    noisy, and for a segment whose ends carry a large depth noise it is biased upwards
    (the observed depth difference of its ends tilts the segment, which turns the
    quadratic depth term into a linear one).

    Returns
    -------
    PredictedErrors
        Arrays (M,), one entry per row of ``bt.table``.
    """
    from endomeasure.measure.predict import ROW_BATCH, PredictedErrors, predict_measurement_error

    t = bt.table
    images = []
    for k in range(len(bt.images)):
        ids, ql, qr, xyz = bt.image_pixels(k)
        if at == "board":
            ql, qr = ideal_board_pixels(model, _grid_of(grids, bt, k, ids), xyz, ql, qr)
        images.append(BoardImage(ids, xyz, ql, qr))
    out = PredictedErrors.empty(t.kind.shape[0])
    for kind, measure_kind in BOARD_KINDS.items():
        rows = np.flatnonzero(t.kind == kind)
        if rows.size == 0:
            continue
        ql, qr = stencil_pixels(t, images, kind)
        for start in range(0, rows.size, ROW_BATCH):
            sl = slice(start, start + ROW_BATCH)
            pred = predict_measurement_error(
                model, measure_kind, ql[sl], qr[sl], noise=noise.of_rows(t.image[rows[sl]]),
                param_cov=param_cov, misfit=misfit, **options,
            )  # fmt: skip
            out.fill(rows[sl], pred)
    return out


def prediction_zones(bt: ModelBoardTest, predicted, zone_mm: float) -> list[dict]:
    """Predicted against actual errors per (board, kind, zone) (module docstring).

    ``predicted``: the :class:`~endomeasure.measure.predict.PredictedErrors` of the rows
    of ``bt.table``. Zones with fewer than two measurements are left out.
    """
    bias, std = predicted.bias, predicted.std
    t = bt.table
    board_of_row = np.asarray(bt.board, dtype=str)[t.image]
    ok = np.isfinite(t.error) & np.isfinite(std) & np.isfinite(t.z_mean)
    rows = []
    for board in dict.fromkeys(board_of_row.tolist()):
        for kind, k, sel in zone_groups(t, zone_mm, ok & (board_of_row == board)):
            e, b, s = t.error[sel], bias[sel], std[sel]
            if e.size < 2:
                continue
            pred_std = float(np.sqrt(np.mean(s**2) + np.var(b)))
            actual_std = float(np.std(e, ddof=1))
            rows.append(
                {
                    "board": board,
                    "kind": kind,
                    "zone_start": zone_bounds(k, zone_mm)[0],
                    "zone_end": zone_bounds(k, zone_mm)[1],
                    "n": int(e.size),
                    "true": float(t.true[sel][0]),
                    "actual_mean": float(np.mean(e)),
                    "actual_std": actual_std,
                    "predicted_mean": float(np.mean(b)),
                    "predicted_std": pred_std,
                    **{
                        f"predicted_{part}": _rms_or_none(getattr(predicted, part)[sel])
                        for part in ("std_image", "std_calibration", "std_model")
                    },
                    "std_ratio": actual_std / pred_std if pred_std > 0 else None,
                    "within_band": float(np.mean(np.abs(e - b) <= BAND_SIGMAS * s)),
                }
            )
    return rows


def _rms_or_none(values: np.ndarray) -> float | None:
    """The RMS of a zone's predicted parts, None for a part that was not propagated."""
    return float(np.sqrt(np.mean(values**2))) if np.all(np.isfinite(values)) else None


def within_band(bt: ModelBoardTest, bias: np.ndarray, std: np.ndarray) -> float:
    """Fraction of all measurements whose error lies in its predicted band."""
    error = bt.table.error
    ok = np.isfinite(error) & np.isfinite(std)
    return float(np.mean(np.abs(error[ok] - bias[ok]) <= BAND_SIGMAS * std[ok]))
