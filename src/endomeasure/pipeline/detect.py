"""``endomeasure detect``: board corners in both halves of many images, into the session.

Steps: expand the given paths; take the frames of every video first (picked by
:func:`endomeasure.features.frames.pick_from_clip`, or every N-th, through
:func:`endomeasure.io.video.video_records`: what ``add-images`` does); read and decode
every image file (per-file errors are results, not exceptions); fix the split (the
session's stored split, a given column, or the band fitted to all images at once by
:func:`endomeasure.features.split.find_split_in_set`);
detect in both halves of every image (:func:`endomeasure.features.detect.detect_split_image`);
then store images, board, split and detections in one atomic session edit. Reading and
detection run in ``workers`` processes (``concurrent.futures.ProcessPoolExecutor``);
OpenCV's own threading is switched off in every process so that N workers use N cores.

Image status: ``ok`` (board in both halves), ``one-half`` (in one half only), ``failed``
(no board in either half, or the image could not be used: unreadable, not an image,
another size than the session's, a different image under a stored name).

A video is all or nothing: an unreadable or truncated clip, frames of another size than
the session's, no frame worth keeping, or no board in any frame taken is a
:class:`BadInputError` and nothing is stored (a damaged clip would otherwise give a
silently smaller set).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from endomeasure import defaults, interrupts
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError, EndomeasureError
from endomeasure.io.video import is_video_file

__all__ = ["DetectReport", "ImageResult", "detect_images"]

STATUS_OK, STATUS_ONE_HALF, STATUS_FAILED = "ok", "one-half", "failed"
QUALITY_KIND = "edge_width_px"
"""What a stored detection's ``quality`` is: the 10-90 % edge width at its corners, px."""


@dataclasses.dataclass(frozen=True)
class HalfSummary:
    """One half of one image in the report."""

    n_corners: int
    edge_width_px: float
    failure: str


@dataclasses.dataclass(frozen=True)
class ImageResult:
    """What happened to one input file.

    Attributes
    ----------
    path : str
    name : str
        Image name in the session ('' when the file could not be read).
    status : str
        ``ok``, ``one-half`` or ``failed``.
    error : str
        Why the image could not be used at all ('' otherwise).
    halves : dict of str to HalfSummary
        ``left`` / ``right``; empty when the image could not be used.
    frame : int or None
        Frame number in the video ``path`` for a frame of a video.
    """

    path: str
    name: str
    status: str
    error: str = ""
    halves: dict = dataclasses.field(default_factory=dict)
    frame: int | None = None


