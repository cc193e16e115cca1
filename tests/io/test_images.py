"""Image files: decoded pixels equal what was written, hash equals the file's SHA-256."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest

from endomeasure.errors import BadInputError
from endomeasure.io.images import find_image_files, read_image_file, sha256_of_file


@pytest.mark.parametrize(
    ("suffix", "shape", "dtype"),
    [
        (".png", (30, 40), np.uint8),
        (".png", (30, 40), np.uint16),
        (".png", (30, 40, 3), np.uint8),
        (".tiff", (30, 40), np.uint16),
        (".bmp", (30, 40, 3), np.uint8),
    ],
)
def test_lossless_images_read_back_exactly_with_the_file_hash(tmp_path, rng, suffix, shape, dtype):
    pixels = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    path = tmp_path / f"frame_007{suffix}"
    assert cv2.imwrite(str(path), pixels)
    rec = read_image_file(path, "test")
    assert rec.name == "frame_007" and rec.image_set == "test"
    assert rec.original_path == str(path)
    assert rec.pixels.dtype == dtype and rec.pixels.shape == shape
    np.testing.assert_array_equal(rec.pixels, pixels)
    assert rec.sha256 == hashlib.sha256(path.read_bytes()).hexdigest() == sha256_of_file(path)


def test_unreadable_images_are_bad_input(tmp_path):
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG not really")
    with pytest.raises(BadInputError, match="cannot decode"):
        read_image_file(broken, "calib")
    with pytest.raises(BadInputError, match="cannot read"):
        read_image_file(tmp_path / "missing.png", "calib")
    with pytest.raises(BadInputError, match="image set"):
        read_image_file(broken, "calibration")


def test_directories_expand_to_sorted_image_files(tmp_path):
    for name in ("b.png", "a.JPG", "notes.txt", "c.tif"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "d.png").write_bytes(b"")
    found = find_image_files([tmp_path])
    assert [p.name for p in found] == ["a.JPG", "b.png", "c.tif"]
    assert find_image_files([tmp_path / "c.tif", tmp_path / "b.png"]) == [
        tmp_path / "c.tif",
        tmp_path / "b.png",
    ]
    with pytest.raises(BadInputError, match="not an image file"):
        find_image_files([tmp_path / "notes.txt"])
    with pytest.raises(BadInputError, match="no such file"):
        find_image_files([tmp_path / "nope"])


@pytest.mark.parametrize(
    ("suffix", "channels", "dtype"),
    [
        (".png", 4, np.uint8),  # colour with alpha
        (".png", 3, np.uint16),
        (".png", 4, np.uint16),
        (".tiff", 3, np.uint16),
        (".tiff", 4, np.uint8),
        (".jpg", 3, np.uint8),
        (".jpg", 1, np.uint8),
        (".bmp", 1, np.uint8),
    ],
)
def test_every_kind_reaches_the_detector_as_its_luma(tmp_path, rng, suffix, channels, dtype):
    """What the detector takes (features.detect.to_gray_u8) is OpenCV's BT.601 grey of the
    stored pixels, 16-bit scaled by 255/65535, the alpha ignored."""
    from endomeasure.features.detect import to_gray_u8

    shape = (30, 40) if channels == 1 else (30, 40, channels)
    pixels = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    path = tmp_path / f"kind{suffix}"
    assert cv2.imwrite(str(path), pixels)
    rec = read_image_file(path, "calib")
    assert rec.pixels.dtype == dtype and rec.pixels.shape == shape
    stored = rec.pixels
    eight = stored if dtype == np.uint8 else np.round(stored / 257.0).astype(np.uint8)
    code = {1: None, 3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}[channels]
    expected = eight if code is None else cv2.cvtColor(eight, code)
    assert np.abs(to_gray_u8(stored).astype(int) - expected).max() <= 1


def test_grey_with_alpha_is_read_as_colour_with_alpha(tmp_path, rng):
    """A grey + alpha PNG (which OpenCV cannot write) decodes to BGRA with equal channels."""
    from endomeasure.features.detect import to_gray_u8

    Image = pytest.importorskip("PIL.Image")  # matplotlib's dependency
    grey = rng.integers(0, 256, (30, 40), dtype=np.uint8)
    path = tmp_path / "ga.png"
    Image.fromarray(np.dstack([grey, np.full_like(grey, 128)]), "LA").save(path)
    rec = read_image_file(path, "calib")
    assert rec.pixels.shape == (30, 40, 4)
    np.testing.assert_array_equal(to_gray_u8(rec.pixels), grey)
