"""Image dimensions from a file's header bytes, without decoding any pixel.

A 30000 x 30000 PNG of one colour is under a megabyte on disk and 2.7 GB once decoded;
reading its size from the header lets :func:`endomeasure.io.images.read_image_file`
refuse it in microseconds. Covers the formats the reader accepts: PNG (the IHDR chunk),
JPEG (the first start-of-frame marker), TIFF (the first IFD's ImageWidth and
ImageLength tags, either byte order) and BMP (the info header). Standard library only.
:func:`checked_image_size` applies the documented limits (and a session's own size) to
the size found, for image files, video frames and the images of a session alike.
"""

from __future__ import annotations

import struct

from endomeasure.defaults import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE
from endomeasure.errors import BadInputError

__all__ = ["checked_image_size", "image_size_from_header"]

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
"""Start-of-frame markers (baseline, progressive, lossless ...): not DHT, JPG, DAC."""
_TIFF_WIDTH, _TIFF_LENGTH = 256, 257
_TIFF_TYPES = {3: ("H", 2), 4: ("I", 4), 16: ("Q", 8)}  # SHORT, LONG, LONG8 (BigTIFF)


def checked_image_size(
    size: tuple[int, int], path: str, expected: tuple[int, int] | None = None
) -> None:
    """Refuse an image of ``size`` (width, height) px beyond the documented maximum
    (:data:`endomeasure.defaults.MAX_IMAGE_SIDE`, :data:`~endomeasure.defaults.MAX_IMAGE_PIXELS`)
    or other than the session's ``expected`` size: a BadInputError."""
    width, height = int(size[0]), int(size[1])
    if width < 1 or height < 1:
        raise BadInputError(f"the image is {width}x{height} px: empty", path=path)
    if max(width, height) > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise BadInputError(
            f"the image is {width}x{height} px, beyond the limit of {MAX_IMAGE_SIDE} px a "
            f"side and {MAX_IMAGE_PIXELS / 1e6:g} MP (decoding it would take "
            f"{width * height * 3 / 1e9:.1f} GB); no endoscope sensor is that large",
            path=path,
            hint="give the probe's own images",
        )
    if expected is not None and (width, height) != tuple(expected):
        raise BadInputError(
            f"image is {width}x{height} px but the session's images are "
            f"{expected[0]}x{expected[1]} px",
            path=path,
            hint="a session holds images of one sensor; use another session",
        )


def image_size_from_header(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` in px from the first bytes of an image file, or None when the
    format is not recognised or its header is damaged."""
    try:
        if data.startswith(_PNG_MAGIC):
            return _png(data)
        if data[:2] == b"\xff\xd8":
            return _jpeg(data)
        if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
            return _tiff(data)
        if data[:2] == b"BM":
            return _bmp(data)
    except (struct.error, IndexError, ValueError):
        return None
    return None


def _png(data: bytes) -> tuple[int, int] | None:
    if data[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def _jpeg(data: bytes) -> tuple[int, int] | None:
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in _JPEG_SOF:
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height
        if marker == 0xDA:  # start of scan before any frame header
            return None
        i += 2 + length
    return None


def _tiff(data: bytes) -> tuple[int, int] | None:
    order = "<" if data[:2] == b"II" else ">"
    big = data[2:4] in (b"+\x00", b"\x00+")
    if big:
        (offset,) = struct.unpack(order + "Q", data[8:16])
        (count,) = struct.unpack(order + "Q", data[offset : offset + 8])
        entry, first, value_at = 20, offset + 8, 12
    else:
        (offset,) = struct.unpack(order + "I", data[4:8])
        (count,) = struct.unpack(order + "H", data[offset : offset + 2])
        entry, first, value_at = 12, offset + 2, 8
    found: dict[int, int] = {}
    for k in range(min(count, 4096)):
        at = first + k * entry
        tag, kind = struct.unpack(order + "HH", data[at : at + 4])
        if tag in (_TIFF_WIDTH, _TIFF_LENGTH) and kind in _TIFF_TYPES:
            code, size = _TIFF_TYPES[kind]
            (found[tag],) = struct.unpack(order + code, data[at + value_at : at + value_at + size])
    if _TIFF_WIDTH in found and _TIFF_LENGTH in found:
        return found[_TIFF_WIDTH], found[_TIFF_LENGTH]
    return None


def _bmp(data: bytes) -> tuple[int, int] | None:
    (header_size,) = struct.unpack("<I", data[14:18])
    if header_size == 12:  # OS/2 BITMAPCOREHEADER
        width, height = struct.unpack("<HH", data[18:22])
    else:
        width, height = struct.unpack("<ii", data[18:26])
    return abs(width), abs(height)