@dataclasses.dataclass(frozen=True)
class DetectReport:
    """The outcome of :func:`detect_images`.

    Attributes
    ----------
    session, board, board_name, image_set : str
    split : int or None, px
        The split used (None when no image could be read).
    split_source : str
        ``session`` (stored before), ``given`` or ``auto``.
    images : list of ImageResult
    stored : bool
        Whether the session was written (not when nothing usable was found).
    videos : list of VideoSummary
        What was taken from each video given (:class:`endomeasure.io.video.VideoSummary`).
    """

    session: str
    board: str
    board_name: str
    image_set: str
    split: int | None
    split_source: str
    images: list[ImageResult]
    stored: bool
    videos: list = dataclasses.field(default_factory=list)

    @property
    def counts(self) -> dict[str, int]:
        out = {STATUS_OK: 0, STATUS_ONE_HALF: 0, STATUS_FAILED: 0}
        for image in self.images:
            out[image.status] += 1
        return out

    @property
    def halves_found(self) -> tuple[int, int]:
        """(halves with the board, halves examined)."""
        examined = [h for image in self.images for h in image.halves.values()]
        return sum(1 for h in examined if not h.failure), len(examined)

    @property
    def exit_code(self) -> int:
        """0 all images usable, 1 some image failed, 2 nothing usable."""
        counts = self.counts
        if counts[STATUS_OK] + counts[STATUS_ONE_HALF] == 0:
            return 2
        return 1 if counts[STATUS_FAILED] else 0

    @property
    def failure(self) -> str:
        """Why the command did not fully succeed, in one sentence ('' when it did): how
        many images could not be used and their most frequent reasons."""
        code = self.exit_code
        if code == 0:
            return ""
        reasons: dict[str, int] = {}
        for image in self.images:
            if image.status != STATUS_FAILED:
                continue
            why = image.error or "; ".join(
                sorted({h.failure for h in image.halves.values() if h.failure})
            )
            reasons[why or "failed"] = reasons.get(why or "failed", 0) + 1
        common = sorted(reasons.items(), key=lambda item: -item[1])[:3]
        listed = ", ".join(f"{why} ({n})" for why, n in common)
        n_failed, n_all = self.counts[STATUS_FAILED], len(self.images)
        if code == 2:
            if n_all == 0:
                return "no image to detect in: the paths hold no image or video file"
            return f"nothing usable: none of the {n_all} image(s) showed the board: {listed}"
        return f"{n_failed} of {n_all} image(s) could not be used: {listed}"

    def to_dict(self) -> dict[str, Any]:
        found, examined = self.halves_found
        return {
            "session": self.session,
            "board": self.board,
            "board_name": self.board_name,
            "image_set": self.image_set,
            "split": self.split,
            "split_source": self.split_source,
            "stored": self.stored,
            "counts": self.counts,
            "halves_found": found,
            "halves_examined": examined,
            "exit_code": self.exit_code,
            "images": [
                {
                    "path": image.path,
                    "name": image.name,
                    "status": image.status,
                    "error": image.error,
                    "frame": image.frame,
                    "halves": {k: dataclasses.asdict(v) for k, v in image.halves.items()},
                }
                for image in self.images
            ],
            "videos": [dataclasses.asdict(v) for v in self.videos],
        }


# ----------------------------------------------------------------- worker functions


def _init_worker(parent_pid: int | None = None) -> None:
    """One OpenCV thread per process: parallelism comes from the process pool. In a pool
    worker (``parent_pid`` given) also: Ctrl-C and SIGTERM left to the parent, and death
    with the parent (:func:`endomeasure.interrupts.worker_initializer`)."""
    if parent_pid is not None:
        interrupts.worker_initializer(parent_pid)
    import cv2

    cv2.setNumThreads(1)
    # Per-file problems are reported per image; OpenCV's own warnings would only add noise.
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def _read_task(
    item,
    image_set: str,
    want_split: bool,
    board: str | None = None,
    split: int | None = None,
    method: str | None = None,
    expected_size: tuple[int, int] | None = None,
):
    """Read and decode one file (``item`` a path), or take a video's frame (``item`` its
    ImageRecord); gather its split evidence, or detect when the split is known. A file
    whose header gives another size than ``expected_size`` is not decoded.

    Never raises for a bad file: returns ``(path, record, split_evidence, error,
    detection)`` with ``error`` set instead.
    """
    from endomeasure.features.detect import detect_split_image
    from endomeasure.features.split import split_evidence
    from endomeasure.io.images import read_image_file

    if isinstance(item, str):
        path = item
        try:
            record = read_image_file(path, image_set, expected_size=expected_size)
        except EndomeasureError as exc:
            return path, None, None, exc.what, None
    else:
        record, path = item, item.original_path
    estimate = detection = None
    if want_split:
        try:
            estimate = split_evidence(record.pixels)
        except EndomeasureError:
            estimate = None
    if board is not None and split is not None and 0 < split < record.pixels.shape[1]:
        detection = detect_split_image(record.pixels, board, split, method=method)
    return path, record, estimate, "", detection


def _detect_task(name: str, pixels: np.ndarray, board: str, split: int, method: str | None):
    from endomeasure.features.detect import detect_split_image

    return name, detect_split_image(pixels, board, split, method=method)


