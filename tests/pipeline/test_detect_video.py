"""``endomeasure detect`` on video files: the frames ``add-images`` would take, detected
and stored with their source and frame number."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from tests.io.video_data import BOARD, IMAGE_SIZE, SPLIT, write_clip

from endomeasure.errors import BadInputError
from endomeasure.io.session import open_session
from endomeasure.io.video import read_frames
from endomeasure.pipeline.detect import detect_images
from endomeasure.pipeline.images import add_images, video_records

SPLIT_TOLERANCE_PX = 3
"""The automatic split against the clip's true band centre (the band is 8 px wide)."""


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_clip(tmp_path_factory.mktemp("video") / "clip.avi", np.random.default_rng(11))


def test_detect_stores_the_frames_the_pick_of_add_images_keeps(clip, tmp_path):
    session = tmp_path / "s.h5"
    stages = set()
    report = detect_images(session, [clip.path], BOARD, split=SPLIT,
                           on_progress=lambda stage, done, total: stages.add(stage))  # fmt: skip
    records, summary = video_records(clip.path, "calib", board=BOARD, split=SPLIT)
    assert report.exit_code == 0 and report.stored
    assert [v.picked for v in report.videos] == [summary.picked]
    assert [r.frame for r in report.images] == summary.picked
    assert {clip.kinds[i] for i in summary.picked} <= {"sharp", "held"}
    assert f"reading {clip.path.name}" in stages
    with open_session(session) as s:
        infos = s.images_info("calib")
        assert [(i.name, i.frame, i.original_path) for i in infos] == [
            (r.name, r.frame, str(clip.path)) for r in records
        ]
        for record in records:
            np.testing.assert_array_equal(s.image(record.name), record.pixels)
        ok = [d for d in s.detections(board=report.board) if d.ok]
        assert len(ok) == 2 * len(records)


def test_a_frame_step_detects_every_nth_frame_and_finds_the_split(clip, tmp_path):
    session = tmp_path / "s.h5"
    report = detect_images(session, [clip.path], BOARD, frame_step=3, image_set="test")
    frames = list(range(0, len(clip.kinds), 3))
    assert [r.frame for r in report.images] == frames
    assert report.split_source == "auto" and abs(report.split - SPLIT) <= SPLIT_TOLERANCE_PX
    by_frame = {r.frame: r for r in report.images}
    # the board half outside the right view is found in the left half only
    for index in clip.frames("half-outside"):
        if index in by_frame:
            assert by_frame[index].status == "one-half"
    with open_session(session) as s:
        assert [i.frame for i in s.images_info("test")] == frames


def test_videos_and_images_go_to_one_session(clip, tmp_path):
    session = tmp_path / "s.h5"
    still = tmp_path / "still.png"
    cv2.imwrite(str(still), next(read_frames(clip.path))[1])
    report = detect_images(session, [still, clip.path], BOARD, split=SPLIT)
    assert report.exit_code == 0
    # in the order given: the image file, then the video's frames
    assert report.images[0].name == "still" and report.images[0].frame is None
    assert [r.frame for r in report.images[1:]] == report.videos[0].picked


def test_a_bad_video_refuses_the_whole_command(clip, tmp_path):
    session = tmp_path / "s.h5"
    cut = tmp_path / "cut.avi"
    cut.write_bytes(clip.path.read_bytes()[: clip.path.stat().st_size // 2])
    with pytest.raises(BadInputError, match="truncated"):
        detect_images(session, [clip.path, cut], BOARD, split=SPLIT)
    with pytest.raises(BadInputError, match="no such video file"):
        detect_images(session, [tmp_path / "missing.avi"], BOARD)
    with pytest.raises(BadInputError, match="--frame-step must be at least 1"):
        detect_images(session, [clip.path], BOARD, frame_step=0)
    assert not session.exists()


def test_frames_of_another_size_than_the_session_are_refused(clip, tmp_path):
    session = tmp_path / "s.h5"
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((IMAGE_SIZE[1] // 2, IMAGE_SIZE[0] // 2), np.uint8))
    add_images(session, [small], "calib")
    before = session.read_bytes()
    with pytest.raises(BadInputError, match="session's images are 240x160 px"):
        detect_images(session, [clip.path], BOARD)
    assert session.read_bytes() == before
