"""Synthetic split images with exactly known corners, shared by the feature tests."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.synthetic import homography_from_pose, render_split_image
from endomeasure.geometry.rotations import rotation_matrix

IMAGE_SIZE = (640, 480)
SPLIT = 320
FOCAL_PX = 420.0
CHESSBOARD = "chessboard:9x6:1.0"


def pose_homographies(
    roll_deg: float = 5.0,
    tilt_deg: tuple[float, float] = (12.0, -15.0),
    distance_mm: float = 16.0,
    split: int = SPLIT,
    image_size: tuple[int, int] = IMAGE_SIZE,
    board_centre_mm: tuple[float, float] = (4.0, 2.5),
    focal_px: float = FOCAL_PX,
) -> dict:
    """Homographies of one board pose seen by two pinholes 1.2 mm apart (left, right).

    The board point ``board_centre_mm`` is placed on the axis of each half's camera, whose
    principal point is the centre of that half.
    """
    width, height = image_size
    rvec = np.radians([tilt_deg[0], tilt_deg[1], roll_deg])
    out = {}
    for half, baseline, centre_u in (
        (Half.LEFT, -0.6, split / 2),
        (Half.RIGHT, 0.6, split + (width - split) / 2),
    ):
        # Board origin such that board_centre_mm lands at (baseline offset, 0, distance).
        rotation = rotation_matrix(rvec)
        centre_cam = np.array([-baseline, 0.0, distance_mm])
        tvec = centre_cam - rotation @ np.array([*board_centre_mm, 0.0])
        out[half] = homography_from_pose(focal_px, (centre_u, height / 2), rvec, tvec)
    return out


def render(board: str = CHESSBOARD, noise: float = 0.0, rng=None, **pose) -> object:
    spec = parse_board_spec(board)
    if "board_centre_mm" not in pose:
        pose["board_centre_mm"] = (
            (spec.cols - 1) * spec.square_mm / 2,
            (spec.rows - 1) * spec.square_mm / 2,
        )
    return render_split_image(
        spec,
        pose_homographies(**pose),
        IMAGE_SIZE,
        SPLIT,
        noise_sigma=noise,
        rng=rng,
        blur_sigma_px=0.8,
    )


@pytest.fixture(scope="module")
def chessboard_render():
    """A noise-free render of the 9x6 board in both halves."""
    return render()