class _Runner:
    """Runs tasks in this process (one worker) or in one process pool reused for all.

    Leaving it by an exception (Ctrl-C, SIGTERM, an error) ends the workers at once
    instead of waiting for their running tasks; workers ignore Ctrl-C themselves (the
    parent reports it) and die with the parent even when it is killed.
    """

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = None

    def __enter__(self) -> _Runner:
        _init_worker()
        if self.workers > 1:
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(
                max_workers=self.workers, initializer=_init_worker, initargs=(os.getpid(),)
            )
        return self

    def __exit__(self, exc_type, *exc_info) -> None:
        if self.pool is None:
            return
        pool, self.pool = self.pool, None
        if exc_type is not None:
            _end_pool(pool)
            return
        try:
            pool.shutdown(wait=True)
        except BaseException:  # interrupted while the idle workers were let go
            _end_pool(pool)
            raise

    def run(
        self, function: Callable, argument_lists: Sequence[tuple], on_done: Callable[[], None]
    ) -> list:
        """``function(*args)`` for each argument tuple, results in order."""
        if self.pool is None or len(argument_lists) <= 1:
            results = []
            for arguments in argument_lists:
                results.append(function(*arguments))
                on_done()
            return results
        from concurrent.futures import as_completed

        results: list = [None] * len(argument_lists)
        # the workers are forked at the first submit: with the signals held back, none
        # can catch a Ctrl-C before its initializer has set it to ignore them
        with interrupts.blocked():
            futures = {
                self.pool.submit(function, *args): index
                for index, args in enumerate(argument_lists)
            }
        for future in as_completed(futures):
            results[futures[future]] = future.result()
            on_done()
        return results


_WORKER_JOIN_S = 2.0
"""How long to wait for a killed worker to be reaped (it dies at once; this bounds a hang)."""
_MANAGER_JOIN_S = 1.0
"""How long to let the pool's own thread finish its clean-up (ms normally; a thread still
stuck after that is ended with the process)."""


def _end_pool(pool) -> None:
    """Cancel what has not started, kill the workers, reap them: no orphans, no waiting.

    Python 3.11's ``ProcessPoolExecutor`` has no public way to end its workers (3.14 adds
    ``kill_workers``), so they are taken from its ``_processes`` before ``shutdown``
    forgets them.
    """
    processes = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)
    call_queue = getattr(pool, "_call_queue", None)
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        with contextlib.suppress(OSError, ValueError, AttributeError):  # gone, or never started
            process.kill()
    for process in processes:
        with contextlib.suppress(OSError, ValueError, AssertionError):
            process.join(_WORKER_JOIN_S)
    # The queue's feeder thread may be stuck writing a task (an image) that no worker
    # will read: without a reader its write fails and the pool's threads can end.
    with contextlib.suppress(AttributeError, OSError):
        call_queue._reader.close()
    if manager is not None:
        manager.join(_MANAGER_JOIN_S)  # its clean-up done while stderr is still captured


# ----------------------------------------------------------------------- the command


def _expand(paths: Iterable[str | os.PathLike]) -> tuple[list[str], list[ImageResult]]:
    """Image and video files from files and directories (a directory gives its image
    files); a bad path is a failed result, not an error (a missing video is the video
    reader's refusal)."""
    from endomeasure.io.images import find_image_files

    files, failures = [], []
    for raw in paths:
        if is_video_file(raw) and not os.path.isdir(raw):
            files.append(os.fspath(raw))
            continue
        try:
            files.extend(str(p) for p in find_image_files([raw]))
        except BadInputError as exc:
            failures.append(
                ImageResult(path=str(raw), name="", status=STATUS_FAILED, error=exc.what)
            )
    return files, failures


def _check_reads(reads, stored_size, stored_images, results):
    """Keep decoded images of the session's size that do not clash with stored ones.

    Appends a failed :class:`ImageResult` to ``results`` for every other file; returns the
    usable records and the detections already made for them (by image name).
    """
    records, detections, seen = [], {}, {}
    size = stored_size
    for path, record, _estimate, error, detection in reads:
        if record is None:
            results.append(ImageResult(path=path, name="", status=STATUS_FAILED, error=error))
            continue
        frame = record.frame
        name = record.name
        image_size = (int(record.pixels.shape[1]), int(record.pixels.shape[0]))
        problem = ""
        if name in seen:
            problem = f"two files give the image name {name!r} (the other is {seen[name]})"
        elif name in stored_images and stored_images[name] != record.sha256:
            problem = f"the session already holds a different image named {name!r}"
        elif size is not None and image_size != tuple(size):
            problem = (
                f"image is {image_size[0]}x{image_size[1]} px but the session's images are "
                f"{size[0]}x{size[1]} px"
            )
        if problem:
            results.append(ImageResult(path=path, name=name, status=STATUS_FAILED,
                                       error=problem, frame=frame))  # fmt: skip
            continue
        seen[name] = path
        size = image_size if size is None else size
        records.append(record)
        if detection is not None:
            detections[name] = detection
    return records, detections


