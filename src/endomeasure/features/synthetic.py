"""Analytic renders of flat targets under known homographies, with exact corner pixels.

This is a small, self-contained oracle for the detector: each half of a split image
shows a flat board mapped by its own homography, so the true pixel of every corner is
``H @ (x, y, 1)`` exactly. It is used by the tests of :mod:`endomeasure.features` and by
``bench/bench_detect.py`` to choose the detector; the physically based digital twin with
real optics is :mod:`endomeasure.simulate`.

Rendering: every pixel is the mean of ``supersample x supersample`` point samples of the
board texture, placed symmetrically about the pixel centre (the centre of pixel column
``c`` is ``u = c``, so the pixel covers ``c - 0.5 <= u < c + 0.5``). The box filter and
any symmetric Gaussian blur added afterwards leave the saddle point of an (locally
affine) X-junction where it is, so the analytic corner pixels stay the truth.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from endomeasure.conventions import Half
from endomeasure.features.boards import BoardSpec, CharucoSpec, ChessboardSpec
from endomeasure.geometry.rotations import rotation_matrix

__all__ = [
    "SyntheticSplitImage",
    "apply_homography",
    "board_texture",
    "homography_from_pose",
    "render_split_image",
]

Texture = Callable[[np.ndarray, np.ndarray], np.ndarray]

# Grey level of the scene around the board (0 black .. 1 white).
BACKGROUND_LEVEL = 0.45
# Grey levels of the board's black and white squares.
BLACK_LEVEL, WHITE_LEVEL = 0.08, 0.92
# Texels per square of the ChArUco texture (nearest-texel lookup; square edges fall on
# texel edges, so the corner positions stay exact).
CHARUCO_TEXELS_PER_SQUARE = 120


def homography_from_pose(
    focal_px: float, centre_px: tuple[float, float], rvec: np.ndarray, tvec_mm: np.ndarray
) -> np.ndarray:
    """Homography from board-plane mm ``(x, y, 1)`` to full-image pixels ``(u, v, 1)``.

    Parameters
    ----------
    focal_px : float, px
    centre_px : (u, v), px
        Principal point, full-image coordinates.
    rvec : ndarray, shape (3,), rad
        Rotation vector of the board in the camera frame.
    tvec_mm : ndarray, shape (3,), mm
        Board origin in the camera frame.

    Returns
    -------
    ndarray, shape (3, 3)
        ``H = K [r1 r2 t]``, normalised so ``H[2, 2] = 1``.
    """
    rotation = rotation_matrix(np.asarray(rvec, dtype=float))
    camera = np.array([[focal_px, 0, centre_px[0]], [0, focal_px, centre_px[1]], [0, 0, 1.0]])
    homography = camera @ np.column_stack(
        [rotation[:, 0], rotation[:, 1], np.asarray(tvec_mm, float)]
    )
    return homography / homography[2, 2]


def apply_homography(homography: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Map points of shape (..., 2) by a 3x3 homography."""
    ones = np.ones(xy.shape[:-1] + (1,))
    mapped = np.concatenate([xy, ones], axis=-1) @ homography.T
    return mapped[..., :2] / mapped[..., 2:3]


def _chessboard_texture(spec: ChessboardSpec, margin_squares: float) -> Texture:
    square = spec.square_mm

    def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # Square (i, j) spans [(i-1) s, i s) in x; inner corner (c, r) sits at (c s, r s).
        i = np.floor(x / square) + 1
        j = np.floor(y / square) + 1
        on_squares = (i >= 0) & (i <= spec.cols) & (j >= 0) & (j <= spec.rows)
        dark = ((i + j) % 2 == 0) & on_squares
        value = np.where(dark, BLACK_LEVEL, WHITE_LEVEL)
        lo_x, hi_x = -square * (1 + margin_squares), square * (spec.cols + margin_squares)
        lo_y, hi_y = -square * (1 + margin_squares), square * (spec.rows + margin_squares)
        on_board = (x >= lo_x) & (x < hi_x) & (y >= lo_y) & (y < hi_y)
        return np.where(on_board, value, BACKGROUND_LEVEL)

    return texture


