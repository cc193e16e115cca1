"""Atomic, locked edits: killed writers, concurrent writers, lock timeouts, snapshots."""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import time

import numpy as np
import pytest

from endomeasure.errors import SessionError
from endomeasure.io._lock import SessionLock
from endomeasure.io.session import ImageRecord, Record, edit_session, open_session

KILL_TRIALS = 24
"""The issue asks for at least 20 random kills."""
NEW_IMAGES = 8
NEW_IMAGE_SIDE = 256
"""Noise images do not compress, so eight of them make the edit last tens of milliseconds:
long enough for most random kills to land inside it, short enough for a quick test."""
KILL_WINDOW_FACTOR = 1.3
"""Kill times are drawn over 1.3 x the measured edit duration, so some kills land before
the edit starts and some after it ends, and most in between."""

_fork = multiprocessing.get_context("fork")


def _new_images():
    rng = np.random.default_rng(7)  # the child and the checker must agree on the pixels
    return [
        ImageRecord(
            f"new{i}",
            rng.integers(0, 256, (NEW_IMAGE_SIDE,) * 2, dtype=np.uint8),
            f"/data/new{i}.png",
            f"{i:064x}",
            "calib",
        )
        for i in range(NEW_IMAGES)
    ]


def _began(path):
    return path.with_name(path.name + ".began")


def _write_new_content(path):
    with edit_session(path) as w:
        _began(path).touch()  # the edit is under way: a kill from now on lands inside it
        w.set_metadata(split=20)
        w.write_images(_new_images())
        w.write_record(
            Record("r", "added", attrs={"n": NEW_IMAGES}, arrays={"values": np.arange(20000.0)})
        )


def _make_old_session(path):
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(NEW_IMAGE_SIDE, NEW_IMAGE_SIDE), split=10)
        w.write_images(
            [
                ImageRecord(
                    "old0",
                    np.full((NEW_IMAGE_SIDE,) * 2, 9, np.uint8),
                    "/data/old0.png",
                    "a" * 64,
                    "calib",
                )
            ]
        )
        w.write_record(Record("r", "base", attrs={"n": 0}))


def _state_of(path) -> str:
    """'old' or 'new' after checking every item; fails on any mixture."""
    with open_session(path) as s:
        names = s.image_names()
        records = s.record_names("r")
        split = s.metadata().split
        np.testing.assert_array_equal(s.image("old0"), 9)
        if names == ["old0"]:
            assert (records, split) == (["base"], 10), "images old but other items new"
            return "old"
        assert names == ["new" + str(i) for i in range(NEW_IMAGES)] + ["old0"], names
        assert (records, split) == (["added", "base"], 20), "images new but other items old"
        for rec in _new_images():
            np.testing.assert_array_equal(s.image(rec.name), rec.pixels)
        np.testing.assert_array_equal(s.record("r", "added").arrays["values"], np.arange(20000.0))
        return "new"


def _temps(directory):
    return [p for p in directory.iterdir() if p.name.endswith(".endomeasure-tmp")]


def test_a_writer_killed_at_random_moments_leaves_old_or_new_content(tmp_path, rng):
    path = tmp_path / "s.h5"
    pristine = tmp_path / "pristine.h5"
    _make_old_session(pristine)

    durations = []
    for _ in range(2):
        shutil.copyfile(pristine, path)
        child = _fork.Process(target=_write_new_content, args=(path,))
        start = time.perf_counter()
        child.start()
        child.join()
        durations.append(time.perf_counter() - start)
        assert child.exitcode == 0
        assert _state_of(path) == "new"
    window = KILL_WINDOW_FACTOR * float(np.median(durations))

    outcomes = {"old": 0, "new": 0}
    killed_mid_edit = 0
    for delay in rng.uniform(0.0, window, KILL_TRIALS):
        shutil.copyfile(pristine, path)
        _began(path).unlink(missing_ok=True)
        child = _fork.Process(target=_write_new_content, args=(path,))
        child.start()
        time.sleep(delay)
        os.kill(child.pid, signal.SIGKILL)
        child.join()
        state = _state_of(path)
        killed_mid_edit += _began(path).exists() and state == "old"
        outcomes[state] += 1
        # the killed writer's lock is gone and its temp file is cleaned by the next edit
        with edit_session(path, lock_timeout=5.0) as w:
            w.write_record(Record("r", "after-kill"))
        assert _temps(tmp_path) == []
        assert "after-kill" in open_session(path).record_names("r")

    print(
        f"edit {np.median(durations) * 1e3:.0f} ms, outcomes {outcomes}, "
        f"killed mid-edit {killed_mid_edit}/{KILL_TRIALS}"
    )
    assert sum(outcomes.values()) == KILL_TRIALS
    # Not vacuous: the kills did interrupt edits and did land on both sides of the commit.
    assert killed_mid_edit >= 3
    assert outcomes["old"] >= 1 and outcomes["new"] >= 1


EDITS_PER_WRITER = 8


def _append_records(path, tag, barrier):
    barrier.wait()
    for i in range(EDITS_PER_WRITER):
        with edit_session(path, lock_timeout=30.0) as w:
            w.write_record(Record("log", f"{tag}{i}", arrays={"x": np.full(1000, i)}))
            # a read-modify-write: lost updates would show as a short count
            count = w.metadata().attrs.get("count", 0)
            w.set_metadata(count=count + 1)


def test_two_processes_editing_at_once_keep_each_others_work(tmp_path):
    path = tmp_path / "s.h5"
    with edit_session(path, create=True):
        pass
    barrier = _fork.Barrier(2)
    writers = [_fork.Process(target=_append_records, args=(path, tag, barrier)) for tag in "ab"]
    for w in writers:
        w.start()
    for w in writers:
        w.join(timeout=60)
        assert w.exitcode == 0
    with open_session(path) as s:
        assert s.record_names("log") == sorted(
            f"{tag}{i}" for tag in "ab" for i in range(EDITS_PER_WRITER)
        )
        assert s.metadata().attrs["count"] == 2 * EDITS_PER_WRITER


def test_a_held_lock_makes_others_wait_then_give_up_with_one_line(tmp_path):
    path = tmp_path / "s.h5"
    with edit_session(path, create=True):
        pass
    with SessionLock(path, exclusive=True):
        with pytest.raises(SessionError, match="locked by another endomeasure command"):
            with edit_session(path, lock_timeout=0.1):
                pass
        with pytest.raises(SessionError, match="locked"):
            open_session(path, lock_timeout=0.1)
    with SessionLock(path, exclusive=False):
        open_session(path, lock_timeout=0.1).close()  # readers share
        with pytest.raises(SessionError, match="locked"):
            with edit_session(path, lock_timeout=0.1):
                pass


def test_an_open_snapshot_does_not_see_later_edits(tmp_path):
    path = tmp_path / "s.h5"
    with edit_session(path, create=True) as w:
        w.write_record(Record("r", "first"))
    with open_session(path) as before:
        with edit_session(path) as w:
            w.write_record(Record("r", "second"))
        assert before.record_names("r") == ["first"]
        with open_session(path) as after:
            assert after.record_names("r") == ["first", "second"]