def _choose_split(given_split, stored_split, estimates, records):
    """The split to use and where it came from: the band fitted to the evidence of every
    usable image at once (the band is fixed, the scene moves)."""
    from endomeasure.features.split import find_split_in_set

    if given_split is not None:
        return given_split, "given"
    if stored_split is not None:
        return stored_split, "session"
    if not records:
        return None, "auto"
    size = (int(records[0].pixels.shape[1]), int(records[0].pixels.shape[0]))
    evidence = [e for e in estimates if e is not None and tuple(e.image_size) == size]
    try:
        return find_split_in_set(evidence).split, "auto"
    except BadInputError as exc:
        raise BadInputError(
            f"{exc.what} (over the {len(records)} images)",
            hint="give the first column of the right half with --split COLUMN",
        ) from None


class _Snapshot(NamedTuple):
    """What the session held before the command (nothing for a new session)."""

    split: int | None
    image_size: tuple[int, int] | None
    images: dict[str, str]  # name -> sha256
    has_detections: bool


def _snapshot(session_path: Path) -> _Snapshot:
    from endomeasure.io.session import open_session

    if not session_path.exists():
        return _Snapshot(None, None, {}, False)
    with open_session(session_path) as session:
        meta = session.metadata()
        images = {info.name: info.sha256 for info in session.images_info()}
        return _Snapshot(meta.split, meta.image_size, images, bool(session.detections()))


def _progress_ticks(on_progress):
    """``tick(stage, total)`` -> a callback counting one item of that stage done."""
    progress = on_progress or (lambda stage, done, total: None)

    def tick(stage: str, total: int) -> Callable[[], None]:
        counter = {"done": 0}

        def done() -> None:
            counter["done"] += 1
            progress(stage, counter["done"], total)

        return done

    return tick


class _Detected(NamedTuple):
    records: list  # ImageRecord of every usable image
    detections: dict  # image name -> SplitDetection
    split: int | None
    split_source: str
    size: tuple[int, int] | None


def _read_and_detect(items, image_set, board_name, given_split, before: _Snapshot, method,
                     workers: int, tick, results) -> _Detected:  # fmt: skip
    """Read every file (a path) or take every frame (an ImageRecord), fix the split,
    detect in both halves; failed files go to ``results``."""
    want_split = given_split is None and before.split is None
    known_split = given_split if given_split is not None else before.split
    with _Runner(workers) as runner:
        # With the split known, each worker reads and detects in one go.
        reads = runner.run(
            _read_task,
            [
                (item, image_set, want_split, board_name, known_split, method, before.image_size)
                for item in items
            ],  # fmt: skip
            tick("reading" if want_split else "detecting", len(items)),
        )
        records, detections = _check_reads(reads, before.image_size, before.images, results)
        split_used, split_source = _choose_split(
            given_split, before.split, [r[2] for r in reads if r[1] is not None], records
        )
        size = before.image_size or (
            (int(records[0].pixels.shape[1]), int(records[0].pixels.shape[0])) if records else None
        )
        if split_used is not None and size is not None and not 0 < split_used < size[0]:
            raise BadInputError(
                f"split column {split_used} is outside the images (width {size[0]} px)",
                hint="give a column between 1 and the image width minus 1",
            )
        missing = [record for record in records if record.name not in detections]
        found = runner.run(
            _detect_task,
            [(r.name, r.pixels, board_name, split_used, method) for r in missing],
            tick("detecting", len(missing)),
        )
        detections.update(dict(found))
    return _Detected(records, detections, split_used, split_source, size)