def _charuco_texture(spec: CharucoSpec, margin_squares: float) -> Texture:
    texels = CHARUCO_TEXELS_PER_SQUARE
    from endomeasure.features.charuco import opencv_charuco_board

    board = opencv_charuco_board(spec)
    image = board.generateImage(
        (spec.squares_x * texels, spec.squares_y * texels), marginSize=0, borderBits=1
    )
    levels = np.where(image > 127, WHITE_LEVEL, BLACK_LEVEL)
    square = spec.square_mm
    height, width = levels.shape

    def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # Board-frame origin is inner corner 0, one square in from the outer corner.
        tx = np.floor((x / square + 1.0) * texels).astype(np.int64)
        ty = np.floor((y / square + 1.0) * texels).astype(np.int64)
        inside = (tx >= 0) & (tx < width) & (ty >= 0) & (ty < height)
        value = levels[np.clip(ty, 0, height - 1), np.clip(tx, 0, width - 1)]
        value = np.where(inside, value, WHITE_LEVEL)
        lo_x, hi_x = -square * (1 + margin_squares), square * (spec.squares_x - 1 + margin_squares)
        lo_y, hi_y = -square * (1 + margin_squares), square * (spec.squares_y - 1 + margin_squares)
        on_board = (x >= lo_x) & (x < hi_x) & (y >= lo_y) & (y < hi_y)
        return np.where(on_board, value, BACKGROUND_LEVEL)

    return texture


def _board_outline(spec: BoardSpec, margin_squares: float = 1.0) -> np.ndarray:
    """The four outer corners of the board with its margin, shape (4, 2), mm."""
    square = spec.square_mm
    lo = -square * (1 + margin_squares)
    hi_x = square * (spec.cols + margin_squares)
    hi_y = square * (spec.rows + margin_squares)
    return np.array([[lo, lo], [hi_x, lo], [hi_x, hi_y], [lo, hi_y]])


def board_texture(spec: BoardSpec, margin_squares: float = 1.0) -> Texture:
    """The board's reflectance as a function of board-frame mm, vectorised.

    Parameters
    ----------
    spec : ChessboardSpec or CharucoSpec
    margin_squares : float
        Width of the white margin around the squares, in squares.

    Returns
    -------
    callable ``(x, y) -> level``; arrays of any shape, mm -> grey level in [0, 1].
    """
    if isinstance(spec, ChessboardSpec):
        return _chessboard_texture(spec, margin_squares)
    return _charuco_texture(spec, margin_squares)


@dataclasses.dataclass(frozen=True)
class SyntheticSplitImage:
    """A rendered split image with its exact answer.

    Attributes
    ----------
    image : ndarray, shape (height, width), uint8
    split : int
        First column of the right half.
    true_pixels : dict Half -> ndarray, shape (n_corners, 2), px
        True full-image pixel of every board corner (in id order) in each half, NaN where
        the corner falls outside that half.
    homographies : dict Half -> ndarray, shape (3, 3)
    """

    image: np.ndarray
    split: int
    true_pixels: dict
    homographies: dict


