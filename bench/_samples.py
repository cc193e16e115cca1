"""Helpers shared by the accuracy scripts that work on a simulated image set (not a
benchmark itself): detect the set into a session with the commands a user runs, and
compare the detections with the simulator's exact corners.

Used by ``accuracy_detect.py`` (detection and calibration figures) and
``accuracy_report.py`` (measure and predict-error figures). The set is read back through
:mod:`endomeasure.simulate.manifest` (``board_groups``, ``load_truth``), never by parsing
its files here.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endomeasure.simulate.manifest import board_groups, load_manifest, load_truth

SETS = ("calib", "test")
HALVES = ("left", "right")


def endomeasure(
    *args, check: bool = True, timeout: float | None = None, env: dict | None = None
) -> subprocess.CompletedProcess:
    """Run the ``endomeasure`` command line (exit codes 0 and 1 are results; with
    ``check``, another one ends the script with the command's stderr)."""
    out = subprocess.run(
        [sys.executable, "-m", "endomeasure", *map(str, args)], capture_output=True, text=True,
        timeout=timeout, env=env,
    )  # fmt: skip
    if check and out.returncode not in (0, 1):
        sys.exit(f"failed: endomeasure {' '.join(map(str, args))}\n{out.stderr}")
    return out


def detect_samples(
    root: str | Path, session: str | Path, sets=SETS, workers: int | None = None
) -> None:
    """``endomeasure detect`` every board group of the given sets of a simulated set
    into ``session`` (one call per board spec and set, as a user would)."""
    for set_name in sets:
        for spec, files in board_groups(root, set_name):
            extra = ["--workers", workers] if workers else []
            endomeasure("detect", session, *files, "--board", spec, "--set", set_name, *extra)


@dataclass(frozen=True)
class HalfErrors:
    """The detection of one board in one half of one image against the truth."""

    image: str
    set_name: str
    half: str
    cols: int
    """Inner-corner columns of the board (corner id = row * cols + col)."""
    visible: bool
    """The truth says the whole board is in this half."""
    ids: np.ndarray
    """(N,) detected ids (empty when the board was not found)."""
    detected: np.ndarray
    """(N, 2) px detected pixels."""
    true_pixels: np.ndarray
    """(C, 2) px true pixel of every corner id of the board (NaN where not seen)."""

    @property
    def found(self) -> bool:
        return self.ids.size > 0

    @property
    def errors(self) -> np.ndarray:
        """(N, 2) px detected minus true pixel of the same id."""
        return self.detected - self.true_pixels[self.ids]


def detection_errors(root: str | Path, session: str | Path, sets=SETS) -> list[HalfErrors]:
    """Every (image, half) of the sets: its detection and the true corner pixels."""
    from endomeasure.conventions import Half
    from endomeasure.io.session import open_session

    with open_session(session) as s:
        by_key = {(d.image, Half.parse(d.half).label): d for d in s.detections() if d.ok}
    manifest = load_manifest(root)
    out = []
    for set_name in sets:
        for item in manifest["sets"].get(set_name, {}).get("images", []):
            name = Path(item["image"]).stem
            truth = load_truth(root, name)
            cols = int(truth["board_spec"].split(":")[1].split("x")[0])  # inner corners
            for half in HALVES:
                det = by_key.get((name, half))
                corners = truth["corners"]["pixels"][half]  # null: a corner not seen
                true_px = np.array([(np.nan, np.nan) if p is None else p for p in corners],
                                   dtype=float).reshape(-1, 2)  # fmt: skip
                ids = np.asarray(det.ids, dtype=np.int64) if det is not None else np.zeros(0, int)
                px = np.asarray(det.pixels, dtype=float) if det is not None else np.zeros((0, 2))
                out.append(
                    HalfErrors(
                        name, set_name, half, cols,
                        bool(truth["board_fully_visible"][half]), ids, px, true_px,
                    )
                )  # fmt: skip
    return out


def truth_board_sets(images: list[tuple[str, dict, np.ndarray, np.ndarray]]) -> list:
    """The board sets of :func:`endomeasure.measure.board_runs.board_sets` from given
    pixels: ``(image, truth, left, right)`` per image, every true corner id in both halves,
    the boards in the order they first appear."""
    from endomeasure.conventions import Half
    from endomeasure.io.session import Detection
    from endomeasure.measure.board_runs import board_sets

    boards, detections = {}, []
    for image, truth, left, right in images:
        boards.setdefault(truth["board_spec"], truth["target"])
        ids = np.asarray(truth["corners"]["ids"], dtype=np.int64)
        for half, pixels in ((Half.LEFT, left), (Half.RIGHT, right)):
            detections.append(Detection(image, truth["board_spec"], half, ids, pixels))
    return board_sets(boards, detections, [image for image, *_ in images])


def truth_board_test(session: Path, data: Path, zone_mm: float, models=None) -> dict:
    """The board test on the true corner pixels of the test set: the models' own error,
    no image noise (``models``: the stored model names to test, default all)."""
    from endomeasure.io.records import load_calibrated_model
    from endomeasure.io.session import open_session
    from endomeasure.measure.board_runs import run_board_test

    with open_session(session) as s:
        names = s.model_names() if models is None else models
        # as `measure --board-test`: a failed calibration's errors are what it shows
        models = {n: load_calibrated_model(s, n, session, allow_failed=True).model for n in names}
        test = s.image_names("test")
    images = []
    for image in test:
        t = load_truth(data, image)
        px = t["corners"]["pixels"]
        images.append((image, t, np.asarray(px["left"], float), np.asarray(px["right"], float)))
    sets = truth_board_sets(images)
    return {n: run_board_test(n, m, sets, zone_mm) for n, m in models.items()}
