"""Picking the frames of a calibration clip worth keeping: sharp, the whole board in both
halves, and a pose distinct from the frames already kept.

A clip is read once to gather each frame's :class:`FrameEvidence` (a fast full-board
check per half and the board's edge blur), then :func:`pick_frames` decides on the whole
clip at once, because "sharp" is relative to the clip: its sharpest frames set the
reference a frame's blur is compared with.

Blur is measured where it matters, on the board's checker edges, for each of the two
edge families (the grid's rows and columns) separately: motion blurs the edges across
the motion and leaves the others sharp, which one isotropic figure would average away.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from endomeasure.features.boards import BoardSpec, ChessboardSpec, parse_board_spec

__all__ = [
    "BLUR_RATIO_MAX",
    "MIN_MOTION",
    "FrameEvidence",
    "FramePick",
    "board_edge_blur_px",
    "frame_evidence",
    "pick_frames",
]

BLUR_RATIO_MAX = 1.5
"""A frame is sharp when its board's edge blur is at most this multiple of the clip's
reference (the 10th percentile over the frames that show the board). Defocus alone
changes the blur by a factor of about 1.4 over an endoscope's working range (default
preset: PSF sigma 0.55-0.82 px over 10-45 mm, 0.62-0.87 px with the pixel box); motion
during the exposure of more than about 2 px across an edge exceeds it."""

MIN_MOTION = 0.05
"""A frame's pose is distinct when the board's outer corners moved, on average over the
four corners and both halves, by at least this fraction of the image diagonal from
every frame kept before it."""

REFERENCE_PERCENTILE = 10.0
"""The clip's sharp reference: this percentile of the blur of the frames with the board
(robust to a few frames sharper than the rest by noise)."""

DERIVATIVE_SIGMA_PX = 1.0
"""Gaussian derivative scale of the blur measure: it keeps the noise out of the second
derivatives; its variance is subtracted from the result."""

FAST_CHECK_MAX_SIDE_PX = 640
"""Halves larger than this are downscaled (by an integer factor) for the fast check."""


@dataclasses.dataclass(frozen=True)
class FrameEvidence:
    """What one frame shows, for :func:`pick_frames`.

    Attributes
    ----------
    index : int
        Frame number in the clip (0 = first).
    grids : tuple of (ndarray, shape (rows, cols, 2), px, or None)
        The board's corners per half (left, right) in full-image pixels, in the fast
        check's order; None where the half does not show the whole board.
    blur_px : float, px
        The board's edge blur (the larger of the two edge families, the worse half);
        NaN unless both halves show the board.
    """

    index: int
    grids: tuple[np.ndarray | None, np.ndarray | None]
    blur_px: float

    @property
    def board_seen(self) -> bool:
        return all(g is not None for g in self.grids)


@dataclasses.dataclass(frozen=True)
class FramePick:
    """The frames kept and why each other frame was not.

    Attributes
    ----------
    picked : list of int
        Frame numbers kept, in clip order.
    reasons : dict of int -> str
        For every frame not kept: ``"board not fully seen in the left half"`` (or right,
        or both), ``"blurred"`` or ``"pose too close to a kept frame"``.
    reference_blur_px : float, px
        The clip's sharp reference (NaN when no frame shows the board).
    """

    picked: list[int]
    reasons: dict[int, str]
    reference_blur_px: float

    def count(self, reason: str) -> int:
        """How many frames were left out for a reason starting with ``reason``."""
        return sum(r.startswith(reason) for r in self.reasons.values())


def board_edge_blur_px(gray: np.ndarray, grid: np.ndarray) -> float:
    """Gaussian sigma of the board's checker edges, px, the worse of the two edge families.

    Parameters
    ----------
    gray : ndarray, shape (height, width), float or uint8
        The image the grid lies in.
    grid : ndarray, shape (rows, cols, 2), px
        Inner corners in grid order (rows >= 2, cols >= 2).

    Notes
    -----
    For a step edge blurred by a Gaussian of sigma ``s`` and seen through Gaussian
    derivatives of sigma ``s0``, the profile across the edge is an erf of sigma
    ``S = sqrt(s^2 + s0^2)``, and ``int I'^2 / int I''^2 = 2 S^2`` whatever the contrast
    and edge length. The derivatives are taken along each family's normal (the
    perpendicular of the mean grid row or column direction), summed over the board's
    inner area (the outer corners grown by half a square), so the board background and
    other objects do not enter. The pixel box adds ``1/12 px^2`` to ``s^2``.
    """
    from scipy.ndimage import gaussian_filter

    gray = np.asarray(gray, dtype=np.float64)
    grid = np.asarray(grid, dtype=np.float64)
    mask = _board_mask(gray.shape, grid)
    if mask.sum() < 16:
        return float("nan")
    s0 = DERIVATIVE_SIGMA_PX
    d = {order: gaussian_filter(gray, s0, order=order) for order in
         ((0, 1), (1, 0), (0, 2), (1, 1), (2, 0))}  # fmt: skip
    ix, iy = d[(0, 1)][mask], d[(1, 0)][mask]
    ixx, ixy, iyy = d[(0, 2)][mask], d[(1, 1)][mask], d[(2, 0)][mask]
    sigmas = []
    for along in (grid[:, 1:] - grid[:, :-1], grid[1:] - grid[:-1]):
        direction = along.reshape(-1, 2).mean(axis=0)
        direction /= np.linalg.norm(direction)
        nx, ny = -direction[1], direction[0]  # the normal of edges running along the lines
        first = np.sum((nx * ix + ny * iy) ** 2)
        second = np.sum((nx * nx * ixx + 2 * nx * ny * ixy + ny * ny * iyy) ** 2)
        if not second > 0:
            return float("nan")
        sigmas.append(np.sqrt(max(first / (2.0 * second) - s0**2, 0.0)))
    return float(max(sigmas))


def _board_mask(shape: tuple[int, int], grid: np.ndarray) -> np.ndarray:
    """The board's inner area: the quadrilateral of the outer corners grown by half a
    square along the grid's own directions."""
    import cv2

    outer = []
    for r, c in ((0, 0), (0, -1), (-1, -1), (-1, 0)):
        rr = 1 if r == 0 else -2
        cc = 1 if c == 0 else -2
        p = grid[r, c]
        outer.append(p + 0.5 * (p - grid[r, cc]) + 0.5 * (p - grid[rr, c]))
    mask = np.zeros(shape, dtype=np.uint8)
    cv2.fillConvexPoly(mask, np.round(np.array(outer) * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    return mask.astype(bool)


def frame_evidence(
    index: int, gray: np.ndarray, split: int, board: str | BoardSpec
) -> FrameEvidence:
    """The fast check of one frame: the whole board in each half, and its edge blur.

    Parameters
    ----------
    index : int
        Frame number.
    gray : ndarray, shape (height, width), uint8
        The frame in grey (:func:`endomeasure.features.detect.to_gray_u8`).
    split : int
        First column of the right half.
    board : str or BoardSpec

    Notes
    -----
    Chessboards: OpenCV's sector-based finder (``findChessboardCornersSB`` with
    ``CALIB_CB_LARGER``) on each half (downscaled above :data:`FAST_CHECK_MAX_SIDE_PX`):
    pixel-level corners of whole boards only, a grid of the spec's size and no larger.
    The classic finder with ``CALIB_CB_FAST_CHECK`` is no faster and misses most sharp
    halves of the default preset's clips (docs/video.md). ChArUco boards: the full
    detector, and a half counts when every corner was found.
    """
    spec = parse_board_spec(board)
    grids = []
    for lo, hi in ((0, split), (split, gray.shape[1])):
        half = np.ascontiguousarray(gray[:, lo:hi])
        grid = _fast_grid(half, spec)
        grids.append(None if grid is None else grid + np.array([lo, 0.0]))
    blur = float("nan")
    if all(g is not None for g in grids):
        blur = max(board_edge_blur_px(gray, g) for g in grids)
    return FrameEvidence(int(index), (grids[0], grids[1]), blur)


def _fast_grid(half: np.ndarray, spec: BoardSpec) -> np.ndarray | None:
    import cv2

    if isinstance(spec, ChessboardSpec):
        factor = max(1, int(np.ceil(max(half.shape) / FAST_CHECK_MAX_SIDE_PX)))
        small = np.ascontiguousarray(half[::factor, ::factor]) if factor > 1 else half
        found, corners, meta = cv2.findChessboardCornersSBWithMeta(
            small, (spec.cols, spec.rows), cv2.CALIB_CB_LARGER
        )
        if not found or corners is None or meta is None:
            return None
        shape = tuple(int(k) for k in meta.shape[:2])
        if sorted(shape) != sorted((spec.rows, spec.cols)):
            return None  # a larger grid: another board, not this one whole
        # a sample of the downscaled image covers factor x factor pixels centred on
        # (factor - 1) / 2 in full-resolution pixel coordinates
        grid = corners.reshape(shape[0], shape[1], 2).astype(np.float64)
        return grid * factor + (factor - 1) / 2.0
    from endomeasure.features.charuco import detect_charuco

    result = detect_charuco(half, spec)
    if not result.ok or len(result.ids) < spec.n_corners:
        return None
    order = np.argsort(result.ids)
    return np.asarray(result.pixels, dtype=np.float64)[order].reshape(spec.rows, spec.cols, 2)


def _outline(grid: np.ndarray) -> np.ndarray:
    return np.array([grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]], dtype=np.float64)


_DIHEDRAL = [np.roll(np.arange(4), k) for k in range(4)]
_DIHEDRAL += [order[::-1] for order in _DIHEDRAL]


def outline_motion_px(a: np.ndarray, b: np.ndarray) -> float:
    """Mean displacement of a board's four outer corners between two grids, px, whatever
    corner each detection listed first (the least over the square's 8 symmetries)."""
    oa, ob = _outline(a), _outline(b)
    return float(min(np.mean(np.linalg.norm(oa - ob[order], axis=1)) for order in _DIHEDRAL))


def pick_frames(
    evidence: Sequence[FrameEvidence],
    image_size: tuple[int, int],
    *,
    blur_ratio_max: float = BLUR_RATIO_MAX,
    min_motion: float = MIN_MOTION,
) -> FramePick:
    """Choose the frames of a clip to keep.

    Parameters
    ----------
    evidence : sequence of FrameEvidence
        Every frame examined, in clip order.
    image_size : (width, height), px
    blur_ratio_max : float
        See :data:`BLUR_RATIO_MAX`.
    min_motion : float
        See :data:`MIN_MOTION` (fraction of the image diagonal).

    Returns
    -------
    FramePick
        Greedy in clip order: a frame showing the whole board in both halves, sharp
        relative to the clip, whose board moved by at least ``min_motion`` from every
        frame kept so far.
    """
    seen = [e for e in evidence if e.board_seen and np.isfinite(e.blur_px)]
    reference = (
        float(np.percentile([e.blur_px for e in seen], REFERENCE_PERCENTILE))
        if seen
        else float("nan")
    )
    threshold = blur_ratio_max * reference
    min_px = min_motion * float(np.hypot(*image_size))
    picked: list[FrameEvidence] = []
    reasons: dict[int, str] = {}
    for e in evidence:
        missing = [name for name, g in zip(("left", "right"), e.grids, strict=True) if g is None]
        if missing:
            where = "both halves" if len(missing) == 2 else f"the {missing[0]} half"
            reasons[e.index] = f"board not fully seen in {where}"
        elif not e.blur_px <= threshold:
            reasons[e.index] = "blurred"
        elif any(_motion(e, kept) < min_px for kept in picked):
            reasons[e.index] = "pose too close to a kept frame"
        else:
            picked.append(e)
    return FramePick([e.index for e in picked], reasons, reference)


def _motion(a: FrameEvidence, b: FrameEvidence) -> float:
    return float(
        np.mean([outline_motion_px(ga, gb) for ga, gb in zip(a.grids, b.grids, strict=True)])
    )
