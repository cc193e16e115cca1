"""Reading the frames of a video file (whatever ``cv2.VideoCapture`` decodes).

A video is read front to back, never by seeking (frame-exact seeking is unreliable for
many codecs), so the frame numbers are the positions in the decoded stream, from 0.
A file that cannot be opened, has no frame, or ends before the frame count its header
promises is bad input: a truncated clip would otherwise give a silently shorter set.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endomeasure.errors import BadInputError

__all__ = ["VIDEO_SUFFIXES", "VideoInfo", "is_video_file", "read_frames", "video_info"]

VIDEO_SUFFIXES = (
    ".avi", ".mp4", ".m4v", ".mkv", ".mov", ".mpg", ".mpeg", ".wmv", ".webm", ".mjpeg",
)  # fmt: skip
"""File types taken as video (matched case-insensitively)."""

ESTIMATED_COUNT_SUFFIXES = (".mkv", ".webm", ".mpg", ".mpeg")
"""Containers whose frame count OpenCV estimates from the duration (it may exceed the
frames by one); the others state it exactly, and every missing frame is truncation."""


def is_video_file(path: str | os.PathLike) -> bool:
    """Whether the path names a video file, by its suffix."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


@dataclass(frozen=True)
class VideoInfo:
    """A video's header: frame count (as the container states it), size and rate."""

    path: str
    frame_count: int
    width: int
    height: int
    fps: float


def _open(path: Path):
    import cv2

    if not path.is_file():
        raise BadInputError("no such video file", path=str(path))
    # Decoder complaints would only add lines to the one-line error the caller raises.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise BadInputError(
            "cannot open the video file",
            path=str(path),
            hint="give a video OpenCV can decode (.avi, .mp4, .mkv, .mov, .mpg, ...)",
        )
    return capture


def video_info(path: str | os.PathLike) -> VideoInfo:
    """The header of a video file.

    Raises
    ------
    BadInputError
        The file is missing or cannot be opened.
    """
    import cv2

    path = Path(path)
    capture = _open(path)
    try:
        return VideoInfo(
            path=str(path),
            frame_count=max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0),
            width=int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
            height=int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            fps=float(capture.get(cv2.CAP_PROP_FPS)),
        )
    finally:
        capture.release()


def read_frames(
    path: str | os.PathLike, keep: Callable[[int], bool] | None = None
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(frame number, pixels)`` for the frames of a video, in order.

    Parameters
    ----------
    path : path-like
    keep : callable(frame number) -> bool, optional
        Decode and yield only the frames it accepts (the others are only stepped over);
        all by default.

    Yields
    ------
    (int, ndarray)
        The frame number from 0 and its pixels, shape (H, W) or (H, W, 3), uint8 or
        uint16, colour in OpenCV's BGR order.

    Raises
    ------
    BadInputError
        The file cannot be opened, holds no frame, ends before the frame count of its
        header (truncated), or changes frame size.
    """
    import cv2

    path = Path(path)
    capture = _open(path)
    try:
        promised = max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
        index, shape = 0, None
        while True:
            if keep is not None and not keep(index):
                if not capture.grab():
                    break
                index += 1
                continue
            ok, frame = capture.read()
            if not ok or frame is None:
                break
            if frame.ndim == 3 and frame.shape[2] == 1:
                frame = frame[:, :, 0]
            if shape is None:
                shape = frame.shape
            elif frame.shape != shape:
                raise BadInputError(
                    f"frame {index} is {frame.shape[1]}x{frame.shape[0]} px, the first "
                    f"{shape[1]}x{shape[0]} px",
                    path=str(path),
                )
            yield index, np.ascontiguousarray(frame)
            index += 1
    finally:
        capture.release()
    if index == 0:
        raise BadInputError(
            "the video holds no readable frame",
            path=str(path),
            hint="check that the file is a complete video",
        )
    slack = 1 if path.suffix.lower() in ESTIMATED_COUNT_SUFFIXES else 0
    if index + slack < promised:
        raise BadInputError(
            f"the video is truncated or damaged: {index} of its {promised} frames are readable",
            path=str(path),
            hint="copy the complete file again",
        )
