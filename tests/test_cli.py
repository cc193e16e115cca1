"""The command line: help, the error boundary, info, add-images, and the videos given to
add-images and detect."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import h5py
import numpy as np
import pytest
from tests.io.video_data import BOARD, IMAGE_SIZE, SPLIT, write_clip
from typer.testing import CliRunner

from endomeasure import __version__, cli
from endomeasure.conventions import Half
from endomeasure.io.integrity import seal_file
from endomeasure.io.session import (
    FORMAT_VERSION,
    Detection,
    ModelRecord,
    Record,
    edit_session,
    open_session,
)

runner = CliRunner()


def run_module(*args: str) -> subprocess.CompletedProcess:
    """Run ``python -m endomeasure`` (the console script's code path) in a subprocess."""
    return subprocess.run(
        [sys.executable, "-m", "endomeasure", *args], capture_output=True, text=True, timeout=60
    )


@pytest.fixture
def session(tmp_path, rng):
    path = tmp_path / "probe.h5"
    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(64, 48), split=32)
        w.write_board("cb1", "chessboard:9x6:1.0", {"cols": 9, "rows": 6, "square_mm": 1.0})
        w.write_detections(
            [
                Detection("img0", "cb1", Half.LEFT, np.arange(12), rng.uniform(0, 31, (12, 2))),
                Detection(
                    "img0", "cb1", Half.RIGHT, np.arange(0), np.zeros((0, 2)), failure="blur"
                ),
                Detection("img1", "cb1", Half.LEFT, np.arange(5), rng.uniform(0, 31, (5, 2))),
            ]
        )
        w.write_model(
            ModelRecord(
                "pinhole",
                "pinhole",
                np.zeros(3),
                ("fx", "fy", "k1"),
                attrs={"rms": 0.25},
                units={"rms": "px"},
            )
        )
        w.write_records([Record("measurement", "m1"), Record("measurement", "m2")])
    return path


def test_help_lists_the_commands_and_h_is_help():
    long = runner.invoke(cli.app, ["--help"])
    short = runner.invoke(cli.app, ["-h"])
    assert long.exit_code == short.exit_code == 0
    assert long.stdout == short.stdout
    for name in ("info", "add-images", "--debug", "--version"):
        assert name in long.stdout
    assert runner.invoke(cli.app, ["info", "-h"]).exit_code == 0


def test_version():
    result = runner.invoke(cli.app, ["--version"])
    assert result.exit_code == 0 and result.stdout.strip() == f"endomeasure {__version__}"


def test_info_json_is_one_document_with_the_counts(session):
    result = runner.invoke(cli.app, ["info", str(session), "--json"])
    assert result.exit_code == 0, result.stderr
    doc = json.loads(result.stdout)  # fails on anything but exactly one JSON document
    assert doc["format_version"] == FORMAT_VERSION
    assert doc["image_size"] == [64, 48] and doc["split"] == 32
    assert doc["images"] == {"calib": 0, "test": 0, "scene": 0}
    assert doc["boards"] == [{"name": "cb1", "spec": "chessboard:9x6:1.0"}]
    assert doc["detections"] == [
        {"board": "cb1", "half": "left", "images": 2, "found": 2, "failed": 0, "corners": 17},
        {"board": "cb1", "half": "right", "images": 1, "found": 0, "failed": 1, "corners": 0},
    ]
    assert doc["models"] == [
        {
            "name": "pinhole",
            "registry_name": "pinhole",
            "n_params": 3,
            "rms": 0.25,
            "rms_units": "px",
            "verdict": "unjudged",  # stored without a verdict
            "verdict_reasons": [],
        }
    ]
    assert doc["records"] == {"measurement": 2}


def test_info_human_output_goes_to_stderr(session):
    result = runner.invoke(cli.app, ["info", str(session)])
    assert result.exit_code == 0
    assert result.stdout == ""
    for text in ("64 x 48 px", "column 32", "chessboard:9x6:1.0", "0.2500 px", "2 measurement"):
        assert text in result.stderr


def write_pngs(directory, names, shape, rng):
    directory.mkdir(parents=True, exist_ok=True)
    for name in names:
        cv2.imwrite(str(directory / f"{name}.png"), rng.integers(0, 256, shape, dtype=np.uint8))


