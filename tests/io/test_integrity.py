"""Checksums of a session: bit flips found before a value is read, the damaged items
named and left out by repair, format 1.0 files upgraded, full disks refused cleanly."""

from __future__ import annotations

import errno
import os
import shutil

import h5py
import numpy as np
import pytest

from endomeasure.errors import BadInputError, SessionError
from endomeasure.io import integrity
from endomeasure.io.integrity import USERBLOCK_SIZE, check_file, item_paths, read_manifest
from endomeasure.io.session import (
    FORMAT_VERSION,
    Record,
    edit_session,
    open_session,
    salvage_session,
)

FLIPS = 60


def _flipped(path, target, position, bit):
    data = bytearray(path.read_bytes())
    data[position] ^= 1 << bit
    target.write_bytes(bytes(data))
    return target


def _temps(directory):
    return [p for p in directory.iterdir() if p.name.endswith(".endomeasure-tmp")]


def test_a_new_session_has_a_checksum_and_a_manifest_of_every_item(session_path):
    assert check_file(session_path).status == "ok"
    with h5py.File(session_path, "r") as h5:
        manifest = read_manifest(h5)
        items = list(item_paths(h5))
        assert sorted(manifest) == sorted(items)
        assert "metadata" in items and "images/grey8" in items
        assert any(item.startswith("detections/cb1/") for item in items)
        for item in items:
            assert manifest[item] == integrity.item_digest(h5, item)
    with open_session(session_path) as s:
        assert s.checksum == "ok"


def test_every_random_bit_flip_is_found_before_anything_is_read(session_path, tmp_path, rng):
    size = session_path.stat().st_size
    for trial, position in enumerate(rng.integers(0, size, FLIPS)):
        bad = _flipped(session_path, tmp_path / f"flip{trial}.h5", int(position), trial % 8)
        before = bad.read_bytes()
        with pytest.raises(SessionError):
            open_session(bad)
        with pytest.raises(SessionError):  # writers refuse it too, and leave it as it was
            with edit_session(bad) as w:
                w.write_record(Record("r", "x"))
        assert bad.read_bytes() == before
        bad.unlink()
    assert _temps(tmp_path) == []


def _chunk_of(path, dataset):
    with h5py.File(path, "r") as h5:
        info = h5[dataset].id.get_chunk_info(0)
        return info.byte_offset, info.size