def _image_result(record, detection) -> ImageResult:
    halves = {
        h.half.label: HalfSummary(len(h.ids), h.quality.edge_width_px, h.failure or "")
        for h in detection.halves
    }
    status = {2: STATUS_OK, 1: STATUS_ONE_HALF, 0: STATUS_FAILED}[detection.n_ok]
    error = "" if detection.n_ok else "no board found in either half"
    return ImageResult(path=record.original_path, name=record.name, status=status,
                       error=error, halves=halves, frame=record.frame)  # fmt: skip


def _stored_detections(found: _Detected, board_name: str, method: str | None) -> list:
    from endomeasure.io.session import Detection

    stored = []
    for record in found.records:
        for half in found.detections[record.name].halves:
            stored.append(
                Detection(
                    image=record.name,
                    board=board_name,
                    half=Half(half.half),
                    ids=half.ids.astype(np.int32),
                    pixels=half.pixels,
                    quality=half.quality.edge_width_px,
                    failure=half.failure or "",
                    covariance=half.covariance,
                    attrs={
                        "quality_kind": QUALITY_KIND,
                        "brightness": half.quality.brightness,
                        "contrast": half.quality.contrast,
                        "split": int(found.split),
                        "method": method or "default",
                    },
                )
            )
    return stored


def _store(session_path: Path, spec, board_name: str, found: _Detected, method) -> None:
    from endomeasure.io.records import board_attrs
    from endomeasure.io.session import edit_session

    stored = _stored_detections(found, board_name, method)
    attrs, units = board_attrs(spec)
    split_used, size = found.split, found.size
    with edit_session(session_path, create=True) as writer:
        meta = writer.metadata()
        # Another command may have set these since the snapshot; a conflict is refused.
        if meta.split is not None and meta.split != split_used:
            raise BadInputError(
                f"the session's split changed to {meta.split} while detecting with {split_used}",
                path=str(session_path),
                hint="run detect again",
            )
        if (
            meta.image_size is not None
            and size is not None
            and tuple(meta.image_size) != tuple(size)
        ):
            raise BadInputError(
                "the session's image size changed while detecting",
                path=str(session_path),
                hint="run detect again",
            )
        extra = {} if meta.split is not None else {"split_method": found.split_source}
        writer.set_metadata(image_size=size, split=split_used, **extra)
        writer.write_images(found.records)
        writer.write_board(board_name, board_name, attrs, units)
        writer.write_detections(stored)


def _video_frames(videos, image_set, board_name, frame_step, split, image_size, on_progress):
    """The frames of every video (the pick ``add-images`` makes, or every
    ``frame_step``-th frame), all of one size: the session's, else the first video's.
    Returns the records and one summary per video."""
    import functools

    from endomeasure.features.frames import pick_from_clip
    from endomeasure.io.video import video_records

    progress = on_progress or (lambda stage, done, total: None)
    records, summaries = [], []
    for video in videos:
        stage = f"reading {os.path.basename(video)}"
        pick = functools.partial(pick_from_clip, board=board_name, split=split, path=video)
        frames, summary = video_records(
            video, image_set, pick=pick, frame_step=frame_step, image_size=image_size,
            on_progress=lambda done, total, stage=stage: progress(stage, done, total),
        )  # fmt: skip
        image_size = image_size or (int(frames[0].pixels.shape[1]), int(frames[0].pixels.shape[0]))
        records.extend(frames)
        summaries.append(summary)
    return records, summaries


def _check_videos_found_board(summaries, found: _Detected, spec) -> None:
    """Refuse a video none of whose frames taken shows the board in either half (frames
    refused before detection, e.g. under a name the session holds for another image, are
    failures of their own in the report)."""
    for summary in summaries:
        detected = [r.name for r in found.records
                    if r.frame is not None and r.original_path == summary.path]  # fmt: skip
        if not detected or any(found.detections[name].n_ok for name in detected):
            continue
        how = "picked" if summary.split is not None else "taken"
        raise BadInputError(
            f"no board {spec.canonical()} found in either half of the {len(detected)} frames "
            f"{how} from the video",
            path=summary.path,
            hint="check the --board spec and the --split, or give another video",
        )