def test_add_images_embeds_sets_and_is_idempotent(tmp_path, rng):
    write_pngs(tmp_path / "calib", ["c0", "c1", "c2"], (24, 32), rng)
    write_pngs(tmp_path / "test", ["t0"], (24, 32), rng)
    session = tmp_path / "s.h5"
    for image_set in ("calib", "test"):
        result = runner.invoke(
            cli.app, ["add-images", str(session), str(tmp_path / image_set), "--set", image_set]
        )
        assert result.exit_code == 0, result.stderr
    again = runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "calib"), "--json"])
    assert json.loads(again.stdout)["added"] == []
    assert json.loads(again.stdout)["unchanged"] == ["c0", "c1", "c2"]
    doc = json.loads(runner.invoke(cli.app, ["info", str(session), "--json"]).stdout)
    assert doc["images"] == {"calib": 3, "test": 1, "scene": 0}
    assert doc["image_size"] == [32, 24]


def test_add_images_refuses_a_second_image_size_in_one_line(tmp_path, rng):
    write_pngs(tmp_path / "a", ["x"], (24, 32), rng)
    write_pngs(tmp_path / "b", ["y"], (20, 32), rng)
    session = tmp_path / "s.h5"
    assert runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "a")]).exit_code == 0
    result = runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "b")])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert "32x20 px but the session's images are 32x24 px" in result.stderr


def test_add_images_keeps_the_usable_files_and_lists_the_others(tmp_path, rng):
    write_pngs(tmp_path / "in", ["a", "b"], (24, 32), rng)
    write_pngs(tmp_path / "in", ["wide"], (24, 40), rng)  # another size than the first
    (tmp_path / "in" / "junk.png").write_bytes(b"not a png")
    session = tmp_path / "s.h5"
    result = runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "in"), "--json"])
    assert result.exit_code == 1, result.stderr
    doc = json.loads(result.stdout)
    assert doc["added"] == ["a", "b"] and doc["exit_code"] == 1
    failed = {item["path"].rsplit("/", 1)[-1]: item["error"] for item in doc["failed"]}
    assert set(failed) == {"junk.png", "wide.png"}
    assert "cannot decode" in failed["junk.png"] and "40x24" in failed["wide.png"]
    lines = result.stderr.splitlines()
    assert lines == [f"error: {doc['error']}"]
    assert lines[0].startswith("error: 2 image file(s) could not be used:")
    assert lines[0].endswith("the other images were stored")
    with open_session(session) as s:
        assert s.image_names() == ["a", "b"]
    plain = runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "in")])
    assert plain.exit_code == 1
    assert sum(line.startswith("not added: ") for line in plain.stderr.splitlines()) == 2
    assert plain.stderr.splitlines()[-1].startswith("error: 2 image file(s)")


def test_add_images_with_no_usable_file_creates_no_session(tmp_path, rng):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "junk.png").write_bytes(b"not a png")
    (tmp_path / "in" / "empty.png").write_bytes(b"")
    session = tmp_path / "s.h5"
    result = runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "in")])
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        "error: none of the 2 image files could be used: cannot decode the image file (2); "
        "nothing was stored"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_two_add_images_commands_at_once_keep_both(tmp_path, rng):
    write_pngs(tmp_path / "a", [f"a{i}" for i in range(4)], (24, 32), rng)
    write_pngs(tmp_path / "b", [f"b{i}" for i in range(4)], (24, 32), rng)
    session = tmp_path / "s.h5"
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "endomeasure",
                "add-images",
                str(session),
                str(tmp_path / d),
                "--json",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for d in "ab"
    ]
    for proc in procs:
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
    doc = json.loads(run_module("info", str(session), "--json").stdout)
    assert doc["images"]["calib"] == 8


def damage(kind: str, path):
    if kind == "missing":
        return path.parent / "missing.h5"
    if kind == "not-hdf5":
        path.write_bytes(b"GIF89a" + bytes(200))
    elif kind == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif kind == "future-version":
        with h5py.File(path, "r+") as f:
            f.attrs["format_version"] = "2.0"
        seal_file(path)
    return path


