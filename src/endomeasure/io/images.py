"""Reading image files for embedding in a session.

The file's bytes are read once: they are hashed (SHA-256, stored with the image so a
session can prove which file it was made from) and decoded from the same buffer, so the
hash always describes the pixels that were stored.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.io.image_header import checked_image_size, image_size_from_header
from endomeasure.io.outputs import file_kind, is_regular_file
from endomeasure.io.session import IMAGE_SETS, ImageRecord
from endomeasure.io.video import VIDEO_SUFFIXES

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
"""File types the image reader accepts (matched case-insensitively)."""


def sha256_of_file(path: str | os.PathLike) -> str:
    """The SHA-256 (hex) of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def find_image_files(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Expand files and directories (not recursively) into image files.

    Files are kept in the order given; a directory contributes its image files sorted by
    name. Raises BadInputError for a path that does not exist or a file of another type.
    """
    out: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            out.extend(
                sorted(
                    p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                )
            )
        elif path.is_file():
            if path.suffix.lower() in VIDEO_SUFFIXES:
                raise BadInputError(
                    "a video file, not an image",
                    path=str(path),
                    hint="add its frames with `endomeasure add-images SESSION VIDEO --board SPEC`",
                )
            if path.suffix.lower() not in IMAGE_SUFFIXES:
                raise BadInputError(
                    "not an image file",
                    path=str(path),
                    hint=f"give {', '.join(IMAGE_SUFFIXES)} files",
                )
            out.append(path)
        else:
            raise BadInputError(_not_a_file(path), path=str(path))
    return out


def _not_a_file(path: Path) -> str:
    """Why ``path`` is neither an image file nor a folder: missing, or its kind."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file or directory"
    except OSError as exc:
        return f"cannot read the path ({exc.strerror or exc})"
    return f"a {file_kind(mode)}, not an image file or a folder"


def read_image_file(
    path: str | os.PathLike,
    image_set: str,
    name: str | None = None,
    *,
    expected_size: tuple[int, int] | None = None,
) -> ImageRecord:
    """Read an image file into an :class:`ImageRecord` ready to embed.

    Parameters
    ----------
    path : path-like
        PNG, JPEG, TIFF or BMP; 8- or 16-bit; grey or colour (kept as stored, colour in
        OpenCV's BGR order).
    image_set : str
        One of ``calib``, ``test``, ``scene``.
    name : str, optional
        Key in the session; default: the file's stem.
    expected_size : (width, height), optional, px
        The session's image size: another size is refused before decoding.

    Raises
    ------
    BadInputError
        Unreadable or undecodable file, a size beyond the limits or other than
        ``expected_size`` (read from the header, before decoding), or a pixel type
        other than 8/16-bit unsigned.
    """
    import cv2  # heavy; only needed when images are actually read

    path = Path(path)
    if image_set not in IMAGE_SETS:
        raise BadInputError(
            f"unknown image set {image_set!r}", hint=f"use one of {', '.join(IMAGE_SETS)}"
        )
    if os.path.exists(path) and not is_regular_file(path):  # a FIFO would block the read
        raise BadInputError(_not_a_file(path), path=str(path))
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise BadInputError(f"cannot read the image file ({exc.strerror})", path=str(path)) from exc
    header_size = image_size_from_header(data[: 1 << 16])
    if header_size is not None:
        checked_image_size(header_size, str(path), expected_size)
    pixels = None
    if data:
        pixels = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is not None and header_size is None:  # a format the header reader does not know
        checked_image_size((pixels.shape[1], pixels.shape[0]), str(path), expected_size)
    if pixels is None:
        raise BadInputError(
            "cannot decode the image file",
            path=str(path),
            hint="give a PNG, JPEG, TIFF or BMP image",
        )
    if pixels.dtype not in (np.uint8, np.uint16):
        raise BadInputError(
            f"unsupported pixel type {pixels.dtype}",
            path=str(path),
            hint="give 8- or 16-bit images",
        )
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[:, :, 0]
    return ImageRecord(
        name=name or path.stem,
        pixels=np.ascontiguousarray(pixels),
        original_path=str(path),
        sha256=hashlib.sha256(data).hexdigest(),
        image_set=image_set,
    )
