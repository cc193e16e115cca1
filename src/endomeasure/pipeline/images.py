"""``endomeasure add-images``: embed image files in a session (creating it if needed)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

from endomeasure.errors import BadInputError
from endomeasure.io.images import find_image_files, read_image_file
from endomeasure.io.session import edit_session

__all__ = ["AddImagesReport", "add_images"]


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
    """

    session: str
    image_set: str
    added: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    image_size: list[int] | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def add_images(
    session_path: str | os.PathLike,
    paths: Iterable[str | os.PathLike],
    image_set: str,
    on_progress: Callable[[int, int], None] | None = None,
) -> AddImagesReport:
    """Embed image files (or the images in directories) in a session, in one atomic edit.

    Parameters
    ----------
    session_path : path-like
        Created when missing (with no images if ``paths`` is empty).
    paths : iterable of path-like
        Image files and/or directories (not searched recursively).
    image_set : str
        ``calib``, ``test`` or ``scene``.
    on_progress : callable(done, total), optional
        Called after each file is read.

    Raises
    ------
    BadInputError
        Unreadable files, two files with one name, or images of different sizes (all
        images of a session come from one sensor, so they share one size).
    """
    files = find_image_files(paths)
    records = []
    for done, path in enumerate(files, start=1):
        records.append(read_image_file(path, image_set))
        if on_progress is not None:
            on_progress(done, len(files))

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
    )