EXPECTED_MESSAGE = {
    "missing": "does not exist",
    "not-hdf5": "not HDF5",
    "truncated": "truncated or damaged",
    "future-version": "version 2.0, this endomeasure",
}


@pytest.mark.parametrize("kind", list(EXPECTED_MESSAGE))
def test_bad_session_files_give_one_line_and_exit_2(session, kind):
    path = damage(kind, session)
    result = run_module("info", str(path))
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1, result.stderr
    assert EXPECTED_MESSAGE[kind] in result.stderr and str(path) in result.stderr
    assert "Traceback" not in result.stderr


def test_debug_adds_the_traceback_and_keeps_the_exit_code(session):
    path = damage("not-hdf5", session)
    result = run_module("--debug", "info", str(path))
    assert result.returncode == 2
    assert "Traceback (most recent call last)" in result.stderr
    assert result.stderr.rstrip().splitlines()[-1].startswith("error: not a session")


def test_an_unexpected_exception_is_one_line_calling_itself_a_bug(session, monkeypatch):
    import endomeasure.pipeline.info as info

    def broken(path):
        raise ZeroDivisionError("division by zero\nsecond line")

    monkeypatch.setattr(info, "summarise_session", broken)
    result = runner.invoke(cli.app, ["info", str(session)])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert "internal error (ZeroDivisionError: division by zero second line)" in result.stderr
    assert "bug" in result.stderr and "--debug" in result.stderr
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_usage_errors_exit_2():
    assert runner.invoke(cli.app, ["info"]).exit_code == 2
    assert runner.invoke(cli.app, ["no-such-command"]).exit_code == 2


# ------------------------------------------------------------------- add-images with video


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_clip(tmp_path_factory.mktemp("clip") / "clip.avi", np.random.default_rng(7))


def test_add_images_picks_video_frames_and_stores_their_frame_numbers(tmp_path, clip):
    session = tmp_path / "s.h5"
    args = ["add-images", str(session), str(clip.path), "--board", BOARD, "--split", str(SPLIT)]
    result = runner.invoke(cli.app, [*args, "--json"])
    assert result.exit_code == 0, result.stderr
    video = json.loads(result.stdout)["videos"][0]
    assert {clip.kinds[i] for i in video["picked"]} <= {"sharp", "held"}
    with open_session(session) as s:
        infos = s.images_info("calib")
    assert [info.frame for info in infos] == video["picked"]
    assert {info.original_path for info in infos} == {str(clip.path)}
    human = runner.invoke(cli.app, args)
    assert human.exit_code == 0
    assert f"kept {len(video['picked'])}" in human.stderr and "blurred" in human.stderr


def _refused_without_touching(session, args):
    before = session.read_bytes() if session.exists() else None
    result = runner.invoke(cli.app, args)
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: ")
    assert (session.read_bytes() if session.exists() else None) == before
    return result.stderr


