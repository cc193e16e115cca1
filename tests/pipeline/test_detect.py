"""``endomeasure detect``: many files, per-image failures, the session, exit codes."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.synthetic import homography_from_pose, render_split_image
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.io.session import open_session
from endomeasure.pipeline.detect import detect_images

runner = CliRunner()

SIZE, SPLIT = (480, 320), 240
# Detected corners against the analytic truth (sigma 2 noise): SPEC's noisy target.
RMS_PX = 0.1
CHESS = "chessboard:7x5:1"


def _render(board: str, roll: float, rng) -> tuple[np.ndarray, dict]:
    spec = parse_board_spec(board)
    centre = np.array([(spec.cols - 1) / 2, (spec.rows - 1) / 2]) * spec.square_mm
    rvec = np.radians([10.0, -12.0, roll])
    homographies = {}
    for half, baseline, u0 in ((Half.LEFT, -0.6, SPLIT / 2), (Half.RIGHT, 0.6, SPLIT * 1.5)):
        tvec = np.array([-baseline, 0.0, 19.0]) - rotation_matrix(rvec) @ [*centre, 0.0]
        homographies[half] = homography_from_pose(300.0, (u0, SIZE[1] / 2), rvec, tvec)
    scene = render_split_image(
        spec, homographies, SIZE, SPLIT, noise_sigma=2.0, rng=rng, band_halfwidth_px=8
    )
    return scene.image, scene.true_pixels


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
    rng = np.random.default_rng(7)
    folder = tmp_path_factory.mktemp("images")
    truth = {}
    for index, roll in enumerate((0.0, 8.0, -10.0)):
        image, pixels = _render(CHESS, roll, rng)
        cv2.imwrite(str(folder / f"chess{index}.png"), image)
        truth[f"chess{index}"] = pixels
    image, _ = _render("chessboard:5x4:2", 3.0, rng)
    cv2.imwrite(str(folder / "other.png"), image)
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    data = (folder / "chess0.png").read_bytes()
    (folder / "truncated.png").write_bytes(data[: len(data) // 3])
    (folder / "notes.txt").write_text("not an image")
    cv2.imwrite(str(folder / "small.png"), np.zeros((50, 60), np.uint8))
    return folder, truth


def _chess_files(folder):
    return [folder / f"chess{i}.png" for i in range(3)]


def test_detects_stores_and_matches_truth(image_dir, tmp_path):
    folder, truth = image_dir
    session = tmp_path / "s.h5"
    report = detect_images(session, _chess_files(folder), CHESS)
    assert report.exit_code == 0 and report.stored
    assert report.split_source == "auto" and abs(report.split - SPLIT) <= 3
    with open_session(session) as s:
        meta = s.metadata()
        assert meta.image_size == SIZE and meta.split == report.split
        assert s.board("chessboard:7x5:1").attrs["square_mm"] == 1.0
        detections = s.detections(board="chessboard:7x5:1")
        assert len(detections) == 6 and all(d.ok for d in detections)
        squared = []
        for d in detections:
            assert d.attrs["quality_kind"] == "edge_width_px" and d.quality > 0
            squared.append(((d.pixels - truth[d.image][d.half][d.ids]) ** 2).sum(axis=1))
        assert np.sqrt(np.mean(np.concatenate(squared))) < RMS_PX
        assert sorted(s.image_names("calib")) == ["chess0", "chess1", "chess2"]


def test_bad_files_are_reported_per_image_and_the_rest_stored(image_dir, tmp_path):
    folder, _ = image_dir
    session = tmp_path / "s.h5"
    paths = [
        *_chess_files(folder),
        folder / "broken.png",
        folder / "truncated.png",
        folder / "notes.txt",
        folder / "small.png",
        folder / "missing.png",
        folder / "other.png",
    ]
    report = detect_images(session, paths, CHESS, split=SPLIT)
    assert report.exit_code == 1
    by_path = {r.path.rsplit("/", 1)[-1]: r for r in report.images}
    assert by_path["broken.png"].error == "cannot decode the image file"
    assert by_path["truncated.png"].status == "failed"
    assert by_path["notes.txt"].error == "not an image file"
    assert "session's images are 480x320" in by_path["small.png"].error
    assert by_path["missing.png"].error == "no such file or directory"
    assert by_path["other.png"].status == "failed"
    assert "does not match the spec" in by_path["other.png"].halves["left"].failure
    with open_session(session) as s:
        assert s.image_names() == ["chess0", "chess1", "chess2", "other"]
        ok = [d for d in s.detections() if d.ok]
        assert len(ok) == 6


def test_several_boards_add_to_one_session(image_dir, tmp_path):
    folder, _ = image_dir
    session = tmp_path / "s.h5"
    first = detect_images(session, _chess_files(folder)[:2], CHESS)
    second = detect_images(session, [folder / "other.png"], "chessboard:5x4:2", image_set="test")
    assert first.exit_code == 0 and second.exit_code == 0
    assert second.split_source == "session" and second.split == first.split
    with open_session(session) as s:
        assert set(s.boards()) == {"chessboard:7x5:1", "chessboard:5x4:2"}
        assert len(s.detections(board="chessboard:7x5:1")) == 4
        assert len(s.detections(board="chessboard:5x4:2")) == 2
        assert s.image_names("test") == ["other"]


def test_nothing_usable_stores_nothing_and_exits_2(image_dir, tmp_path):
    folder, _ = image_dir
    session = tmp_path / "s.h5"
    report = detect_images(session, [folder / "broken.png", folder / "notes.txt"], CHESS)
    assert report.exit_code == 2 and not report.stored
    assert not session.exists()
    # a board spec that matches nothing in the images is nothing usable too
    wrong = detect_images(session, _chess_files(folder)[:1], "chessboard:9x9:1", split=SPLIT)
    assert wrong.exit_code == 2 and not session.exists()


def test_a_split_contradicting_stored_detections_is_refused(image_dir, tmp_path):
    folder, _ = image_dir
    session = tmp_path / "s.h5"
    detect_images(session, _chess_files(folder)[:1], CHESS, split=SPLIT)
    with pytest.raises(BadInputError, match="differs from the session's split"):
        detect_images(session, _chess_files(folder)[1:2], CHESS, split=SPLIT + 10)


def test_two_workers_give_the_same_detections(image_dir, tmp_path):
    folder, _ = image_dir
    one = detect_images(tmp_path / "a.h5", _chess_files(folder), CHESS, split=SPLIT, workers=1)
    two = detect_images(tmp_path / "b.h5", _chess_files(folder), CHESS, split=SPLIT, workers=2)
    assert one.to_dict()["images"] == two.to_dict()["images"]
    with open_session(tmp_path / "a.h5") as a, open_session(tmp_path / "b.h5") as b:
        for da, db in zip(a.detections(), b.detections(), strict=True):
            np.testing.assert_array_equal(da.pixels, db.pixels)


def test_cli_json_is_one_document_and_exit_code(image_dir, tmp_path):
    folder, _ = image_dir
    session = tmp_path / "s.h5"
    args = ["detect", str(session), str(folder / "chess0.png"), str(folder / "broken.png")]
    result = runner.invoke(cli.app, [*args, "--board", CHESS, "--json"])
    assert result.exit_code == 1
    document = json.loads(result.stdout)
    assert document["counts"] == {"ok": 1, "one-half": 0, "failed": 1}
    table = runner.invoke(cli.app, ["detect", str(session), str(folder), "--board", CHESS])
    # the folder holds the other board and broken files: exit 1, a table, nothing on stdout
    assert table.exit_code == 1
    assert table.stdout == ""


@pytest.mark.parametrize(
    ("args", "complaint"),
    [
        (["--board", "chessboard:7by5:1"], "bad board spec"),
        (["--board", CHESS, "--split", "middle"], "--split must be 'auto'"),
        (["--board", CHESS, "--set", "train"], "unknown image set"),
        (["--board", CHESS, "--workers", "0"], "--workers must be at least 1"),
    ],
)
def test_cli_bad_usage_is_one_line_and_exit_2(image_dir, tmp_path, args, complaint):
    folder, _ = image_dir
    result = runner.invoke(cli.app, ["detect", str(tmp_path / "s.h5"), str(folder), *args])
    assert result.exit_code == 2
    assert complaint in result.stderr
    assert "Traceback" not in result.stderr