def test_a_flip_in_an_image_names_it_and_repair_keeps_everything_else(session_path, tmp_path):
    offset, size = _chunk_of(session_path, "images/grey8")
    bad = _flipped(session_path, tmp_path / "bad.h5", offset + size // 2, 3)
    with pytest.raises(SessionError, match=r"1 of \d+ stored items .*images/grey8"):
        open_session(bad)

    report, checksum = salvage_session(bad, tmp_path / "fixed.h5")
    assert checksum == "damaged"
    assert list(report.damaged) == ["images/grey8"]
    with open_session(tmp_path / "fixed.h5") as fixed, h5py.File(session_path, "r") as h5:
        assert fixed.checksum == "ok"
        assert "grey8" not in fixed.image_names()
        kept = sorted(item_paths(fixed._h5))
        assert kept == sorted(set(item_paths(h5)) - {"images/grey8"})
        # the kept items are the very ones written: same digests as in the original
        original = read_manifest(h5)
        assert all(read_manifest(fixed._h5)[item] == original[item] for item in kept)


def test_a_flip_outside_the_items_keeps_all_of_them(session_path, tmp_path):
    bad = _flipped(session_path, tmp_path / "bad.h5", 100, 0)  # in the checksum block
    with pytest.raises(SessionError, match="outside its stored items"):
        open_session(bad)
    report, _ = salvage_session(bad, tmp_path / "fixed.h5")
    assert report.damaged == {} and len(report.intact) > 5


def test_repair_refuses_an_existing_output(session_path):
    with pytest.raises(BadInputError, match="must be a new file"):
        salvage_session(session_path, session_path)


def test_a_truncated_session_is_refused_and_nothing_is_salvaged(session_path, tmp_path):
    cut = tmp_path / "cut.h5"
    cut.write_bytes(session_path.read_bytes()[: USERBLOCK_SIZE + 300])
    with pytest.raises(SessionError, match="truncated or damaged"):
        open_session(cut)
    with pytest.raises(SessionError, match="nothing can be salvaged"):
        salvage_session(cut, tmp_path / "fixed.h5")


def _as_format_1_0(source, target):
    """The same items in a file as endomeasure 1.0 wrote it: no user block, no manifest."""
    with h5py.File(source, "r") as old, h5py.File(target, "w") as new:
        for key, value in old.attrs.items():
            new.attrs[key] = value
        new.attrs["format_version"] = "1.0"
        for key in old:
            if key != integrity.MANIFEST:
                old.copy(old[key], new, name=key)


def test_a_format_1_0_file_is_read_unchecked_and_upgraded_by_its_first_edit(session_path, tmp_path):
    legacy = tmp_path / "legacy.h5"
    _as_format_1_0(session_path, legacy)
    assert check_file(legacy).status == "unchecked"
    with open_session(legacy) as s:
        assert s.checksum == "unchecked" and s.format_version == "1.0"
        names = s.image_names()
    with edit_session(legacy) as w:
        w.write_record(Record("r", "after-upgrade"))
    assert check_file(legacy).status == "ok"
    with open_session(legacy) as s, h5py.File(session_path, "r") as h5:
        assert s.format_version == FORMAT_VERSION and s.image_names() == names
        upgraded, original = read_manifest(s._h5), read_manifest(h5)
        assert {k: v for k, v in upgraded.items() if k in original} == original
        assert "records/r/after-upgrade" in upgraded


def test_the_manifest_follows_writes_replacements_and_deletions(session_path):
    with edit_session(session_path) as w:
        w.write_record(Record("measurement", "m1", attrs={"value": 2.0}))  # replaced
        w.delete_detections("cb1")
        w.delete_model("pinhole")
    with open_session(session_path) as s:
        manifest = read_manifest(s._h5)
        assert sorted(manifest) == sorted(item_paths(s._h5))
        assert not any(k.startswith(("detections/cb1/", "models/")) for k in manifest)
        assert any(k.startswith("detections/ch2/") for k in manifest)
        assert manifest["records/measurement/m1"] == integrity.item_digest(
            s._h5, "records/measurement/m1"
        )


def test_a_full_disk_found_before_writing_leaves_the_session_as_it_was(session_path, monkeypatch):
    before = session_path.read_bytes()
    usage = shutil.disk_usage(session_path.parent)
    monkeypatch.setattr(shutil, "disk_usage", lambda _: usage._replace(free=len(before) // 2))
    with pytest.raises(SessionError, match="not enough free space .* MB are free"):
        with edit_session(session_path) as w:
            w.write_record(Record("r", "x"))
    assert session_path.read_bytes() == before
    assert _temps(session_path.parent) == []


@pytest.mark.parametrize("fail_after", [0, 4096, 20000])
def test_a_disk_that_fills_while_writing_leaves_the_session_as_it_was(
    session_path, monkeypatch, fail_after
):
    before = session_path.read_bytes()
    real_write, written = os.write, [0]

    def filling_write(fd, data):
        if written[0] + len(data) > fail_after:
            room = fail_after - written[0]
            if room <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            data = bytes(data[:room])
        n = real_write(fd, data)
        written[0] += n
        return n

    monkeypatch.setattr(os, "write", filling_write)
    with pytest.raises(SessionError, match="cannot write the session .No space left"):
        with edit_session(session_path) as w:
            w.write_record(Record("r", "x", arrays={"values": np.arange(5000.0)}))
    monkeypatch.undo()
    assert session_path.read_bytes() == before
    assert _temps(session_path.parent) == []
    with open_session(session_path) as s:
        assert "r" not in s.record_kinds()
