"""Session file: round trip of every stored kind, version handling, damaged files."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError, SessionError, SessionVersionError
from endomeasure.io.integrity import seal_file
from endomeasure.io.session import (
    FORMAT_VERSION,
    Detection,
    ImageRecord,
    Record,
    edit_session,
    open_session,
)


def assert_same_value(actual, expected):
    """Equality for attribute values, NaN equal to NaN, tuples equal to lists."""
    if isinstance(expected, dict):
        assert isinstance(actual, dict) and actual.keys() == expected.keys()
        for key in expected:
            assert_same_value(actual[key], expected[key])
    elif isinstance(expected, (list, tuple)):
        assert list(np.asarray(actual).tolist()) == list(np.asarray(expected).tolist())
    elif isinstance(expected, float) and math.isnan(expected):
        assert isinstance(actual, float) and math.isnan(actual)
    else:
        assert actual == expected and type(actual) is type(expected)


def test_round_trip_of_every_kind(session_path, contents):
    with open_session(session_path) as s:
        meta = s.metadata()
        assert meta.format_version == FORMAT_VERSION
        assert meta.created_by.startswith("endomeasure ")
        assert meta.image_size == (64, 48) and meta.split == 31
        assert meta.attrs == {"split_method": "auto"}

        assert s.image_names() == sorted(r.name for r in contents["images"])
        for rec in contents["images"]:
            back = s.image_record(rec.name)
            assert back.pixels.dtype == rec.pixels.dtype
            np.testing.assert_array_equal(back.pixels, rec.pixels)
            assert (back.original_path, back.sha256, back.image_set) == (
                rec.original_path,
                rec.sha256,
                rec.image_set,
            )
        assert s.image_info("colour16").channel_order == "BGR"
        assert s.image_info("grey8").channel_order == "gray"
        assert s.image_names("test") == ["colour16"]

        boards = s.boards()
        assert sorted(boards) == sorted(contents["boards"])
        for name, (spec, attrs) in contents["boards"].items():
            assert boards[name].spec == spec
            assert_same_value(boards[name].attrs, attrs)

        dets = s.detections()
        assert len(dets) == len(contents["detections"])
        for want in contents["detections"]:
            (got,) = s.detections(board=want.board, image=want.image, half=want.half)
            assert got.ids.dtype == np.int32 and got.pixels.dtype == np.float64
            np.testing.assert_array_equal(got.ids, want.ids)
            np.testing.assert_array_equal(got.pixels, want.pixels)
            assert_same_value(got.quality, float(want.quality))
            assert got.failure == want.failure and got.ok == (want.failure == "")
            assert got.attrs == want.attrs
        assert [d.half for d in s.detections(half="right")] == [Half.RIGHT, Half.RIGHT]

        (want,) = contents["models"]
        got = s.model("pinhole")
        assert s.model_names() == ["pinhole"]
        assert got.registry_name == want.registry_name
        np.testing.assert_array_equal(got.params, want.params)
        assert got.param_names == want.param_names
        assert got.config == want.config
        assert sorted(got.arrays) == sorted(want.arrays)
        for key, value in want.arrays.items():
            np.testing.assert_array_equal(got.arrays[key], value)
        assert got.attrs == want.attrs
        assert got.units == want.units

        assert s.record_kinds() == ["measurement", "prediction"]
        for want in contents["records"]:
            got = s.record(want.kind, want.name)
            assert_same_value(got.attrs, want.attrs)
            assert sorted(got.arrays) == sorted(want.arrays)
            for key, value in want.arrays.items():
                assert got.arrays[key].dtype == value.dtype
                np.testing.assert_array_equal(got.arrays[key], value)
            assert got.units == want.units


def test_every_group_carries_type_and_version(session_path):
    untyped = []

    def visit(name, obj):
        if isinstance(obj, h5py.Group) and not {"type", "version"} <= set(obj.attrs):
            untyped.append(name)

    with h5py.File(session_path, "r") as f:
        assert f.attrs["endomeasure_format"] == "session"
        assert f.attrs["format_version"] == FORMAT_VERSION
        f.visititems(visit)
        n_groups = []
        f.visititems(lambda n, o: n_groups.append(n) if isinstance(o, h5py.Group) else None)
        assert f["detections/cb1/grey8/left/pixels"].attrs["units"] == "px"
        assert f["metadata"].attrs["units:split"] == "px"
    assert len(n_groups) > 10
    assert untyped == []


scalars = st.one_of(
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.booleans(),
)
attr_values = st.one_of(
    scalars,
    st.lists(st.floats(allow_nan=False, width=64), min_size=1, max_size=5),
    st.dictionaries(st.text(max_size=5), st.integers(-100, 100), max_size=3),
)
attr_names = st.text(
    alphabet=st.characters(blacklist_characters="/\x00", blacklist_categories=("Cs",)),
    min_size=1,
    max_size=12,
).filter(
    lambda s: (
        s not in ("type", "version", "json_attrs", "kind", ".", "..") and not s.startswith("units:")
    )
)
arrays = hnp.arrays(
    dtype=st.sampled_from([np.float64, np.float32, np.int32, np.int64, np.uint8, np.bool_]),
    shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4),
)


@settings(max_examples=60)  # each example writes and reads a file
@given(
    attrs=st.dictionaries(attr_names, attr_values, max_size=6),
    named_arrays=st.dictionaries(attr_names, arrays, max_size=3),
)
def test_record_round_trip_of_arbitrary_attrs_and_arrays(attrs, named_arrays):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.h5"
        with edit_session(path, create=True) as w:
            w.write_record(Record("thing", "r", attrs=attrs, arrays=named_arrays))
        with open_session(path) as s:
            got = s.record("thing", "r")
    assert_same_value(got.attrs, attrs)
    assert sorted(got.arrays) == sorted(named_arrays)
    for key, value in named_arrays.items():
        assert got.arrays[key].dtype == value.dtype and got.arrays[key].shape == value.shape
        np.testing.assert_array_equal(got.arrays[key], value)


def test_writer_reads_its_own_edits_and_replaces_items(session_path):
    with edit_session(session_path) as w:
        w.write_record(Record("measurement", "m001", attrs={"value": 9.0}))
        assert w.record("measurement", "m001").attrs == {"value": 9.0}
        w.set_metadata(split=40)
        assert w.metadata().image_size == (64, 48)  # untouched fields keep their values
        w.delete_record("prediction", "zone-12")
        w.delete_model("pinhole")
        w.delete_detections("cb1")
    with open_session(session_path) as s:
        assert s.record("measurement", "m001").attrs == {"value": 9.0}
        assert s.metadata().split == 40
        assert s.record_names("prediction") == []
        assert s.model_names() == []
        assert {d.board for d in s.detections()} == {"ch2"}


def test_same_image_twice_is_kept_and_a_different_one_refused(session_path, rng):
    with open_session(session_path) as s:
        rec = s.image_record("grey8")
    with edit_session(session_path) as w:
        assert w.write_images([rec]) == []
    other = ImageRecord(
        "grey8", rng.integers(0, 256, (48, 64), dtype=np.uint8), "/x.png", "0" * 64, "calib"
    )
    with pytest.raises(BadInputError, match="different image named 'grey8'"):
        with edit_session(session_path) as w:
            w.write_images([other])
    with edit_session(session_path) as w:
        assert w.write_images([other], replace=True) == ["grey8"]
    with open_session(session_path) as s:
        np.testing.assert_array_equal(s.image("grey8"), other.pixels)


def test_a_failed_edit_leaves_the_file_untouched_and_no_temp(session_path):
    before = session_path.read_bytes()
    with pytest.raises(ZeroDivisionError):
        with edit_session(session_path) as w:
            w.write_record(Record("measurement", "m002", attrs={"value": 1.0}))
            w.set_metadata(split=1)
            1 / 0  # noqa: B018
    assert session_path.read_bytes() == before
    assert sorted(p.name for p in session_path.parent.iterdir()) == ["probe.h5", "probe.h5.lock"]


def test_bad_items_are_refused_with_a_domain_error(session_path, rng):
    with pytest.raises(BadInputError, match="no board named 'nope'.*available: cb1, ch2"):
        with edit_session(session_path) as w:
            w.write_detection(Detection("grey8", "nope", Half.LEFT, np.zeros(0), np.zeros((0, 2))))
    with pytest.raises(BadInputError, match="image set"):
        with edit_session(session_path) as w:
            w.write_images([ImageRecord("x", np.zeros((2, 2), np.uint8), "", "", "calibration")])
    with pytest.raises(BadInputError, match="float32"):
        with edit_session(session_path) as w:
            w.write_images([ImageRecord("x", np.zeros((2, 2), np.float32), "", "", "calib")])
    with pytest.raises(BadInputError, match="invalid record name"):
        with edit_session(session_path) as w:
            w.write_record(Record("measurement", "a/b"))
    with open_session(session_path) as s:
        with pytest.raises(BadInputError, match="no model named 'raytrace'.*available: pinhole"):
            s.model("raytrace")


def test_missing_file_is_a_session_error_unless_created(tmp_path):
    with pytest.raises(SessionError, match="does not exist"):
        open_session(tmp_path / "none.h5")
    with pytest.raises(SessionError, match="does not exist"):
        with edit_session(tmp_path / "none.h5"):
            pass
    assert not (tmp_path / "none.h5").exists()
    with edit_session(tmp_path / "new.h5", create=True):
        pass
    with open_session(tmp_path / "new.h5") as s:
        assert s.images_info() == [] and s.metadata().image_size is None


def test_not_hdf5_and_not_a_session_are_refused(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("not a session\n")
    with pytest.raises(SessionError, match="not HDF5"):
        open_session(text)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(SessionError, match="not an endomeasure session"):
        open_session(other)
    with pytest.raises(SessionError, match="not an endomeasure session"):
        with edit_session(other):
            pass


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_truncated_session_is_a_session_error(session_path, fraction):
    data = session_path.read_bytes()
    session_path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(SessionError, match="truncated or damaged"):
        with open_session(session_path) as s:
            for name in s.image_names():
                s.image(name)


def set_root_version(path, version):
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = version
    seal_file(path)


def test_future_major_version_is_refused_naming_both_versions(session_path):
    set_root_version(session_path, "2.0")
    before = session_path.read_bytes()
    with pytest.raises(SessionVersionError) as excinfo:
        open_session(session_path)
    message = excinfo.value.one_line()
    assert "version 2.0" in message and "reads version 1.x" in message
    assert "newer endomeasure" in message
    with pytest.raises(SessionVersionError):
        with edit_session(session_path):
            pass
    assert session_path.read_bytes() == before


def test_future_major_version_of_one_group_is_refused(session_path):
    with h5py.File(session_path, "r+") as f:
        f["models/pinhole"].attrs["version"] = "3.1"
    seal_file(session_path)
    with open_session(session_path) as s:
        assert s.image_names()  # other content still reads
        with pytest.raises(
            SessionVersionError, match="group /models/pinhole has session format version 3.1"
        ):
            s.model("pinhole")


def test_newer_minor_version_reads_skips_unknown_types_and_is_not_downgraded(session_path):
    set_root_version(session_path, "1.7")
    with h5py.File(session_path, "r+") as f:
        extra = f["images"].create_dataset("future-thing", data=np.zeros(3))
        extra.attrs["type"] = "image_reference"
        extra.attrs["version"] = "1.0"
        f.create_group("annotations").attrs["type"] = "annotations"
    seal_file(session_path)
    with open_session(session_path) as s:
        assert "future-thing" not in s.image_names()
        assert s.metadata().format_version == "1.7"
    with edit_session(session_path) as w:
        w.write_record(Record("measurement", "m9"))
    with h5py.File(session_path, "r") as f:
        assert f.attrs["format_version"] == "1.7"
        assert "annotations" in f and "future-thing" in f["images"]


def test_file_permissions_survive_an_edit(session_path):
    os.chmod(session_path, 0o640)
    with edit_session(session_path) as w:
        w.write_record(Record("measurement", "m9"))
    assert os.stat(session_path).st_mode & 0o777 == 0o640


def test_bad_arguments_and_closed_sessions_are_not_reported_as_damage(session_path):
    s = open_session(session_path)
    with pytest.raises(BadInputError, match="half must be 'left' or 'right'"):
        s.detections(half="middle")
    s.close()
    with pytest.raises(RuntimeError, match="closed session"):
        s.image_names()