def detect_images(
    session_path: str | os.PathLike,
    paths: Iterable[str | os.PathLike],
    board: str,
    *,
    image_set: str = "calib",
    split: int | None = None,
    workers: int = 1,
    method: str | None = None,
    frame_step: int | None = None,
    on_progress: Callable[[str, int, int], None] | None = None,
) -> DetectReport:
    """Detect a board in both halves of image files and store everything in a session.

    Parameters
    ----------
    session_path : path-like
        Created when missing.
    paths : iterable of path-like
        Image files, directories of images and video files
        (:data:`endomeasure.io.video.VIDEO_SUFFIXES`).
    board : str
        Board spec (``chessboard:COLSxROWS:SQUARE_MM`` or ``charuco:...``).
    image_set : str
        ``calib``, ``test`` or ``scene``.
    split : int or None, px
        None keeps the session's split, or finds one (median over the images); a column
        overrides when the session has none or the same one.
    workers : int
        Processes for reading and detection.
    method : str, optional
        Chessboard method; the detector's default when None.
    frame_step : int, optional
        Take every ``frame_step``-th frame of a video (0, N, 2N, ...) instead of the
        frames picked by :func:`endomeasure.features.frames.pick_frames`.
    on_progress : callable(stage, done, total), optional
        ``stage`` is ``"reading"``, ``"detecting"`` or ``"reading <video file name>"``
        (once per pass over the clip).

    Returns
    -------
    DetectReport
        Per-image results; :attr:`DetectReport.exit_code` says how the command should end.

    Raises
    ------
    BadInputError
        Malformed board spec, image set, worker count or frame step; a split that
        contradicts the one stored with existing detections; no split could be found;
        a video that cannot be used (see the module docstring).
    SessionError
        The session cannot be read.
    """
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.io.session import IMAGE_SETS

    spec = parse_board_spec(board)
    board_name = spec.canonical()
    if image_set not in IMAGE_SETS:
        raise BadInputError(
            f"unknown image set {image_set!r}", hint=f"use one of {', '.join(IMAGE_SETS)}"
        )
    if int(workers) < 1:
        raise BadInputError(f"--workers must be at least 1, not {workers}")
    most = defaults.MAX_WORKERS_PER_CPU * (os.cpu_count() or 1)
    if int(workers) > most:
        raise BadInputError(
            f"--workers {workers} is more than {defaults.MAX_WORKERS_PER_CPU} per CPU "
            f"({most} on this machine): more processes only add memory and start-up time",
            hint=f"give at most --workers {most}",
        )
    if frame_step is not None and int(frame_step) < 1:
        raise BadInputError(f"--frame-step must be at least 1, not {frame_step}")
    from endomeasure.io.outputs import checked_session_target

    session_path = Path(session_path)
    checked_session_target(session_path, create=True)  # before reading any image
    before = _snapshot(session_path)
    if split is not None and before.split is not None and split != before.split:
        if before.has_detections:
            raise BadInputError(
                f"--split {split} differs from the session's split {before.split}, which its "
                "detections were made with",
                path=str(session_path),
                hint="use --split auto to keep the session's split, or start a new session",
            )

    files, results = _expand(paths)
    videos = [f for f in files if is_video_file(f)]
    frames, summaries = _video_frames(
        videos, image_set, board_name, frame_step, split if split is not None else before.split,
        before.image_size, on_progress,
    )  # fmt: skip
    # the frames first: they fix the size of a new session's images, as a video must
    items = [*frames, *(f for f in files if not is_video_file(f))]
    found = _read_and_detect(items, image_set, board_name, split, before, method, int(workers),
                             _progress_ticks(on_progress), results)  # fmt: skip
    _check_videos_found_board(summaries, found, spec)
    results.extend(_image_result(r, found.detections[r.name]) for r in found.records)
    order = {path: index for index, path in enumerate(files)}
    results.sort(key=lambda r: order.get(r.path, -1))
    report = DetectReport(
        session=str(session_path),
        board=board_name,
        board_name=board_name,
        image_set=image_set,
        split=found.split,
        split_source=found.split_source,
        images=results,
        stored=False,
        videos=summaries,
    )
    if report.exit_code == 2:
        return report
    _store(session_path, spec, board_name, found, method)
    return dataclasses.replace(report, stored=True)
