"""``endomeasure add-images``: embed image files, or frames picked from videos, in a
session (creating it if needed)."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from endomeasure.errors import BadInputError
from endomeasure.io.images import IMAGE_SUFFIXES, find_image_files, read_image_file
from endomeasure.io.outputs import checked_session_target
from endomeasure.io.session import IMAGE_SETS, ImageRecord, edit_session, open_session
from endomeasure.io.video import VideoSummary, is_video_file

__all__ = ["AddImagesReport", "FailedFile", "VideoSummary", "add_images", "video_records"]


@dataclass(frozen=True)
class FailedFile:
    """An image file given to :func:`add_images` that was not embedded, and why."""

    path: str
    error: str
    hint: str = ""


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
    failed : list of FailedFile
        The files that could not be used (the others were embedded).
    """

    session: str
    image_set: str
    added: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    image_size: list[int] | None = None
    videos: list[VideoSummary] = field(default_factory=list)
    failed: list[FailedFile] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """0 every file embedded (or already there), 1 some could not be used."""
        return 1 if self.failed else 0

    @property
    def failure(self) -> str:
        """How many files could not be used and their most frequent reasons ('' if none)."""
        if not self.failed:
            return ""
        return f"{len(self.failed)} image file(s) could not be used: {_reasons(self.failed)}"

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "exit_code": self.exit_code}


def _reasons(failed: list[FailedFile]) -> str:
    """The three most frequent reasons of ``failed``, with their counts."""
    counts: dict[str, int] = {}
    for item in failed:
        counts[item.error] = counts.get(item.error, 0) + 1
    common = sorted(counts.items(), key=lambda item: -item[1])[:3]
    return ", ".join(f"{why} ({n})" for why, n in common)


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

    A file that cannot be used (unreadable, not an image, beyond the size limits, of
    another size than the session's images, a second file with one name, a different
    image under a name the session holds) is left out and listed in the report's
    ``failed``; the others are embedded, as ``detect`` does. Nothing usable at all is an
    error, and then no session is created.

    Parameters
    ----------
    session_path : path-like
        Created when missing.
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
        No image given, folders without image files, or no file usable (the reason of
        the one file, or the most frequent ones); for videos (all or nothing): an
        unreadable or truncated file, frames of another size, no board to pick with, no
        frame worth keeping.
    """
    if frame_step is not None and int(frame_step) < 1:
        raise BadInputError(f"--frame-step must be at least 1, not {frame_step}")
    if image_set not in IMAGE_SETS:
        raise BadInputError(
            f"unknown image set {image_set!r}", hint=f"use one of {', '.join(IMAGE_SETS)}"
        )
    checked_session_target(session_path, create=True)  # before reading any image
    paths = list(paths)
    if not paths:
        raise BadInputError(
            "no image given", hint="give image files, folders of images or video files"
        )
    videos = [p for p in paths if is_video_file(p) and not os.path.isdir(p)]
    files, failed = _expand([p for p in paths if not (is_video_file(p) and not os.path.isdir(p))])
    if not files and not videos and not failed:
        raise BadInputError(
            "no image file in " + ", ".join(os.fspath(p) for p in paths),
            hint=f"a folder contributes its {', '.join(IMAGE_SUFFIXES)} files (not subfolders)",
        )
    stored_size, stored_split, stored_board, stored_images = _session_facts(session_path)
    records = _read_files(files, image_set, stored_size, failed, on_progress)
    summaries = []
    if videos:
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
    records = _distinct(records, stored_images, failed)
    if not records:
        raise _nothing_usable(failed)

    with edit_session(session_path, create=True) as session:
        size = session.metadata().image_size
        for rec in records:
            rec_size = (int(rec.pixels.shape[1]), int(rec.pixels.shape[0]))
            if size is None:
                size = rec_size
            elif rec_size != size:  # another command stored other images meanwhile
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
        failed=failed,
    )


def _read_files(files, image_set, size, failed, on_progress) -> list[ImageRecord]:
    """The image records of the files that can be used; the others go to ``failed``.
    Each file's size is read from its header, before decoding, and must be ``size`` (the
    session's), else the first usable file's."""
    records = []
    for done, path in enumerate(files, start=1):
        try:
            record = read_image_file(path, image_set, expected_size=size)
        except BadInputError as exc:
            failed.append(FailedFile(str(path), exc.what, exc.hint or ""))
        else:
            records.append(record)
            size = size or (int(record.pixels.shape[1]), int(record.pixels.shape[0]))
        if on_progress is not None:
            on_progress(done, len(files))
    return records


def _expand(paths: list) -> tuple[list[Path], list[FailedFile]]:
    """The image files of each path (a folder gives its image files, as in ``detect``);
    a path that is missing, not an image file, or a FIFO is a failure of its own."""
    files, failed = [], []
    for raw in paths:
        try:
            files.extend(find_image_files([raw]))
        except BadInputError as exc:
            failed.append(FailedFile(os.fspath(raw), exc.what, exc.hint or ""))
    return files, failed


def _distinct(records: list, stored_images: dict[str, str], failed: list) -> list:
    """``records`` without a second file of one name, nor a different image under a name
    the session holds (those go to ``failed``)."""
    kept, names = [], {}
    for rec in records:
        problem = ""
        if rec.name in names:
            problem = f"two files give the image name {rec.name!r} (the other is {names[rec.name]})"
        elif rec.name in stored_images and stored_images[rec.name] != rec.sha256:
            problem = f"the session already holds a different image named {rec.name!r}"
        if problem:
            failed.append(FailedFile(rec.original_path, problem))
            continue
        names[rec.name] = rec.original_path
        kept.append(rec)
    return kept


def _nothing_usable(failed: list[FailedFile]) -> BadInputError:
    """The refusal when no file could be used: the one file's own reason, or a count."""
    if len(failed) == 1:
        return BadInputError(failed[0].error, path=failed[0].path, hint=failed[0].hint or None)
    return BadInputError(
        f"none of the {len(failed)} image files could be used: {_reasons(failed)}",
        hint="nothing was stored",
    )


def _session_facts(
    session_path,
) -> tuple[tuple[int, int] | None, int | None, str | None, dict[str, str]]:
    """The session's image size, split and only board spec (None where unknown), and the
    SHA-256 of each stored image by name."""
    if not os.path.exists(session_path):
        return None, None, None, {}
    with open_session(session_path) as session:
        meta = session.metadata()
        boards = session.boards()
        spec = next(iter(boards.values())).spec if len(boards) == 1 else None
        size = None if meta.image_size is None else tuple(int(n) for n in meta.image_size)
        images = {info.name: info.sha256 for info in session.images_info()}
        return size, meta.split, spec, images


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
    :func:`endomeasure.features.frames.pick_from_clip` (sharp, the whole board in both
    halves, distinct poses), which needs ``board``; the split is found from the clip
    when None. Each record keeps the video's path, its SHA-256 and the frame number
    (:func:`endomeasure.io.video.video_records`; ``detect`` makes the same call).

    Raises
    ------
    BadInputError
        Unreadable or truncated video, frames of another size than ``image_size``, no
        board spec for the pick, no split found, or no frame worth keeping.
    """
    from endomeasure.features.frames import pick_from_clip
    from endomeasure.io.video import video_records as records_of_video

    pick = functools.partial(pick_from_clip, board=board, split=split, path=os.fspath(path))
    return records_of_video(path, image_set, pick=pick, frame_step=frame_step,
                            image_size=image_size, on_progress=on_progress)  # fmt: skip
