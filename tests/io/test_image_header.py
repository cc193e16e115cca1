"""Image sizes from file headers, against the files OpenCV writes, and the size limits."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from endomeasure import defaults
from endomeasure.errors import BadInputError
from endomeasure.io.image_header import checked_image_size, image_size_from_header
from endomeasure.io.images import read_image_file

SIZES = [(32, 24), (1, 1), (641, 479), (3000, 7)]


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif", ".bmp"])
@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
@pytest.mark.parametrize("channels", [1, 3])
def test_the_header_size_is_the_decoded_size(tmp_path, rng, suffix, size, channels):
    width, height = size
    shape = (height, width) if channels == 1 else (height, width, channels)
    path = tmp_path / f"x{suffix}"
    assert cv2.imwrite(str(path), rng.integers(0, 256, shape, dtype=np.uint8))
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # the oracle: OpenCV's decoder
    assert image_size_from_header(path.read_bytes()) == (decoded.shape[1], decoded.shape[0])


def test_a_progressive_jpeg_and_16_bit_png(tmp_path, rng):
    jpeg = tmp_path / "p.jpg"
    cv2.imwrite(str(jpeg), rng.integers(0, 256, (40, 50, 3), dtype=np.uint8),
                [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])  # fmt: skip
    assert image_size_from_header(jpeg.read_bytes()) == (50, 40)
    png = tmp_path / "d.png"
    cv2.imwrite(str(png), rng.integers(0, 65536, (9, 11), dtype=np.uint16))
    assert image_size_from_header(png.read_bytes()) == (11, 9)


@pytest.mark.parametrize(
    "data",
    [b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"II*\x00\xff\xff\xff\xff", b"BM", b"GIF89a"],
    ids=["empty", "png-cut", "jpeg-cut", "tiff-bad-offset", "bmp-cut", "gif"],
)
def test_damaged_or_unknown_headers_give_none(data):
    assert image_size_from_header(data) is None


def test_the_limits(tmp_path):
    checked_image_size((defaults.MAX_IMAGE_SIDE, 16), "x")
    for size in [(defaults.MAX_IMAGE_SIDE + 1, 1), (15000, 15000), (0, 5)]:
        with pytest.raises(BadInputError):
            checked_image_size(size, "x")
    with pytest.raises(BadInputError, match="but the session's images are 64x48"):
        checked_image_size((32, 24), "x", expected=(64, 48))


def test_a_file_of_another_size_is_refused_before_decoding(tmp_path, rng, monkeypatch):
    path = tmp_path / "x.png"
    cv2.imwrite(str(path), rng.integers(0, 256, (24, 32), dtype=np.uint8))

    def no_decoding(*args, **kwargs):
        raise AssertionError("decoded although the header already refused the file")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    with pytest.raises(BadInputError, match="32x24 px but the session's images are 64x48"):
        read_image_file(path, "calib", expected_size=(64, 48))
