"""Hostile input: bad options, impossible outputs, odd files, crafted sessions, limits.

Every case runs the command line as a careless user would and checks the output
contract (``endomeasure.cli``): the exit code; exactly one stderr line that starts with
``error:`` and no traceback or "bug"; every file of the sessions' folder byte for byte
as before (nothing written, replaced or created, lock sidecars aside); and stdout empty,
or with ``--json`` one strict JSON document (no ``NaN``) carrying the error and the exit
code. Each case runs with and without ``--json``.

The sessions are built once per module: a calibrated one from a known model
(``tests.pipeline.measure_data``), links to it, and copies whose metadata or datasets are
crafted with h5py.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from tests.conftest import make_raytrace_model
from tests.hostile_data import crafted, png_header_only, replace_image, run_measured
from tests.pipeline.measure_data import BOARD, board_points, build_session
from typer.testing import CliRunner

from endomeasure import cli, defaults

runner = CliRunner()

MAX_REFUSAL_RSS_MB = 300
"""The issue's bound on the peak memory of refusing a 30000 x 30000 PNG."""


# ----------------------------------------------------------------------------- the world


def _huge_detection(h5) -> None:
    """The pixels of one stored detection, declared as 1e9 corners (empty chunks on disk)."""
    node = h5["detections"][BOARD]
    pixels = node[sorted(node.keys())[0]]["left"]
    attrs = dict(pixels["pixels"].attrs)
    del pixels["pixels"]
    dset = pixels.create_dataset("pixels", shape=(10**9, 2), dtype="f8", chunks=(4096, 2))
    for key, value in attrs.items():
        dset.attrs[key] = value


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Paths for the cases: ``{S}`` the calibrated session and its neighbours."""
    root = tmp_path_factory.mktemp("hostile")
    data = root / "data"  # every file here is hashed before and after each case
    data.mkdir()
    session, _ = build_session(data / "s.h5")
    (data / "link.h5").symlink_to(session)
    shutil.copyfile(session, data / "h1.h5")
    os.link(data / "h1.h5", data / "h2.h5")
    os.mkfifo(data / "fifo")
    os.mkfifo(data / "fifo.png")
    os.mkfifo(data / "fifo.json")
    (data / "text.h5").write_text("not a session\n")
    (data / "empty.h5").write_bytes(b"")
    with h5py.File(data / "plain.h5", "w") as h5:
        h5["x"] = np.arange(3)
    head = session.read_bytes()
    (data / "cut.h5").write_bytes(head[: len(head) // 3])
    crafted(session, data / "future.h5", lambda h5: h5.attrs.__setitem__("format_version", "9.0"))
    crafted(
        session,
        data / "huge-meta.h5",
        lambda h5: h5["metadata"].attrs.__setitem__("image_size", np.array([64000, 48000])),
    )
    crafted(
        session,
        data / "split.h5",
        lambda h5: h5["metadata"].attrs.__setitem__("split", 5000),
    )
    crafted(
        session,
        data / "huge-image.h5",
        lambda h5: replace_image(h5, "scene", (48000, 64000), "u1"),
    )
    crafted(session, data / "shape.h5", lambda h5: replace_image(h5, "scene", (480, 320), "u1"))
    crafted(session, data / "float.h5", lambda h5: replace_image(h5, "scene", (480, 640), "f8"))
    crafted(session, data / "huge-detection.h5", _huge_detection)
    crafted(
        session,
        data / "variance.h5",
        lambda h5: h5["models"]["raytrace"].attrs.__setitem__("residual_variance", "big"),
    )
    crafted(
        session,
        data / "bytes.h5",
        lambda h5: h5.attrs.__setitem__("created_by", np.bytes_(b"\xff\xfe endomeasure")),
    )

    images = root / "images"
    images.mkdir()
    (images / "empty").mkdir()
    junk = images / "junk"
    junk.mkdir()
    (junk / "garbage.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    (junk / "zero.png").write_bytes(b"")
    (junk / "text.png").write_text("hello\n")
    (images / "notes.txt").write_text("not an image\n")
    (images / "clip.avi").write_bytes(b"RIFF not a video")
    big = images / "big"
    big.mkdir()
    png_header_only(big / "huge.png", 30000, 30000)
    png_header_only(images / "wide.png", defaults.MAX_IMAGE_SIDE + 1, 8)
    small = images / "small"
    small.mkdir()
    cv2.imwrite(str(small / "s.png"), np.full((24, 32), 128, np.uint8))
    warns = images / "warns"  # a PNG whose bad colour profile makes libpng warn on stderr
    warns.mkdir()
    png_header_only(warns / "w.png", 32, 24, iccp=True)
    flat = images / "flat"
    flat.mkdir()
    cv2.imwrite(str(flat / "f.png"), np.full((480, 640), 128, np.uint8))

    out = root / "out"  # where valid outputs would go
    out.mkdir()
    (out / "existing-dir").mkdir()
    (out / "dir.png").mkdir()
    (out / "file.txt").write_text("x\n")
    return {
        "S": str(session),
        "D": str(data),
        "I": str(images),
        "O": str(out),
        "data": data,
        "root": root,
    }


def _hashes(root: Path) -> dict[str, str]:
    """Everything under ``root`` (lock sidecars aside): the SHA-256 of each regular file,
    the target of each link, and the kind of everything else, so that a file replaced,
    changed, created or deleted, or a link turned into a file, shows."""
    out = {}
    for path in sorted(root.rglob("*")):
        key = str(path.relative_to(root))
        if path.name.endswith(".lock"):
            continue
        if path.is_symlink():
            out[key] = "link to " + os.readlink(path)
        elif path.is_file():
            out[key] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[key] = "directory" if path.is_dir() else "special"
    return out


def _strict_json(text: str):
    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def _args(template: list[str], world: dict, json_output: bool) -> list[str]:
    args = [a.format(**world) for a in template]
    if json_output:  # right after the command name: never taken as an option's value
        index = next(i for i, a in enumerate(args) if not a.startswith("--"))
        args.insert(index + 1, "--json")
    return args


def check_refusal(world, template, code, message, json_output):
    """Run one case and check the output contract (module docstring)."""
    before = _hashes(world["root"])
    args = _args(template, world, json_output)
    result = runner.invoke(cli.app, args)
    assert result.exit_code == code, (args, result.stderr, result.stdout)
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, result.stderr
    assert result.stderr.rstrip("\n").splitlines()[-1] == errors[0]
    assert "Traceback" not in result.stderr + result.stdout
    assert "bug" not in result.stderr
    assert len(errors[0]) <= len("error: ") + cli.ERROR_LINE_LIMIT
    if message:
        assert message in errors[0], errors[0]
    if json_output:
        doc = _strict_json(result.stdout)
        assert doc["exit_code"] == code and doc["error"] == errors[0].removeprefix("error: ")
    else:
        assert result.stdout == ""
    assert _hashes(world["root"]) == before
    return errors[0]


def cases(*rows):
    """``pytest.param(args, code, message, id=...)`` for each row ``(id, args, code,
    message)``."""
    return [pytest.param(args, code, message, id=name) for name, args, code, message in rows]


JSON = pytest.mark.parametrize("json_output", [False, True], ids=["text", "json"])

# ------------------------------------------------------------------------- usage errors

USAGE = cases(
    ("info-unknown-option", ["info", "{S}", "--bogus"], 2, "No such option"),
    ("export-unknown-option", ["export", "{S}", "{O}/m.json", "--colour"], 2, "No such option"),
    ("measure-unknown-option", ["measure", "{S}", "--frobnicate", "3"], 2, "No such option"),
    (
        "detect-workers-abc",
        ["detect", "{S}", "{I}/flat", "--board", BOARD, "--workers", "abc"],
        2,
        "--workers",
    ),
    ("simulate-seed-abc", ["simulate", "{O}/sim", "--seed", "abc"], 2, "--seed"),
    ("measure-patch-abc", ["measure", "{S}", "--patch", "abc"], 2, "--patch"),
    ("measure-zone-abc", ["measure", "{S}", "--board-test", "--zone-mm", "wide"], 2, "--zone-mm"),
    ("predict-samples-abc", ["predict-error", "{S}", "--map", "--samples", "many"], 2, "--samples"),
    ("predict-rho-abc", ["predict-error", "{S}", "--map", "--rho-images", "x"], 2, "--rho-images"),
    ("calibrate-index-abc", ["calibrate", "{S}", "--glass-index", "glass"], 2, "--glass-index"),
    ("measure-warn-abc", ["measure", "{S}", "--warn-percent", "lots"], 2, "--warn-percent"),
    ("info-missing-session", ["info"], 2, "Missing argument"),
    ("export-missing-out", ["export", "{S}"], 2, "Missing argument"),
    ("detect-missing-board", ["detect", "{S}", "{I}/flat"], 2, "Missing option"),
    ("detect-missing-images", ["detect", "{S}", "--board", BOARD], 2, "Missing argument"),
    ("calibrate-missing-session", ["calibrate"], 2, "Missing argument"),
    ("measure-missing-session", ["measure"], 2, "Missing argument"),
    ("simulate-missing-folder", ["simulate"], 2, "Missing argument"),
    ("no-such-command", ["frobnicate", "{S}"], 2, "No such command"),
    ("extra-argument", ["info", "{S}", "{S}"], 2, "unexpected extra argument"),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), USAGE)
def test_usage_errors_are_one_line(world, template, code, message, json_output):
    line = check_refusal(world, template, code, message, json_output)
    assert "--help" in line  # the hint: where to read about the options


# ---------------------------------------------------------------- outputs never destroy

OUTPUTS = cases(
    ("export-over-session", ["export", "{S}", "{S}", "--model", "raytrace"], 2, "overwrite"),
    (
        "export-over-symlink",
        ["export", "{S}", "{D}/link.h5", "--model", "raytrace"],
        2,
        "overwrite",
    ),
    ("export-to-device", ["export", "{S}", "/dev/null", "--model", "raytrace"], 2, "device"),
    (
        "export-to-directory",
        ["export", "{S}", "{O}/existing-dir", "--model", "raytrace"],
        2,
        "directory",
    ),
    ("export-to-fifo", ["export", "{S}", "{D}/fifo.json", "--model", "raytrace"], 2, "FIFO"),
    (
        "export-to-proc",
        ["export", "{S}", "/proc/x.json", "--model", "raytrace"],
        2,
        "no file can be created",
    ),
    (
        "export-missing-folder",
        ["export", "{S}", "{O}/nope/m.json", "--model", "raytrace"],
        2,
        "does not exist",
    ),
    (
        "export-yaml-suffix",
        ["export", "{S}", "{O}/m.json", "--model", "raytrace", "--format", "opencv-yaml"],
        2,
        "",
    ),
    (
        "board-test-plot-h5",
        ["measure", "{S}", "--board-test", "--plot", "{O}/x.h5"],
        2,
        "PNG / PDF / SVG",
    ),
    (
        "board-test-plot-session",
        ["measure", "{S}", "--board-test", "--plot", "{S}"],
        2,
        "overwrite",
    ),
    (
        "board-test-plot-dir",
        ["measure", "{S}", "--board-test", "--plot", "{O}/dir.png"],
        2,
        "directory",
    ),
    (
        "board-test-plot-missing",
        ["measure", "{S}", "--board-test", "--plot", "{O}/no/x.png"],
        2,
        "does not exist",
    ),
    (
        "board-test-plot-proc",
        ["measure", "{S}", "--board-test", "--plot", "/proc/x.png"],
        2,
        "no file can be created",
    ),
    (
        "measure-plot-h5",
        [
            "measure",
            "{S}",
            "--image",
            "scene",
            "--left",
            "300,240",
            "--left",
            "310,240",
            "--plot",
            "{O}/x.h5",
        ],
        2,
        "PNG / PDF / SVG",
    ),
    (
        "predict-plot-h5",
        ["predict-error", "{S}", "--board-test", "--plot", "{O}/x.h5"],
        2,
        "PNG / PDF / SVG",
    ),
    (
        "predict-plot-session",
        ["predict-error", "{S}", "--board-test", "--plot", "{D}/link.h5"],
        2,
        "overwrite",
    ),
    (
        "map-csv-missing-folder",
        ["predict-error", "{S}", "--map", "--csv", "/nope/x.csv"],
        2,
        "does not exist",
    ),
    ("map-csv-session", ["predict-error", "{S}", "--map", "--csv", "{S}"], 2, "overwrite"),
    ("map-csv-device", ["predict-error", "{S}", "--map", "--csv", "/dev/null"], 2, "device"),
    (
        "map-csv-is-plot",
        ["predict-error", "{S}", "--map", "--csv", "{O}/m.png", "--plot", "{O}/m.png"],
        2,
        "same file",
    ),
    ("map-csv-dir", ["predict-error", "{S}", "--map", "--csv", "{O}/existing-dir"], 2, "directory"),
    ("calibrate-plot-file", ["calibrate", "{S}", "--plot", "{O}/file.txt"], 2, "not a folder"),
    ("calibrate-plot-missing", ["calibrate", "{S}", "--plot", "/nope/plots"], 2, "does not exist"),
    ("simulate-into-session", ["simulate", "{S}"], 2, "not a folder"),
    ("simulate-into-device", ["simulate", "/dev/null"], 2, "not a folder"),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), OUTPUTS)
def test_outputs_that_would_destroy_are_refused(world, template, code, message, json_output):
    check_refusal(world, template, code, message, json_output)


# ----------------------------------------------------------------------- session paths

SESSIONS = cases(
    ("info-missing", ["info", "{D}/nope.h5"], 2, "does not exist"),
    ("info-directory", ["info", "{O}"], 2, "directory"),
    ("info-fifo", ["info", "{D}/fifo"], 2, "FIFO"),
    ("info-device", ["info", "/dev/null"], 2, "device"),
    ("info-text", ["info", "{D}/text.h5"], 2, "not HDF5"),
    ("info-empty", ["info", "{D}/empty.h5"], 2, "not HDF5"),
    ("info-truncated", ["info", "{D}/cut.h5"], 2, ""),
    ("info-plain-hdf5", ["info", "{D}/plain.h5"], 2, "not an endomeasure session"),
    ("info-future", ["info", "{D}/future.h5"], 2, "version"),
    ("export-fifo", ["export", "{D}/fifo", "{O}/m.json"], 2, "FIFO"),
    ("measure-truncated", ["measure", "{D}/cut.h5", "--board-test"], 2, ""),
    ("predict-text", ["predict-error", "{D}/text.h5", "--board-test"], 2, "not HDF5"),
    ("calibrate-missing", ["calibrate", "{D}/nope.h5"], 2, "does not exist"),
    ("calibrate-fifo", ["calibrate", "{D}/fifo"], 2, "FIFO"),
    ("calibrate-hard-link", ["calibrate", "{D}/h1.h5"], 2, "hard links"),
    ("calibrate-no-calib-images", ["calibrate", "{S}"], 2, "no calibration images"),
    ("board-test-hard-link", ["measure", "{D}/h2.h5", "--board-test"], 2, "hard links"),
    ("add-images-hard-link", ["add-images", "{D}/h1.h5", "{I}/flat"], 2, "hard links"),
    ("add-images-to-fifo", ["add-images", "{D}/fifo", "{I}/flat"], 2, "FIFO"),
    ("add-images-to-device", ["add-images", "/dev/null", "{I}/flat"], 2, "device"),
    ("add-images-no-folder", ["add-images", "{D}/nope/s.h5", "{I}/flat"], 2, "does not exist"),
    ("add-images-in-proc", ["add-images", "/proc/s.h5", "{I}/flat"], 2, ""),
    ("detect-to-fifo", ["detect", "{D}/fifo", "{I}/flat", "--board", BOARD], 2, "FIFO"),
    ("detect-hard-link", ["detect", "{D}/h2.h5", "{I}/flat", "--board", BOARD], 2, "hard links"),
    ("detect-text", ["detect", "{D}/text.h5", "{I}/flat", "--board", BOARD], 2, "not HDF5"),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), SESSIONS)
def test_bad_session_paths_are_one_line(world, template, code, message, json_output):
    check_refusal(world, template, code, message, json_output)


# ------------------------------------------------------------------- crafted sessions

CRAFTED = cases(
    ("info-huge-metadata", ["info", "{D}/huge-meta.h5"], 2, "beyond the limit"),
    ("info-split-outside", ["info", "{D}/split.h5"], 2, "split column"),
    (
        "measure-huge-image",
        [
            "measure",
            "{D}/huge-image.h5",
            "--image",
            "scene",
            "--left",
            "300,240",
            "--left",
            "310,240",
        ],
        2,
        "beyond the limit",
    ),
    (
        "measure-image-shape",
        ["measure", "{D}/shape.h5", "--image", "scene", "--left", "300,240", "--left", "310,240"],
        2,
        "declares 640x480",
    ),
    (
        "measure-float-image",
        ["measure", "{D}/float.h5", "--image", "scene", "--left", "300,240", "--left", "310,240"],
        2,
        "pixel type",
    ),
    (
        "board-test-huge-metadata",
        ["measure", "{D}/huge-meta.h5", "--board-test"],
        2,
        "beyond the limit",
    ),
    (
        "board-test-huge-detection",
        ["measure", "{D}/huge-detection.h5", "--board-test"],
        2,
        "any session holds",
    ),
    ("predict-string-variance", ["predict-error", "{D}/variance.h5", "--map"], 2, "not a number"),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), CRAFTED)
def test_crafted_sessions_are_refused_before_reading(world, template, code, message, json_output):
    check_refusal(world, template, code, message, json_output)


def test_a_bytes_creator_still_gives_strict_json(world):
    result = runner.invoke(cli.app, ["info", f"{world['D']}/bytes.h5", "--json"])
    assert result.exit_code == 0, result.stderr
    assert "endomeasure" in _strict_json(result.stdout)["created_by"]


# ---------------------------------------------------------------------------- limits

_POINTS = [a for i in range(defaults.MAX_POINTS_PER_MEASUREMENT + 1)
           for a in ("--left", f"{100 + i % 200},{100 + i // 200}")]  # fmt: skip
_MEASURE = ["measure", "{S}", "--image", "scene", "--left", "300,240", "--left", "310,240"]
_MAP = ["predict-error", "{S}", "--map"]

LIMITS = cases(
    (
        "workers-1000",
        ["detect", "{D}/new.h5", "{I}/flat", "--board", BOARD, "--workers", "1000"],
        2,
        "per CPU",
    ),
    (
        "workers-0",
        ["detect", "{D}/new.h5", "{I}/flat", "--board", BOARD, "--workers", "0"],
        2,
        "at least 1",
    ),
    ("samples-huge", [*_MAP, "--method", "mc", "--samples", "1000000000"], 2, "--samples"),
    ("samples-few", [*_MAP, "--method", "mc", "--samples", "3"], 2, "--samples"),
    ("grid-huge", [*_MAP, "--grid", "100000,100000"], 2, "points"),
    ("grid-tiny", [*_MAP, "--grid", "1,1"], 2, "2x2"),
    ("grid-junk", [*_MAP, "--grid", "a,b"], 2, "grid"),
    ("depths-tiny-step", [*_MAP, "--depths", "10:45:1e-9"], 2, "planes"),
    ("depths-nan", [*_MAP, "--depths", "nan,12"], 2, "depths"),
    ("depths-negative", [*_MAP, "--depths", "-5,10"], 2, "depths"),
    ("depths-junk", [*_MAP, "--depths", "near:far"], 2, "depths"),
    ("size-zero", [*_MAP, "--size-mm", "0"], 2, "template size"),
    ("size-nan", [*_MAP, "--size-mm", "nan"], 2, "template size"),
    ("sigma-huge", [*_MAP, "--sigma", "1e308"], 2, "beyond"),
    ("sigma-negative", [*_MAP, "--sigma", "-1"], 2, "sigma"),
    ("sigma-inf", [*_MAP, "--sigma", "inf"], 2, "sigma"),
    ("sigma-three", [*_MAP, "--sigma", "1,2,3"], 2, "noise"),
    ("rho-nan", [*_MAP, "--rho-images", "nan"], 2, "--rho-images"),
    ("rho-two", [*_MAP, "--rho-images", "2"], 2, "--rho-images"),
    ("zone-tiny", ["measure", "{S}", "--board-test", "--zone-mm", "1e-9"], 2, "below"),
    ("zone-zero", ["measure", "{S}", "--board-test", "--zone-mm", "0"], 2, "positive"),
    ("zone-nan", ["measure", "{S}", "--board-test", "--zone-mm", "nan"], 2, "positive"),
    ("zone-inf", ["predict-error", "{S}", "--board-test", "--zone-mm", "inf"], 2, "positive"),
    ("patch-huge", [*_MEASURE, "--patch", "100001"], 2, "larger than"),
    ("patch-even", [*_MEASURE, "--patch", "14"], 2, "patch size"),
    ("patch-zero", [*_MEASURE, "--patch", "0"], 2, "patch size"),
    (
        "too-many-points",
        ["measure", "{S}", "--image", "scene", "--kind", "polyline", *_POINTS],
        2,
        "more than",
    ),
    ("warn-negative", [*_MEASURE, "--warn-percent", "-3"], 2, "threshold"),
    (
        "pixel-nan",
        ["measure", "{S}", "--image", "scene", "--left", "nan,1", "--left", "3,4"],
        2,
        "not finite",
    ),
    (
        "pixel-junk",
        ["measure", "{S}", "--image", "scene", "--left", "here", "--left", "3,4"],
        2,
        "pixel",
    ),
    ("huge-png-new-session", ["add-images", "{D}/new.h5", "{I}/big"], 2, "beyond the limit"),
    ("huge-png-session", ["add-images", "{S}", "{I}/big"], 2, "beyond the limit"),
    ("wide-png", ["add-images", "{D}/new.h5", "{I}/wide.png"], 2, "beyond the limit"),
    (
        "huge-png-detect",
        ["detect", "{D}/new.h5", "{I}/big", "--board", BOARD],
        2,
        "beyond the limit",
    ),
    ("small-png-session", ["add-images", "{S}", "{I}/small"], 2, "but the session's images"),
    ("glass-index-low", ["calibrate", "{S}", "--glass-index", "0.9"], 2, "exceed 1"),
    (
        "frame-step-zero",
        ["add-images", "{D}/new.h5", "{I}/flat", "--frame-step", "0"],
        2,
        "--frame-step",
    ),
    ("simulate-negative-seed", ["simulate", "{O}/sim", "--seed", "-1"], 2, "seed"),
    (
        "split-junk",
        ["detect", "{D}/new.h5", "{I}/flat", "--board", BOARD, "--split", "middle"],
        2,
        "--split",
    ),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), LIMITS)
def test_limits_are_checked_before_work(world, template, code, message, json_output):
    check_refusal(world, template, code, message, json_output)


# ------------------------------------------------------------------------ image inputs

IMAGES = cases(
    ("add-empty-folder", ["add-images", "{D}/new.h5", "{I}/empty"], 2, "no image file"),
    ("add-nothing", ["add-images", "{D}/new.h5"], 2, "no image given"),
    ("add-garbage", ["add-images", "{D}/new.h5", "{I}/junk"], 2, "decode"),
    ("add-fifo", ["add-images", "{D}/new.h5", "{D}/fifo.png"], 2, "FIFO"),
    ("add-missing", ["add-images", "{D}/new.h5", "{I}/nope.png"], 2, "no such file"),
    ("add-text-file", ["add-images", "{D}/new.h5", "{I}/notes.txt"], 2, "not an image file"),
    (
        "add-bad-video",
        ["add-images", "{D}/new.h5", "{I}/clip.avi", "--frame-step", "1"],
        2,
        "video",
    ),
    ("add-bad-set", ["add-images", "{D}/new.h5", "{I}/flat", "--set", "holiday"], 2, "image set"),
    (
        "detect-empty-folder",
        ["detect", "{D}/new.h5", "{I}/empty", "--board", BOARD],
        2,
        "no image to detect",
    ),
    ("detect-garbage", ["detect", "{D}/new.h5", "{I}/junk", "--board", BOARD], 2, "nothing usable"),
    (
        "detect-fifo",
        ["detect", "{D}/new.h5", "{D}/fifo.png", "--board", BOARD],
        2,
        "nothing usable",
    ),
    (
        "detect-no-board",
        ["detect", "{D}/new.h5", "{I}/flat", "--board", BOARD, "--split", "320"],
        2,
        "nothing usable",
    ),
    (
        "detect-bad-set",
        ["detect", "{D}/new.h5", "{I}/flat", "--board", BOARD, "--set", "x"],
        2,
        "image set",
    ),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), IMAGES)
def test_bad_images_are_one_line(world, template, code, message, json_output):
    check_refusal(world, template, code, message, json_output)


# ------------------------------------------------------------------------ board specs

BOARDS = cases(
    ("zero-cols", ["detect", "{D}/new.h5", "{I}/flat", "--board", "chessboard:0x6:1"], 2, ""),
    ("letters", ["detect", "{D}/new.h5", "{I}/flat", "--board", "chessboard:axb:1"], 2, ""),
    (
        "negative-square",
        ["detect", "{D}/new.h5", "{I}/flat", "--board", "chessboard:7x6:-1"],
        2,
        "",
    ),
    ("unknown-kind", ["detect", "{D}/new.h5", "{I}/flat", "--board", "circles:7x6:1"], 2, ""),
    ("charuco-short", ["detect", "{D}/new.h5", "{I}/flat", "--board", "charuco:5x5:1"], 2, ""),
    ("empty-spec", ["detect", "{D}/new.h5", "{I}/flat", "--board", ""], 2, ""),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), BOARDS)
def test_bad_board_specs_are_one_line(world, template, code, message, json_output):
    check_refusal(world, template, code, message, json_output)


# ----------------------------------------------------------- options with no effect

IGNORED = cases(
    (
        "board-test-with-points",
        ["measure", "{S}", "--board-test", "--left", "1,2"],
        2,
        "no effect with --board-test",
    ),
    (
        "board-test-with-image",
        ["measure", "{S}", "--board-test", "--image", "scene"],
        2,
        "no effect",
    ),
    ("zone-without-board-test", [*_MEASURE, "--zone-mm", "3"], 2, "no effect without"),
    (
        "model-with-measurement",
        ["predict-error", "{S}", "--measurement", "m1", "--model", "pinhole"],
        2,
        "--model has no effect",
    ),
    (
        "grid-with-board-test",
        ["predict-error", "{S}", "--board-test", "--grid", "4,4"],
        2,
        "--grid has no effect",
    ),
    ("samples-without-mc", [*_MAP, "--samples", "1000"], 2, "--samples has no effect"),
    ("zone-with-map", [*_MAP, "--zone-mm", "3"], 2, "no effect with --map"),
    ("two-modes", ["predict-error", "{S}", "--map", "--board-test"], 2, "one mode"),
    ("bogus-model", [*_MEASURE, "--model", "bogus"], 2, "give --model one of the stored"),
)


@JSON
@pytest.mark.parametrize(("template", "code", "message"), IGNORED)
def test_options_are_never_silently_ignored(world, template, code, message, json_output):
    line = check_refusal(world, template, code, message, json_output)
    assert "calibrate --model bogus" not in line


# ------------------------------------------------------------- JSON on success is strict


@pytest.mark.parametrize(
    "template",
    [
        ["info", "{S}", "--json"],
        ["predict-error", "{S}", "--map", "--grid", "3,3", "--depths", "14,20", "--json"],
    ],
    ids=["info", "map"],
)
def test_json_documents_are_strict(world, template, tmp_path):
    # on a copy: these commands may store records
    copy = tmp_path / "s.h5"
    shutil.copyfile(world["S"], copy)
    result = runner.invoke(cli.app, [a.format(**{**world, "S": str(copy)}) for a in template])
    assert result.exit_code == 0, result.stderr
    assert isinstance(_strict_json(result.stdout), dict)


def test_nan_and_bytes_become_strict_json():
    doc = cli._json_safe({"a": float("nan"), "b": [np.float64("inf"), 1.5], "c": b"\xff",
                          "d": np.int32(3), "e": (1, 2)})  # fmt: skip
    assert doc == {"a": None, "b": [None, 1.5], "c": "\ufffd", "d": 3, "e": [1, 2]}
    json.dumps(doc, allow_nan=False)


# --------------------------------------------------- a long line keeps its file and hint


@pytest.mark.parametrize("length", [10, 299, 300, 1000, 100_000])
def test_a_long_error_line_keeps_its_end_and_its_hint(length):
    what = "start " + "x" * length + " end"
    line = cli._compose(what, "the hint to follow", "/some/session.h5")
    assert len(line) <= cli.ERROR_LINE_LIMIT
    assert line.startswith("start ")
    assert line.endswith("[/some/session.h5]; the hint to follow")
    assert "end [" in line


# ------------------------------------------------------------ writes through links


def test_an_edit_through_a_symlink_changes_the_target_and_keeps_the_link(world, tmp_path):
    target = tmp_path / "target.h5"
    shutil.copyfile(world["S"], target)
    os.chmod(target, 0o640)
    link = tmp_path / "link.h5"
    link.symlink_to(target)
    before = target.read_bytes()
    model = make_raytrace_model()
    points = board_points(16.0)[:2]
    pixels = [a for half in ("left", "right") for q in model.project(points, half).pixels
              for a in (f"--{half}", f"{q[0]:.4f},{q[1]:.4f}")]  # fmt: skip
    result = runner.invoke(cli.app, ["measure", str(link), "--image", "scene", *pixels])
    assert result.exit_code == 0, result.stderr
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_bytes() != before  # the measurement went to the target
    assert os.stat(target).st_mode & 0o777 == 0o640  # and the file kept its mode


# ------------------------------------------------------ the real process, native stderr


def _run_module(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "endomeasure", *args], capture_output=True, text=True, timeout=60
    )


@pytest.mark.parametrize(
    "args",
    [
        ["add-images", "{D}/new.h5", "{I}/big"],
        ["detect", "{D}/new.h5", "{I}/big", "--board", BOARD],
        ["measure", "{D}/huge-image.h5", "--image", "scene", "--left", "300,240", "--left",
         "310,240"],
    ],
    ids=["png-add-images", "png-detect", "crafted-session-image"],
)  # fmt: skip
def test_huge_images_are_refused_in_a_small_process(world, args):
    result, peak_mb = run_measured(*[a.format(**world) for a in args])
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "beyond the limit" in errors[0], result.stderr
    assert peak_mb < MAX_REFUSAL_RSS_MB
    assert not (world["data"] / "new.h5").exists()


@pytest.mark.parametrize(
    "args",
    [
        ["info", "{S}", "--bogus"],
        ["detect", "{S}", "{I}/flat", "--board", BOARD, "--workers", "abc"],
        ["info"],
        ["detect", "{D}/new.h5", "{I}/junk", "--board", BOARD],
    ],
    ids=["unknown-option", "workers-abc", "missing-argument", "libpng-on-garbage"],
)
def test_the_console_entry_point_prints_one_line(world, args):
    result = _run_module(*[a.format(**world) for a in args])
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, result.stderr
    assert "╭" not in result.stderr and "Usage:" not in result.stderr
    assert "libpng" not in result.stderr and "Warning" not in result.stderr


def test_library_warnings_never_reach_stderr(world, tmp_path):
    session = tmp_path / "w.h5"
    result = _run_module("add-images", str(session), f"{world['I']}/warns")
    assert result.returncode == 0, result.stderr
    # only the summary (rich wraps it at the terminal width)
    assert " ".join(result.stderr.split()) == f"{session}: added 1 calib image(s)"
    debug = _run_module("--debug", "add-images", str(tmp_path / "d.h5"), f"{world['I']}/warns")
    assert "libpng warning" in debug.stderr  # the warning exists: --debug lets it through


def test_warnings_and_native_stderr_are_captured_inside_a_command(capfd):
    with cli._error_boundary():
        import warnings

        warnings.warn("a library's warning", RuntimeWarning, stacklevel=1)
        np.log(np.zeros(1))  # numpy's own RuntimeWarning
        os.write(2, b"a native library's message\n")
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""
