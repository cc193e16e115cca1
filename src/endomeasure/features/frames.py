"""Picking the frames of a calibration clip worth keeping: sharp, the whole board in both
halves, and a pose distinct from the frames already kept.

A clip is read once to gather each frame's :class:`FrameEvidence` (a fast full-board
check per half and the board's edge blur), then :func:`pick_frames` decides on the whole
clip at once, because "sharp" is relative to the clip: its sharpest frames at each board
scale set the reference a frame's blur is compared with.

Blur is measured where it matters, on the board's checker edges, for each of the two
edge families (the grid's rows and columns) separately. Defocus blurs both alike, and
changes with the distance, hence with the board's scale in the image; motion blurs the
edges across the motion and leaves the others sharp. So a frame is blurred when its
edges are wider than the clip's sharpest at the same scale, or when the two families
differ.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.features.boards import BoardSpec, ChessboardSpec, parse_board_spec

__all__ = [
    "ANISOTROPY_MAX",
    "BLUR_RATIO_MAX",
    "MIN_MOTION",
    "SPLIT_SAMPLE_FRAMES",
    "ClipPick",
    "FrameEvidence",
    "FramePick",
    "board_edge_blur_px",
    "edge_blur_by_family",
    "frame_evidence",
    "pick_frames",
    "pick_from_clip",
    "sharp_envelope",
]

BLUR_RATIO_MAX = 1.15
"""A frame is sharp when its board's edge blur is at most this multiple of the clip's
sharp envelope at its board scale (:func:`sharp_envelope`): motion adds in quadrature,
so this lets through a smear of about half the in-focus blur (sigma ``0.57 s``, a box of
about 1.5 px for the default preset's 0.75 px edges)."""

ANISOTROPY_MAX = 1.15
"""... and when its two edge families' blurs differ by at most this factor in either
half: defocus and the lens PSF blur every direction alike (sharp frames of the default
preset differ by a few per cent), motion only across itself."""

MIN_MOTION = 0.02
"""A frame's pose is distinct when the board's outer corners moved, on average over the
four corners and both halves, by at least this fraction of the image diagonal (16 px on
640 x 480) from every frame kept before it."""

ENVELOPE_ROUNDS = 4
"""Refits of the sharp envelope to the frames on or below it."""

DERIVATIVE_SIGMA_PX = 1.0
"""Gaussian derivative scale of the blur measure: it keeps the noise out of the second
derivatives; its variance is subtracted from the result."""

FAST_CHECK_MAX_SIDE_PX = 640
"""Halves larger than this are downscaled (by an integer factor) for the fast check."""

SPLIT_SAMPLE_FRAMES = 16
"""Frames spread over a clip whose prism band gives the split when none is known."""

LEFT_OUT_REASONS = ("board not fully seen", "blurred", "pose too close to a kept frame")


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
    anisotropy : float
        The larger ratio of the two families' blurs over the halves (1 for defocus).
    """

    index: int
    grids: tuple[np.ndarray | None, np.ndarray | None]
    blur_px: float
    anisotropy: float = 1.0

    @property
    def board_seen(self) -> bool:
        return all(g is not None for g in self.grids)

    @property
    def scale_px(self) -> float:
        """Mean distance of neighbouring corners over both halves, px (NaN unless seen)."""
        if not self.board_seen:
            return float("nan")
        steps = [np.linalg.norm(np.diff(g, axis=axis), axis=-1).ravel()
                 for g in self.grids for axis in (0, 1)]  # fmt: skip
        return float(np.mean(np.concatenate(steps)))


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
        The clip's sharpest edge blur, the sharp envelope's least value (NaN when no
        frame shows the board).
    """

    picked: list[int]
    reasons: dict[int, str]
    reference_blur_px: float

    def count(self, reason: str) -> int:
        """How many frames were left out for a reason starting with ``reason``."""
        return sum(r.startswith(reason) for r in self.reasons.values())


def edge_blur_by_family(gray: np.ndarray, grid: np.ndarray) -> tuple[float, float]:
    """Gaussian sigma of the board's checker edges, px, for the edges along the grid's
    rows and along its columns.

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

    grid = np.asarray(grid, dtype=np.float64)
    gray = np.asarray(gray)
    # only the board's box (with the filters' reach) is filtered
    reach = int(np.ceil(4 * DERIVATIVE_SIGMA_PX)) + 2
    spacing = float(np.max(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    lo = np.maximum(np.floor(grid.reshape(-1, 2).min(axis=0) - spacing).astype(int) - reach, 0)
    hi = np.ceil(grid.reshape(-1, 2).max(axis=0) + spacing).astype(int) + reach + 1
    box = gray[lo[1] : hi[1], lo[0] : hi[0]].astype(np.float64)
    local = grid - lo
    mask = _board_mask(box.shape, local)
    if mask.sum() < 16:
        return float("nan"), float("nan")
    s0 = DERIVATIVE_SIGMA_PX
    d = {order: gaussian_filter(box, s0, order=order) for order in
         ((0, 1), (1, 0), (0, 2), (1, 1), (2, 0))}  # fmt: skip
    ix, iy = d[(0, 1)][mask], d[(1, 0)][mask]
    ixx, ixy, iyy = d[(0, 2)][mask], d[(1, 1)][mask], d[(2, 0)][mask]
    sigmas = []
    for along in (local[:, 1:] - local[:, :-1], local[1:] - local[:-1]):
        direction = along.reshape(-1, 2).mean(axis=0)
        direction /= np.linalg.norm(direction)
        nx, ny = -direction[1], direction[0]  # the normal of edges running along the lines
        first = np.sum((nx * ix + ny * iy) ** 2)
        second = np.sum((nx * nx * ixx + 2 * nx * ny * ixy + ny * ny * iyy) ** 2)
        sigma = np.sqrt(max(first / (2.0 * second) - s0**2, 0.0)) if second > 0 else np.nan
        sigmas.append(float(sigma))
    return sigmas[0], sigmas[1]


def board_edge_blur_px(gray: np.ndarray, grid: np.ndarray) -> float:
    """The worse of the two edge families' blur (:func:`edge_blur_by_family`), px."""
    return float(max(edge_blur_by_family(gray, grid)))


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
    blur, anisotropy = float("nan"), float("nan")
    if all(g is not None for g in grids):
        families = np.array([edge_blur_by_family(gray, g) for g in grids])  # (2 halves, 2)
        blur = float(np.max(families))
        anisotropy = float(np.max(families.max(axis=1) / np.maximum(families.min(axis=1), 1e-9)))
    return FrameEvidence(int(index), (grids[0], grids[1]), blur, anisotropy)


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


def sharp_envelope(scale_px: np.ndarray, blur_px: np.ndarray) -> np.ndarray:
    """The clip's sharpest blur at each board scale, px, evaluated at ``scale_px``.

    Parameters
    ----------
    scale_px, blur_px : ndarray, shape (n,), px
        Board scale (:attr:`FrameEvidence.scale_px`) and edge blur of the frames showing
        the board.

    Notes
    -----
    The defocus blur's diameter is proportional to ``|1/z - 1/z_focus|`` and the board's
    scale to ``1/z``, so ``blur^2 = a + b s + c s^2``: a parabola in the scale, fitted to
    the lower envelope (refitted :data:`ENVELOPE_ROUNDS` times to the frames on or below
    the last fit; motion only adds blur). Fewer than 4 frames, or a fit that is not
    convex: the clip's least blur.
    """
    s = np.asarray(scale_px, dtype=np.float64)
    b2 = np.asarray(blur_px, dtype=np.float64) ** 2
    floor = float(np.min(b2)) if len(b2) else float("nan")
    if len(s) < 4 or np.ptp(s) <= 0:
        return np.sqrt(np.full(len(s), floor))
    x = (s - s.mean()) / np.ptp(s)
    design = np.stack([np.ones_like(x), x, x**2], axis=1)
    keep = np.ones(len(s), dtype=bool)
    coeffs = np.array([floor, 0.0, 0.0])
    for _ in range(ENVELOPE_ROUNDS):
        if keep.sum() < 4:
            break
        coeffs = np.linalg.lstsq(design[keep], b2[keep], rcond=None)[0]
        keep = b2 <= design @ coeffs
    if coeffs[2] < 0:
        return np.sqrt(np.full(len(s), floor))
    return np.sqrt(np.maximum(design @ coeffs, floor))


def pick_frames(
    evidence: Sequence[FrameEvidence],
    image_size: tuple[int, int],
    *,
    blur_ratio_max: float = BLUR_RATIO_MAX,
    anisotropy_max: float = ANISOTROPY_MAX,
    min_motion: float = MIN_MOTION,
) -> FramePick:
    """Choose the frames of a clip to keep.

    Parameters
    ----------
    evidence : sequence of FrameEvidence
        Every frame examined, in clip order.
    image_size : (width, height), px
    blur_ratio_max, anisotropy_max : float
        See :data:`BLUR_RATIO_MAX` and :data:`ANISOTROPY_MAX`.
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
    envelope = sharp_envelope(np.array([e.scale_px for e in seen]),
                              np.array([e.blur_px for e in seen]))  # fmt: skip
    reference = {e.index: float(r) for e, r in zip(seen, envelope, strict=True)}
    min_px = min_motion * float(np.hypot(*image_size))
    picked: list[FrameEvidence] = []
    reasons: dict[int, str] = {}
    for e in evidence:
        missing = [name for name, g in zip(("left", "right"), e.grids, strict=True) if g is None]
        if missing:
            where = "both halves" if len(missing) == 2 else f"the {missing[0]} half"
            reasons[e.index] = f"board not fully seen in {where}"
        elif not (
            e.blur_px <= blur_ratio_max * reference.get(e.index, np.nan)
            and e.anisotropy <= anisotropy_max
        ):
            reasons[e.index] = "blurred"
        elif any(_motion(e, kept) < min_px for kept in picked):
            reasons[e.index] = "pose too close to a kept frame"
        else:
            picked.append(e)
    sharpest = float(np.min(envelope)) if len(envelope) else float("nan")
    return FramePick([e.index for e in picked], reasons, sharpest)


def _motion(a: FrameEvidence, b: FrameEvidence) -> float:
    return float(
        np.mean([outline_motion_px(ga, gb) for ga, gb in zip(a.grids, b.grids, strict=True)])
    )


class ClipPick(NamedTuple):
    """The outcome of :func:`pick_from_clip`.

    Attributes
    ----------
    frames : int
        Frames examined.
    picked : list of int
        Frame numbers kept, in clip order.
    split : int, px
        The split the halves were checked with.
    reference_blur_px : float, px
        The clip's sharpest edge blur (:attr:`FramePick.reference_blur_px`).
    left_out : dict of str -> int
        Frames not kept, by reason (:data:`LEFT_OUT_REASONS`).
    """

    frames: int
    picked: list[int]
    split: int
    reference_blur_px: float
    left_out: dict[str, int]


FrameReader = Callable[[Callable[[int], bool] | None], Iterable[tuple[int, np.ndarray]]]
"""``read(keep)``: the ``(frame number, pixels)`` of a clip's frames that ``keep`` accepts
(all for None), in order (e.g. :func:`endomeasure.io.video.read_frames` of one file)."""


def pick_from_clip(
    read: FrameReader,
    total: int,
    progress: Callable[[int, int], None],
    *,
    board: str | None,
    split: int | None = None,
    path: str = "",
) -> ClipPick:
    """The frames of a clip worth keeping (the rules of :func:`pick_frames`).

    Pass 1, when ``split`` is None: the split from the prism band of
    :data:`SPLIT_SAMPLE_FRAMES` frames spread over the clip; pass 2: every frame's fast
    check and blur (:func:`frame_evidence`), reported to ``progress(done, total)``; then
    the pick over the whole clip.

    Parameters
    ----------
    read : FrameReader
        The clip's frames (the caller opens the file, so this module reads none).
    total : int
        Frame count the clip's header states (for the progress only).
    progress : callable(done, total)
    board : str or None
        Board spec; None is refused (the pick needs the board).
    split : int or None, px
    path : str
        The clip's file, for the messages.

    Raises
    ------
    BadInputError
        No board spec, no split found, a split outside the frames, or no frame worth
        keeping.
    """
    from endomeasure.features.detect import to_gray_u8

    if board is None:
        raise BadInputError(
            "picking frames from a video needs the board",
            path=path or None,
            hint="give --board SPEC, or --frame-step N to take every N-th frame",
        )
    spec = parse_board_spec(board)
    if split is None:
        from endomeasure.features.split import find_split_in_set, split_evidence

        every = max(1, total // SPLIT_SAMPLE_FRAMES)
        sample = read(lambda i: i % every == 0)
        split = find_split_in_set([split_evidence(px) for _, px in sample], path=path or None).split
    evidence, size = [], None
    for index, pixels in read(None):
        progress(index + 1, max(total, index + 1))
        size = (int(pixels.shape[1]), int(pixels.shape[0]))
        if not 0 < split < size[0]:
            raise BadInputError(
                f"split column {split} is outside the video's frames (width {size[0]} px)",
                path=path or None,
            )
        evidence.append(frame_evidence(index, to_gray_u8(pixels), split, spec))
    pick = pick_frames(evidence, size)
    left_out = {reason: pick.count(reason) for reason in LEFT_OUT_REASONS}
    if not pick.picked:
        raise BadInputError(
            f"no frame of the video shows the whole board {spec.canonical()} sharp in both "
            f"halves ({len(evidence)} frames: board not fully seen in "
            f"{left_out['board not fully seen']}, blurred {left_out['blurred']})",
            path=path or None,
            hint="check the --board spec and the --split, or give --frame-step N",
        )
    return ClipPick(len(evidence), pick.picked, int(split), float(pick.reference_blur_px),
                    left_out)  # fmt: skip
