"""Video input: reading frames, refusing damaged files, and the frames kept from a clip."""

from __future__ import annotations

import numpy as np
import pytest
from tests.io.video_data import BOARD, IMAGE_SIZE, SPLIT, write_clip

from endomeasure.errors import BadInputError
from endomeasure.features.frames import pick_from_clip
from endomeasure.io.images import sha256_of_file
from endomeasure.io.video import read_frames, video_info
from endomeasure.pipeline.images import video_records


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_clip(tmp_path_factory.mktemp("video") / "clip.avi", np.random.default_rng(5))


def test_frames_are_read_in_order_with_their_size(clip):
    info = video_info(clip.path)
    assert (info.width, info.height, info.frame_count) == (*IMAGE_SIZE, len(clip.kinds))
    frames = list(read_frames(clip.path))
    assert [i for i, _ in frames] == list(range(len(clip.kinds)))
    assert frames[0][1].shape == (IMAGE_SIZE[1], IMAGE_SIZE[0], 3)
    kept = [i for i, _ in read_frames(clip.path, keep=lambda i: i % 4 == 0)]
    assert kept == list(range(0, len(clip.kinds), 4))


@pytest.mark.parametrize("fraction", [0.3, 0.6])
def test_a_truncated_video_is_bad_input(clip, tmp_path, fraction):
    data = clip.path.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(BadInputError, match="truncated"):
        list(read_frames(cut))


def test_a_file_that_is_no_video_is_bad_input(tmp_path):
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video " * 100)
    with pytest.raises(BadInputError, match="cannot open the video"):
        list(read_frames(junk))


def test_the_pick_keeps_each_sharp_pose_once_and_no_blurred_or_half_outside_frame(clip):
    records, summary = video_records(clip.path, "calib", board=BOARD, split=SPLIT)
    # one frame of every pose held still (the first whose halves pass the fast check)
    assert sorted(clip.poses[i] for i in summary.picked) == list(range(4))
    assert {clip.kinds[i] for i in summary.picked} <= {"sharp", "held"}
    assert not set(summary.picked) & set(clip.frames("blurred") + clip.frames("half-outside"))
    assert [r.frame for r in records] == summary.picked
    assert records[0].name == f"clip_f{summary.picked[0]:06d}"
    assert {r.original_path for r in records} == {str(clip.path)}
    assert {r.sha256 for r in records} == {sha256_of_file(clip.path)}
    assert summary.left_out["board not fully seen"] >= len(clip.frames("half-outside"))
    assert summary.left_out["blurred"] >= 2


def test_the_pick_needs_only_a_frame_reader(clip):
    # features.frames reads no file: the same frames from memory give the same pick
    frames = list(read_frames(clip.path))

    def read(keep):
        return [(i, px) for i, px in frames if keep is None or keep(i)]

    done = []
    pick = pick_from_clip(read, len(frames), lambda d, t: done.append(d), board=BOARD,
                          split=SPLIT)  # fmt: skip
    _, summary = video_records(clip.path, "calib", board=BOARD, split=SPLIT)
    assert pick.picked == summary.picked and pick.frames == len(frames)
    assert pick.left_out == summary.left_out
    assert done == list(range(1, len(frames) + 1))


def test_the_split_is_found_from_the_clip(clip):
    _, summary = video_records(clip.path, "calib", board=BOARD)
    assert abs(summary.split - SPLIT) <= 2
    assert sorted(clip.poses[i] for i in summary.picked) == list(range(4))


def test_a_frame_step_takes_every_nth_frame(clip):
    records, summary = video_records(clip.path, "test", frame_step=3)
    assert summary.picked == list(range(0, len(clip.kinds), 3))
    assert all(r.image_set == "test" and r.pixels.shape[:2] == IMAGE_SIZE[::-1] for r in records)


def test_refusals(clip, tmp_path):
    with pytest.raises(BadInputError, match="needs the board"):
        video_records(clip.path, "calib", split=SPLIT)
    with pytest.raises(BadInputError, match="session's images are 640x480"):
        video_records(clip.path, "calib", board=BOARD, split=SPLIT, image_size=(640, 480))
    with pytest.raises(BadInputError, match="no frame of the video shows the whole board"):
        video_records(clip.path, "calib", board="chessboard:8x3:1.0", split=SPLIT)
