"""Reading the frames of a video file (whatever ``cv2.VideoCapture`` decodes).

A video is read front to back, never by seeking (frame-exact seeking is unreliable for
many codecs), so the frame numbers are the positions in the decoded stream, from 0.
A file that cannot be opened, has no frame, or ends before the frame count its header
promises is bad input: a truncated clip would otherwise give a silently shorter set.

:func:`video_records` turns a clip into the image records a session stores, every N-th
frame or the frames a pick chooses; the pick itself is passed in (``add-images`` and
``detect`` pass :func:`endomeasure.features.frames.pick_from_clip`), so this module
reads files and knows no detector.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.io.image_header import checked_image_size
from endomeasure.io.outputs import file_kind

__all__ = [
    "VIDEO_SUFFIXES",
    "VideoInfo",
    "VideoSummary",
    "is_video_file",
    "read_frames",
    "video_info",
    "video_records",
]

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
        what = "no such video file"
        if os.path.exists(path):
            what = f"a {file_kind(os.stat(path).st_mode)}, not a video file"
        raise BadInputError(what, path=str(path))
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


@dataclass(frozen=True)
class VideoSummary:
    """What was taken from one video.

    Attributes
    ----------
    path : str
    frames : int
        Frames decoded.
    picked : list of int
        Frame numbers stored.
    split : int or None, px
        The split the halves were checked with (None with a frame step).
    reference_blur_px : float or None, px
        The clip's sharp reference edge blur (automatic pick only).
    left_out : dict of str -> int
        Frames not kept, by reason (automatic pick only).
    """

    path: str
    frames: int
    picked: list[int]
    split: int | None = None
    reference_blur_px: float | None = None
    left_out: dict[str, int] = field(default_factory=dict)


def _size_check(size: tuple[int, int], image_size, path: str) -> None:
    checked_image_size(size, path)  # the limits, from the container before any decoding
    if image_size is not None and size != tuple(image_size):
        raise BadInputError(
            f"the video's frames are {size[0]}x{size[1]} px but the session's images are "
            f"{image_size[0]}x{image_size[1]} px",
            path=path,
            hint="a session holds images of one sensor; use another session",
        )


def video_records(
    path: str | os.PathLike,
    image_set: str,
    *,
    pick: Callable[..., Any] | None = None,
    frame_step: int | None = None,
    image_size: tuple[int, int] | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> tuple[list, VideoSummary]:
    """The frames of a video worth keeping, as image records named ``<stem>_f<NNNNNN>``.

    Parameters
    ----------
    path : path-like
    image_set : str
    pick : callable(read, total, progress) -> ClipPick, optional
        Chooses the frames (:func:`endomeasure.features.frames.pick_from_clip` with its
        board and split bound); used unless ``frame_step`` is given.
    frame_step : int, optional
        Every N-th frame (0, N, 2N, ...) instead.
    image_size : (width, height), optional, px
        The session's image size the frames must have.
    on_progress : callable(done, total), optional
        After each frame of a pass over the clip.

    Returns
    -------
    list of ImageRecord, VideoSummary
        Each record keeps the video's path, its SHA-256 and the frame number.

    Raises
    ------
    BadInputError
        Unreadable or truncated video, frames of another size than ``image_size``, and
        whatever ``pick`` refuses.
    """
    import hashlib

    from endomeasure.io.session import ImageRecord

    if frame_step is None and pick is None:
        raise ValueError("video_records needs a pick or a frame step")
    path = os.fspath(path)
    info = video_info(path)
    if info.width > 0:
        _size_check((info.width, info.height), image_size, path)
    total = info.frame_count
    progress = on_progress or (lambda done, total: None)
    # the video file's SHA-256, as io.images gives an image file's (not imported from
    # there: io.images imports this module)
    with open(path, "rb") as stream:
        digest = hashlib.file_digest(stream, "sha256").hexdigest()
    stem = os.path.splitext(os.path.basename(path))[0]

    def record(index: int, pixels) -> ImageRecord:
        return ImageRecord(name=f"{stem}_f{index:06d}", pixels=pixels, original_path=path,
                           sha256=digest, image_set=image_set, frame=index)  # fmt: skip

    if frame_step is not None:
        step = int(frame_step)
        records = []
        for index, pixels in read_frames(path, keep=lambda i: i % step == 0):
            progress(index + 1, max(total, index + 1))
            records.append(record(index, pixels))
        frames = max(total, records[-1].frame + 1)
        summary = VideoSummary(path, frames, [r.frame for r in records])
    else:
        chosen = pick(lambda keep: read_frames(path, keep=keep), total, progress)
        summary = VideoSummary(path, chosen.frames, list(chosen.picked), chosen.split,
                               chosen.reference_blur_px, dict(chosen.left_out))  # fmt: skip
        wanted = set(summary.picked)
        records = [record(i, px) for i, px in read_frames(path, keep=wanted.__contains__)]
    _size_check((int(records[0].pixels.shape[1]), int(records[0].pixels.shape[0])),
                image_size, path)  # fmt: skip
    return records, summary
