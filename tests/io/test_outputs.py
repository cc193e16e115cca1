"""Output paths checked before work, and session edits through links."""

from __future__ import annotations

import os

import numpy as np
import pytest

from endomeasure.errors import BadInputError, SessionError
from endomeasure.io.integrity import seal_file
from endomeasure.io.outputs import (
    PLOT_SUFFIXES,
    atomic_write,
    checked_output,
    checked_output_dir,
    checked_outputs,
    checked_session_target,
)
from endomeasure.io.session import Record, edit_session, open_session


@pytest.fixture
def session(tmp_path):
    path = tmp_path / "s.h5"
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(64, 48), split=32)
    return path


def test_a_new_file_in_a_writable_folder_is_accepted_and_nothing_is_left(tmp_path):
    assert checked_output(tmp_path / "m.json", "model") == tmp_path / "m.json"
    assert list(tmp_path.iterdir()) == []  # the folder probe removed its file


@pytest.mark.parametrize("how", ["same", "symlink", "hard-link"])
def test_the_input_itself_is_refused_by_inode(session, tmp_path, how):
    out = {"same": session, "symlink": tmp_path / "l.h5", "hard-link": tmp_path / "h.h5"}[how]
    if how == "symlink":
        out.symlink_to(session)
    elif how == "hard-link":
        os.link(session, out)
    with pytest.raises(BadInputError, match="overwrite the command's input"):
        checked_output(out, "exported model", inputs=[session])


@pytest.mark.parametrize(
    ("make", "kind"),
    [(lambda p: p.mkdir(), "directory"), (lambda p: os.mkfifo(p), "FIFO")],
    ids=["directory", "fifo"],
)
def test_an_existing_special_file_is_refused(tmp_path, make, kind):
    target = tmp_path / "x.png"
    make(target)
    with pytest.raises(BadInputError, match=kind):
        checked_output(target, "plot")


def test_devices_missing_folders_and_unwritable_folders_are_refused(tmp_path):
    with pytest.raises(BadInputError, match="character device"):
        checked_output("/dev/null", "CSV file")
    with pytest.raises(BadInputError, match="does not exist"):
        checked_output(tmp_path / "no" / "x.csv", "CSV file")
    with pytest.raises(BadInputError, match="no file can be created"):
        checked_output("/proc/x.csv", "CSV file")


def test_plot_suffixes_and_outputs_that_collide(tmp_path):
    with pytest.raises(BadInputError, match="PNG / PDF / SVG"):
        checked_output(tmp_path / "x.h5", "plot", suffixes=PLOT_SUFFIXES)
    with pytest.raises(BadInputError, match="same file"):
        checked_outputs(
            [(tmp_path / "a.png", "plot", PLOT_SUFFIXES), (tmp_path / "a.png", "CSV file", None)]
        )
    assert checked_outputs([(None, "plot", None)]) == [None]


def test_a_symlinked_output_is_written_through_keeping_the_link_and_mode(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old\n")
    os.chmod(target, 0o600)
    link = tmp_path / "link.json"
    link.symlink_to(target)
    path = checked_output(link, "exported model")
    assert path == target
    atomic_write(path, lambda p: p.write_text("new\n"))
    assert link.is_symlink() and target.read_text() == "new\n"
    assert os.stat(target).st_mode & 0o777 == 0o600


def test_output_folders(tmp_path):
    assert checked_output_dir(tmp_path / "plots", "plot folder") == tmp_path / "plots"
    with pytest.raises(BadInputError, match="does not exist"):
        checked_output_dir(tmp_path / "a" / "b", "plot folder")
    assert checked_output_dir(tmp_path / "a" / "b", "output folder", create_parents=True)
    (tmp_path / "f").write_text("x")
    with pytest.raises(BadInputError, match="not a folder"):
        checked_output_dir(tmp_path / "f", "plot folder")
    assert not (tmp_path / "plots").exists() and not (tmp_path / "a").exists()


def test_an_edit_through_a_symlink_replaces_the_target_and_keeps_link_and_mode(session, tmp_path):
    os.chmod(session, 0o640)
    link = tmp_path / "link.h5"
    link.symlink_to(session.name)  # relative, as users make them
    with edit_session(link) as w:
        w.write_record(Record("note", "n1", attrs={"x": 1}))
    assert link.is_symlink() and os.readlink(link) == session.name
    with open_session(session) as s:
        assert s.record_names("note") == ["n1"]
    assert os.stat(session).st_mode & 0o777 == 0o640
    assert not (tmp_path / "link.h5.lock").exists()  # the target's lock was taken


def test_a_hard_linked_session_is_refused_for_edits_but_read(session, tmp_path):
    other = tmp_path / "other.h5"
    os.link(session, other)
    before = session.read_bytes()
    with pytest.raises(SessionError, match="2 hard links"), edit_session(other):
        pass
    assert session.read_bytes() == before and os.stat(session).st_nlink == 2
    with open_session(other) as s:
        assert s.metadata().image_size == (64, 48)


@pytest.mark.parametrize("create", [False, True])
def test_a_fifo_session_is_refused_without_opening_it(tmp_path, create):
    fifo = tmp_path / "s.h5"
    os.mkfifo(fifo)  # opening it for reading would block this test forever
    with pytest.raises(SessionError, match="FIFO"):
        checked_session_target(fifo, create=create)
    with pytest.raises(SessionError, match="FIFO"):
        open_session(fifo)


def test_a_crafted_image_size_is_refused_on_open(session):
    import h5py

    with h5py.File(session, "r+") as h5:
        h5["metadata"].attrs["image_size"] = np.array([64000, 48000])
    seal_file(session)
    with pytest.raises(SessionError, match="beyond the limit"):
        open_session(session)
