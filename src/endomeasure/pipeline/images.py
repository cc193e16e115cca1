"""``endomeasure add-images``: embed image files, or frames picked from videos, in a
session (creating it if needed)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

from endomeasure.errors import BadInputError
from endomeasure.io.images import find_image_files, read_image_file, sha256_of_file
from endomeasure.io.session import ImageRecord, edit_session, open_session
from endomeasure.io.video import is_video_file

__all__ = ["AddImagesReport", "VideoSummary", "add_images", "video_records"]

SPLIT_SAMPLE_FRAMES = 16
"""Frames spread over a clip whose prism band gives the split when none is known."""


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


@dataclass(frozen=True)
class AddImagesReport:
    """What :func:`add_images` did.

    Attributes
    ----------
    session : str
    image_set : str
    added : list of str
        Names of the images embedded now.
    unchanged : list of str
        Images already in the session with the same SHA-256.
    image_size : [width, height] or None, px
        The session's image size afterwards.
    videos : list of VideoSummary
        One per video given.
    """

    session: str
    image_set: str
    added: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    image_size: list[int] | None = None
    videos: list[VideoSummary] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def add_images(
    session_path: str | os.PathLike,
    paths: Iterable[str | os.PathLike],
    image_set: str,
    on_progress: Callable[[int, int], None] | None = None,
    *,
    board: str | None = None,
    frame_step: int | None = None,
    split: int | None = None,
) -> AddImagesReport:
    """Embed image files (or the images in directories) and frames of videos in a
    session, in one atomic edit.

    Parameters
    ----------
    session_path : path-like
        Created when missing (with no images if ``paths`` is empty).
    paths : iterable of path-like
        Image files, directories of images (not searched recursively) and video files
        (:data:`endomeasure.io.video.VIDEO_SUFFIXES`).
    image_set : str
        ``calib``, ``test`` or ``scene``.
    on_progress : callable(done, total), optional
        Called after each file is read, and after each frame of a video (once per pass).
    board : str, optional
        Board spec for picking video frames; default: the session's only board.
    frame_step : int, optional
        Take every ``frame_step``-th frame of a video (0, N, 2N, ...) instead of picking.
    split : int, optional, px
        Split for checking the halves of video frames; default: the session's, else
        found from the clip's prism band.

    Raises
    ------
    BadInputError
        Unreadable files, two files with one name, or images of different sizes (all
        images of a session come from one sensor, so they share one size); for videos:
        an unreadable or truncated file, no board to pick with, no frame worth keeping.
    """
    if frame_step is not None and int(frame_step) < 1:
        raise BadInputError(f"--frame-step must be at least 1, not {frame_step}")
    paths = list(paths)
    videos = [p for p in paths if is_video_file(p) and not os.path.isdir(p)]
    files = find_image_files([p for p in paths if not (is_video_file(p) and not os.path.isdir(p))])
    records = []
    for done, path in enumerate(files, start=1):
        records.append(read_image_file(path, image_set))
        if on_progress is not None:
            on_progress(done, len(files))
    summaries = []
    if videos:
        stored_size, stored_split, stored_board = _session_facts(session_path)
        size = stored_size or (
            (int(records[0].pixels.shape[1]), int(records[0].pixels.shape[0])) if records else None
        )
        for video in videos:
            frames, summary = video_records(
                video, image_set, board=board or stored_board, frame_step=frame_step,
                split=split if split is not None else stored_split, image_size=size,
                on_progress=on_progress,
            )  # fmt: skip
            records.extend(frames)
            summaries.append(summary)
            size = size or (int(frames[0].pixels.shape[1]), int(frames[0].pixels.shape[0]))

    names: dict[str, str] = {}
    for rec in records:
        if rec.name in names:
            raise BadInputError(
                f"two files give the image name {rec.name!r}: {names[rec.name]} and "
                f"{rec.original_path}",
                hint="rename one of them",
            )
        names[rec.name] = rec.original_path

    with edit_session(session_path, create=True) as session:
        size = session.metadata().image_size
        for rec in records:
            rec_size = (int(rec.pixels.shape[1]), int(rec.pixels.shape[0]))
            if size is None:
                size = rec_size
            elif rec_size != size:
                raise BadInputError(
                    f"image is {rec_size[0]}x{rec_size[1]} px but the session's images are "
                    f"{size[0]}x{size[1]} px",
                    path=rec.original_path,
                    hint="a session holds images of one sensor; use another session",
                )
        if size is not None:
            session.set_metadata(image_size=size)
        added = session.write_images(records)
    added_set = set(added)
    return AddImagesReport(
        session=str(session_path),
        image_set=image_set,
        added=added,
        unchanged=[rec.name for rec in records if rec.name not in added_set],
        image_size=None if size is None else list(size),
        videos=summaries,
    )


def _session_facts(session_path) -> tuple[tuple[int, int] | None, int | None, str | None]:
    """The session's image size, split and only board spec (None where unknown)."""
    if not os.path.exists(session_path):
        return None, None, None
    with open_session(session_path) as session:
        meta = session.metadata()
        boards = session.boards()
        spec = next(iter(boards.values())).spec if len(boards) == 1 else None
        size = None if meta.image_size is None else tuple(int(n) for n in meta.image_size)
        return size, meta.split, spec