def render_split_image(
    spec: BoardSpec,
    homographies: dict,
    image_size: tuple[int, int],
    split: int,
    *,
    supersample: int = 4,
    blur_sigma_px: float = 0.7,
    noise_sigma: float = 0.0,
    band_halfwidth_px: float = 12.0,
    band_depth: float = 0.9,
    rng: np.random.Generator | None = None,
    exact_float: bool = False,
) -> SyntheticSplitImage:
    """Render a board into both halves of a split image, each half by its own homography.

    Parameters
    ----------
    spec : ChessboardSpec or CharucoSpec
    homographies : dict Half -> ndarray shape (3, 3)
        Board mm -> full-image px for each half; a half missing from the dict shows only
        background.
    image_size : (width, height), px
    split : int
        First column of the right half.
    supersample : int
        Point samples per pixel side.
    blur_sigma_px : float, px
        Gaussian blur of the whole image (optics); 0 for none.
    noise_sigma : float
        Standard deviation of additive Gaussian noise, in grey levels of 0..255.
    band_halfwidth_px : float, px
        Half width of the dark band at the split (the prism apex); 0 for none.
    band_depth : float
        How much of the light the band's centre removes (0..1).
    rng : numpy Generator, optional
        Needed when ``noise_sigma > 0``.
    exact_float : bool
        Return a float64 image in 0..255 without quantisation (for tests of refinement).

    Returns
    -------
    SyntheticSplitImage
    """
    width, height = image_size
    texture = board_texture(spec)
    image = np.full((height, width), BACKGROUND_LEVEL)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    n_points = spec.cols * spec.rows
    board_xy = spec.object_points[:, :2]
    true_pixels = {}
    for half in (Half.LEFT, Half.RIGHT):
        col_lo, col_hi = (0, split) if half is Half.LEFT else (split, width)
        homography = homographies.get(half)
        if homography is None:
            true_pixels[half] = np.full((n_points, 2), np.nan)
            continue
        inverse = np.linalg.inv(homography)
        # Only the board's footprint needs point sampling; the rest is background.
        outline = apply_homography(homography, _board_outline(spec))
        box_lo = np.floor(outline.min(axis=0)).astype(int) - 2
        box_hi = np.ceil(outline.max(axis=0)).astype(int) + 3
        cols = np.arange(max(col_lo, box_lo[0]), min(col_hi, box_hi[0]))
        rows = np.arange(max(0, box_lo[1]), min(height, box_hi[1]))
        if len(cols) == 0 or len(rows) == 0:
            cols = rows = np.arange(0)
        # Render row blocks to bound memory: (rows, cols, s, s) samples at a time.
        block = max(1, 2_000_000 // max(1, len(cols) * supersample * supersample))
        for start in range(0, len(rows), block):
            r = rows[start : start + block]
            u = cols[None, :, None, None] + offsets[None, None, None, :]
            v = r[:, None, None, None] + offsets[None, None, :, None]
            u, v = np.broadcast_arrays(u, v)
            board = apply_homography(inverse, np.stack([u, v], axis=-1))
            # Points behind the camera map to w < 0; they never occur for the poses used.
            levels = texture(board[..., 0], board[..., 1])
            image[r[0] : r[-1] + 1, cols[0] : cols[-1] + 1] = levels.mean(axis=(2, 3))
        pixels = apply_homography(homography, board_xy)
        inside = (pixels[:, 0] >= col_lo - 0.5) & (pixels[:, 0] < col_hi - 0.5)
        inside &= (pixels[:, 1] >= -0.5) & (pixels[:, 1] < height - 0.5)
        pixels[~inside] = np.nan
        true_pixels[half] = pixels
    if band_halfwidth_px > 0:
        u = np.arange(width) - (split - 0.5)
        image = image * (1.0 - band_depth * np.exp(-0.5 * (u / band_halfwidth_px) ** 2))[None, :]
    if blur_sigma_px > 0:
        from scipy.ndimage import gaussian_filter

        image = gaussian_filter(image, blur_sigma_px, mode="nearest")
    image = image * 255.0
    if noise_sigma > 0:
        if rng is None:
            raise ValueError("noise_sigma > 0 needs an rng")
        image = image + rng.normal(0.0, noise_sigma, image.shape)
    if not exact_float:
        image = np.clip(np.round(image), 0, 255).astype(np.uint8)
    return SyntheticSplitImage(
        image=image, split=split, true_pixels=true_pixels, homographies=dict(homographies)
    )
