"""A small calibration clip for the video tests: a chessboard moving in front of a split
image, rendered by the analytic renderer (exact corners), with motion-blurred frames and
a frame whose board is half outside the right view, written by ``cv2.VideoWriter``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endomeasure.conventions import Half
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.synthetic import homography_from_pose, render_split_image
from endomeasure.geometry.rotations import rotation_matrix

BOARD = "chessboard:7x5:1.0"
IMAGE_SIZE = (480, 320)
SPLIT = 240
FOCAL_PX = 300.0
NOISE_SIGMA = 2.0
BLUR_SUBFRAMES = 5
"""Renders averaged along the motion for one motion-blurred frame."""


@dataclass(frozen=True)
class Clip:
    path: Path
    kinds: list[str]
    """Per frame: ``sharp`` (a new pose), ``held`` (the previous pose again), ``blurred``
    (moving during the exposure) or ``half-outside`` (the board leaves the right view)."""
    poses: list[int]
    """Per frame: the key pose it shows (-1 for the half-outside frame)."""

    def frames(self, kind: str) -> list[int]:
        return [i for i, k in enumerate(self.kinds) if k == kind]


def _homographies(pose: tuple[float, float, float, float]) -> dict:
    """Two pinholes 1.2 mm apart, each half's principal point at its centre; the pose is
    (board centre x mm, y mm, distance mm, roll deg)."""
    spec = parse_board_spec(BOARD)
    x, y, z, roll = pose
    width, height = IMAGE_SIZE
    rvec = np.radians([8.0, -6.0, roll])
    rotation = rotation_matrix(rvec)
    centre_board = np.array([(spec.cols - 1) / 2 * spec.square_mm,
                             (spec.rows - 1) / 2 * spec.square_mm, 0.0])  # fmt: skip
    out = {}
    for half, baseline, centre_u in ((Half.LEFT, -0.6, SPLIT / 2),
                                     (Half.RIGHT, 0.6, SPLIT + (width - SPLIT) / 2)):  # fmt: skip
        tvec = np.array([x - baseline, y, z]) - rotation @ centre_board
        out[half] = homography_from_pose(FOCAL_PX, (centre_u, height / 2), rvec, tvec)
    return out


def _render(pose, rng, subframes: int = 1, travel=(0.0, 0.0)) -> np.ndarray:
    """A frame at ``pose``, averaged over ``subframes`` renders moved along ``travel`` mm."""
    spec = parse_board_spec(BOARD)
    images = []
    for s in np.linspace(-0.5, 0.5, subframes) if subframes > 1 else [0.0]:
        moved = (pose[0] + s * travel[0], pose[1] + s * travel[1], *pose[2:])
        rendered = render_split_image(spec, _homographies(moved), IMAGE_SIZE, SPLIT,
                                      blur_sigma_px=0.7, exact_float=True)  # fmt: skip
        images.append(rendered.image)
    image = np.mean(images, axis=0) + rng.normal(0.0, NOISE_SIGMA, images[0].shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


KEY_POSES = [(0.0, 0.0, 16.0, 0.0), (1.8, 1.2, 19.0, 10.0), (0.0, -1.2, 14.0, -20.0),
             (1.5, -1.5, 24.0, -12.0)]  # fmt: skip
"""Board centre x, y (mm), distance (mm) and roll (deg) of the poses held still."""


def write_clip(path: Path, rng: np.random.Generator, colour: bool = True) -> Clip:
    """The clip: each key pose held for two frames, a motion-blurred frame (the board
    moving 0.5 mm, about 9 px, during the exposure) after each, and one frame with the
    board half outside the right view."""
    import cv2

    frames, kinds, poses = [], [], []
    for k, pose in enumerate(KEY_POSES):
        frames += [_render(pose, rng), _render(pose, rng)]
        kinds += ["sharp", "held"]
        travel = (0.5, 0.0) if k % 2 == 0 else (0.0, 0.5)  # across one edge family
        frames.append(_render(pose, rng, BLUR_SUBFRAMES, travel))
        kinds.append("blurred")
        poses += [k, k, k]
        if k == 1:
            frames.append(_render((-2.6, 0.0, 16.0, 0.0), rng))
            kinds.append("half-outside")
            poses.append(-1)
    fourcc = cv2.VideoWriter_fourcc(*"MJPG")
    writer = cv2.VideoWriter(str(path), fourcc, 10.0, IMAGE_SIZE, isColor=colour)
    assert writer.isOpened()
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if colour else frame)
    writer.release()
    return Clip(Path(path), kinds, poses)