def video_records(
    path: str | os.PathLike,
    image_set: str,
    *,
    board: str | None = None,
    frame_step: int | None = None,
    split: int | None = None,
    image_size: tuple[int, int] | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> tuple[list[ImageRecord], VideoSummary]:
    """The frames of a video worth keeping, as image records named ``<stem>_f<NNNNNN>``.

    With ``frame_step`` every N-th frame; otherwise frames picked by
    :func:`endomeasure.features.frames.pick_frames` (sharp, the whole board in both
    halves, distinct poses), which needs ``board``. Each record keeps the video's path,
    its SHA-256 and the frame number.

    Raises
    ------
    BadInputError
        Unreadable or truncated video, frames of another size than ``image_size``, no
        board spec for the pick, no split found, or no frame worth keeping.
    """
    from endomeasure.io.video import read_frames, video_info

    path = os.fspath(path)
    info = video_info(path)
    if image_size is not None and info.width > 0 and (info.width, info.height) != tuple(image_size):
        raise BadInputError(
            f"the video's frames are {info.width}x{info.height} px but the session's images "
            f"are {image_size[0]}x{image_size[1]} px",
            path=path,
            hint="a session holds images of one sensor; use another session",
        )
    total = info.frame_count
    progress = on_progress or (lambda done, total: None)
    digest = sha256_of_file(path)
    stem = os.path.splitext(os.path.basename(path))[0]

    def record(index: int, pixels) -> ImageRecord:
        return ImageRecord(name=f"{stem}_f{index:06d}", pixels=pixels, original_path=path,
                           sha256=digest, image_set=image_set, frame=index)  # fmt: skip

    if frame_step is not None:
        step = int(frame_step)
        frames = read_frames(path, keep=lambda i: i % step == 0)
        records = [record(i, px) for i, px in _with_progress(frames, total, progress)]
        summary = VideoSummary(path, max(total, records[-1].frame + 1), [r.frame for r in records])
    else:
        summary = _pick(path, board, split, total, progress)
        wanted = set(summary.picked)
        records = [record(i, px) for i, px in read_frames(path, keep=wanted.__contains__)]
    size = (int(records[0].pixels.shape[1]), int(records[0].pixels.shape[0]))
    if image_size is not None and size != tuple(image_size):
        raise BadInputError(
            f"the video's frames are {size[0]}x{size[1]} px but the session's images are "
            f"{image_size[0]}x{image_size[1]} px",
            path=path,
            hint="a session holds images of one sensor; use another session",
        )
    return records, summary


def _with_progress(frames, total: int, progress):
    """Pass the frames on, reporting each one to ``progress(done, total)``."""
    for index, pixels in frames:
        progress(index + 1, max(total, index + 1))
        yield index, pixels


def _pick(path: str, board: str | None, split: int | None, total: int, progress) -> VideoSummary:
    """Pass 1 (when the split is unknown): the split from frames spread over the clip;
    pass 2: every frame's fast check and blur; then the pick."""
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.features.detect import to_gray_u8
    from endomeasure.features.frames import frame_evidence, pick_frames
    from endomeasure.io.video import read_frames

    if board is None:
        raise BadInputError(
            "picking frames from a video needs the board",
            path=path,
            hint="give --board SPEC, or --frame-step N to take every N-th frame",
        )
    spec = parse_board_spec(board)
    if split is None:
        from endomeasure.features.split import find_split_in_set, split_evidence

        every = max(1, total // SPLIT_SAMPLE_FRAMES)
        sample = read_frames(path, keep=lambda i: i % every == 0)
        evidence = [split_evidence(pixels) for _, pixels in sample]
        split = find_split_in_set(evidence, path=path).split
    evidence, size = [], None
    for index, pixels in _with_progress(read_frames(path), total, progress):
        size = (int(pixels.shape[1]), int(pixels.shape[0]))
        if not 0 < split < size[0]:
            raise BadInputError(
                f"split column {split} is outside the video's frames (width {size[0]} px)",
                path=path,
            )
        evidence.append(frame_evidence(index, to_gray_u8(pixels), split, spec))
    pick = pick_frames(evidence, size)
    left_out = {
        reason: pick.count(reason)
        for reason in ("board not fully seen", "blurred", "pose too close to a kept frame")
    }
    if not pick.picked:
        raise BadInputError(
            f"no frame of the video shows the whole board {spec.canonical()} sharp in both "
            f"halves ({len(evidence)} frames: board not fully seen in "
            f"{left_out['board not fully seen']}, blurred {left_out['blurred']})",
            path=path,
            hint="check the --board spec and the --split, or give --frame-step N",
        )
    reference = pick.reference_blur_px
    return VideoSummary(path, len(evidence), pick.picked, int(split), float(reference), left_out)