def test_add_images_refuses_bad_videos_in_one_line_leaving_the_session(tmp_path, clip, rng):
    session = tmp_path / "s.h5"
    write_pngs(tmp_path / "png", ["x"], (IMAGE_SIZE[1], IMAGE_SIZE[0]), rng)
    added = runner.invoke(cli.app, ["add-images", str(session), str(tmp_path / "png")])
    assert added.exit_code == 0
    cut = tmp_path / "cut.avi"
    cut.write_bytes(clip.path.read_bytes()[: clip.path.stat().st_size // 2])
    assert "truncated" in _refused_without_touching(
        session, ["add-images", str(session), str(cut), "--board", BOARD]
    )
    blank = tmp_path / "blank.avi"
    writer = cv2.VideoWriter(str(blank), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, IMAGE_SIZE)
    for level in (90, 100, 110):
        writer.write(np.full((IMAGE_SIZE[1], IMAGE_SIZE[0], 3), level, np.uint8))
    writer.release()
    assert "no frame of the video shows the whole board" in _refused_without_touching(
        session, ["add-images", str(session), str(blank), "--board", BOARD, "--split", "240"]
    )
    other = tmp_path / "other.h5"
    write_pngs(tmp_path / "small", ["y"], (48, 64), rng)
    added = runner.invoke(cli.app, ["add-images", str(other), str(tmp_path / "small")])
    assert added.exit_code == 0
    assert "session's images are 64x48 px" in _refused_without_touching(
        other, ["add-images", str(other), str(clip.path), "--frame-step", "2"]
    )
    assert "needs the board" in _refused_without_touching(
        tmp_path / "new.h5", ["add-images", str(tmp_path / "new.h5"), str(clip.path)]
    )


# ------------------------------------------------- bad videos for add-images and detect


@pytest.fixture(scope="module")
def bad_videos(tmp_path_factory, clip):
    """Videos each command must refuse: truncated (a valid clip cut to 40 % of its
    bytes), a file with a video suffix that is not a video, a clip of a plain grey field
    (no board in any frame), and the good clip (its frames are 480x320 px)."""
    folder = tmp_path_factory.mktemp("bad")
    cut = folder / "cut.avi"
    cut.write_bytes(clip.path.read_bytes()[: int(clip.path.stat().st_size * 0.4)])
    junk = folder / "junk.mp4"
    junk.write_bytes(b"\x00\x00\x00\x18ftypmp42 but nothing else " * 40)
    blank = folder / "blank.avi"
    writer = cv2.VideoWriter(str(blank), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, IMAGE_SIZE)
    for level in (90, 100, 110, 120):
        writer.write(np.full((IMAGE_SIZE[1], IMAGE_SIZE[0], 3), level, np.uint8))
    writer.release()
    return {"cut": cut, "junk": junk, "blank": blank, "good": clip.path}


def _session_with_an_image(folder, rng, shape=(IMAGE_SIZE[1], IMAGE_SIZE[0])):
    """A session holding one random image of ``shape`` (rows, cols), no detections."""
    folder.mkdir(parents=True, exist_ok=True)
    session = folder / "s.h5"
    write_pngs(folder / "png", ["x"], shape, rng)
    assert runner.invoke(cli.app, ["add-images", str(session), str(folder / "png")]).exit_code == 0
    return session


def _refused_naming(session, args, video, what):
    """Exit 2, one line naming the video and saying what is wrong and what to do, and the
    session's bytes unchanged."""
    message = _refused_without_touching(session, args)
    assert "Traceback" not in message
    assert what in message
    named = f"[{video}]; "
    assert named in message, message
    assert len(message.split(named, 1)[1].strip()) > 10  # the hint: what to do


COMMANDS = {
    "add-images": lambda session, video, *extra: ["add-images", str(session), str(video),
                                                  "--board", BOARD, *extra],
    "detect": lambda session, video, *extra: ["detect", str(session), str(video),
                                              "--board", BOARD, *extra],
}  # fmt: skip


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize(
    ("video", "extra", "what"),
    [
        ("cut", [], "truncated"),
        ("cut", ["--frame-step", "2"], "truncated"),
        ("junk", [], "cannot open the video file"),
        ("blank", ["--split", str(SPLIT)], "no frame of the video shows the whole board"),
    ],
)
def test_bad_videos_are_one_line_exit_2_and_leave_the_session(
    tmp_path, rng, bad_videos, command, video, extra, what
):
    session = _session_with_an_image(tmp_path, rng)
    args = COMMANDS[command](session, bad_videos[video], *extra)
    _refused_naming(session, args, bad_videos[video], what)


def test_detect_refuses_a_video_with_no_board_in_any_frame_taken(tmp_path, rng, bad_videos):
    # with a frame step nothing is picked: the frames are detected, and none has a board
    session = _session_with_an_image(tmp_path, rng)
    args = COMMANDS["detect"](session, bad_videos["blank"], "--frame-step", "1", "--split",
                              str(SPLIT))  # fmt: skip
    _refused_naming(session, args, bad_videos["blank"], "in either half of the 4 frames taken")


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("extra", [[], ["--frame-step", "3"]])
def test_a_video_of_another_frame_size_is_refused(tmp_path, rng, bad_videos, command, extra):
    session = _session_with_an_image(tmp_path, rng, shape=(48, 64))
    args = COMMANDS[command](session, bad_videos["good"], *extra)
    _refused_naming(session, args, bad_videos["good"], "session's images are 64x48 px")


def test_detect_stores_the_frames_of_a_video_from_the_command_line(tmp_path, clip):
    session = tmp_path / "s.h5"
    args = ["detect", str(session), str(clip.path), "--board", BOARD, "--split", str(SPLIT)]
    result = runner.invoke(cli.app, [*args, "--json"])
    assert result.exit_code == 0, result.stderr
    document = json.loads(result.stdout)
    picked = document["videos"][0]["picked"]
    assert [image["frame"] for image in document["images"]] == picked
    with open_session(session) as s:
        assert [i.frame for i in s.images_info("calib")] == picked
    human = runner.invoke(cli.app, [*args, "--frame-step", "4"])
    assert human.exit_code in (0, 1)
    assert f"{clip.path}: {len(clip.kinds)} frames, kept 4" in human.stderr


@pytest.mark.parametrize("command", COMMANDS)
def test_a_truncated_video_is_one_line_in_a_real_process(tmp_path, rng, bad_videos, command):
    # what a user sees: the decoder's own complaints must not reach stderr either
    session = _session_with_an_image(tmp_path, rng)
    before = session.read_bytes()
    result = run_module(*COMMANDS[command](session, bad_videos["cut"]))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: ")
    assert f"[{bad_videos['cut']}]; " in result.stderr and "truncated" in result.stderr
    assert session.read_bytes() == before


# ----- terminal output: whole numbers in tables, reflowed help ----------------------------

ELLIPSIS = "\u2026"


def test_a_wide_table_piped_at_80_columns_prints_every_number_whole(tmp_path):
    from tests.conftest import make_pinhole_model
    from tests.pipeline.measure_data import build_session

    session, _ = build_session(tmp_path / "m.h5", models=("pinhole",))
    model = make_pinhole_model()
    points = np.array([[-2.0, 0.5, 15.0], [1.5, -1.0, 19.0]])
    args = ["measure", str(session), "--model", "pinhole", "--image", "scene"]
    for half, option in ((Half.LEFT, "--left"), (Half.RIGHT, "--right")):
        for q in model.project(points, half).pixels:
            args += [option, f"{q[0]:.6f},{q[1]:.6f}"]
    result = runner.invoke(cli.app, args, env={"COLUMNS": "80"})  # captured: not a terminal
    assert result.exit_code == 0, result.output
    assert ELLIPSIS not in result.stderr
    table_lines = [line for line in result.stderr.splitlines() if "│" in line]
    assert max(len(line) for line in table_lines) > 80  # the table is wider than 80 columns
    for half in (Half.LEFT, Half.RIGHT):
        for q in model.project(points, half).pixels:
            assert "{:.2f},{:.2f}".format(*q) in result.stderr
    for p in points:
        assert all(f"{v:.4f}" in result.stderr for v in p)


def test_measure_help_paragraphs_are_reflowed_to_the_width():
    """At 100 columns each line of a help paragraph but its last is filled: the next
    line's first word would not have fitted on it (the docstring's own line breaks,
    ~88 characters, would leave room)."""
    result = runner.invoke(cli.app, ["measure", "-h"], env={"COLUMNS": "100"})
    assert result.exit_code == 0
    text = result.stdout.split("╭")[0]  # the description, before the option boxes
    paragraphs = [[]]
    for line in (line.rstrip() for line in text.splitlines()):
        if line:
            paragraphs[-1].append(line)
        elif paragraphs[-1]:
            paragraphs.append([])
    checked = 0
    for lines in paragraphs:
        if lines and lines[0].lstrip().startswith("Usage:"):
            continue
        for line, following in zip(lines, lines[1:], strict=False):
            if following.lstrip().startswith("- "):  # a list item starts its own line
                continue
            next_word = following.split()[0]
            assert len(line) + 1 + len(next_word) > 100 - 4, (line, following)
            checked += 1
    assert checked >= 3  # the measure description wraps over several lines


def test_no_help_text_is_cut_at_80_columns():
    """Every command's help, piped at 80 columns, shows its words whole (rich cuts a word
    longer than its cell with an ellipsis)."""
    commands = [c.name for c in cli.app.registered_commands]
    assert {"report", "verify", "compare"} <= set(commands)
    for name in commands:
        result = runner.invoke(cli.app, [name, "-h"], env={"COLUMNS": "80"})
        assert result.exit_code == 0, name
        assert ELLIPSIS not in result.stdout, name
