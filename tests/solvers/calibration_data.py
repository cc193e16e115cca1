"""Synthetic calibration detections with exact ground truth (a test helper, not a test).

Board corners are projected through a known ("truth") camera model at many poses, the
way the paper's protocol takes them (SPEC 2): 10-45 mm from the probe, tilted up to
30 degrees about the horizontal and vertical axes, near the axis so both halves see the
board; optional seeded Gaussian pixel noise. The corner ids follow the board-frame
rule (id = row * cols + col) in both halves.

Used by ``tests/solvers/test_calibrate.py``, ``tests/pipeline/test_calibrate.py`` and
``bench/bench_calibrate.py`` (loaded by path: the tests run in importlib mode).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from endomeasure.conventions import Half, in_half
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.solvers.calibrate import ViewDetections

BOARD_COLS, BOARD_ROWS = 11, 8
SQUARES_MM = (0.5, 1.0, 2.0)  # the paper's three boards


def random_tilt(rng: np.random.Generator, max_tilt_deg: float) -> np.ndarray:
    """A board rotation: tilts uniform in ``+-max_tilt_deg`` about x then y, an in-plane
    roll within +-10 degrees (3, 3)."""
    ax, ay = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    az = np.radians(rng.uniform(-10.0, 10.0))
    return (
        rotation_matrix(np.array([0.0, 0.0, az]))
        @ rotation_matrix(np.array([0.0, ay, 0.0]))
        @ rotation_matrix(np.array([ax, 0.0, 0.0]))
    )


def board_corners(cols: int, rows: int, square_mm: float) -> np.ndarray:
    """Board-frame corners in id order, shape (rows * cols, 3), mm."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    return np.stack([c * square_mm, r * square_mm, np.zeros(r.size)], axis=-1)


def perturbed_raytrace_truth():
    """The tests' nominal raytrace design, moved off its symmetric values (the truth)."""
    from tests.conftest import make_raytrace_model

    return make_raytrace_model(
        cx=323.0, cy=236.5, k1=-0.10, k2=0.015,
        rear_a=0.010, rear_b=-0.005, rear_d=0.70,
        left_a=math.radians(-17.5), left_b=0.004, left_d=2.05,
        right_a=math.radians(18.3), right_b=-0.003, right_d=2.00,
    )  # fmt: skip


class SyntheticSet(NamedTuple):
    views: list[ViewDetections]
    boards: dict[str, np.ndarray]
    poses: list[tuple[np.ndarray, np.ndarray]]  # true T_model_board (R, t) per view
    true_pixels: list[tuple[np.ndarray, np.ndarray]]  # noise-free pixels per view and half


def synthetic_views(
    model,
    rng: np.random.Generator,
    n_images: int = 12,
    noise_px: float = 0.0,
    near_mm: float = 10.0,
    far_mm: float = 45.0,
    max_tilt_deg: float = 30.0,
    min_corners: int = 8,
) -> SyntheticSet:
    """Detections of boards at random poses projected through ``model``.

    Distances are stratified over ``[near_mm, far_mm]`` (one image per stratum), the
    square size grows with distance (0.5, 1, 2 mm), tilts are uniform in
    ``+-max_tilt_deg`` about x and y, in-plane rotation within +-10 degrees. Corners
    that the model cannot project into a half, or that noise pushes over its edge,
    are missing (as a detector would miss them). A pose is redrawn until both halves
    see at least ``min_corners`` corners.
    """
    width, height = model.config.image_size
    boards = {f"sq{s:g}": board_corners(BOARD_COLS, BOARD_ROWS, s) for s in SQUARES_MM}
    views, poses, truths = [], [], []
    while len(views) < n_images:
        z = near_mm + (far_mm - near_mm) * (len(views) + rng.uniform()) / n_images
        square = 0.5 if z < 18.0 else (1.0 if z < 30.0 else 2.0)
        name = f"sq{square:g}"
        X = boards[name]
        R = random_tilt(rng, max_tilt_deg)
        centre = np.array([rng.uniform(-0.08, 0.08) * z, rng.uniform(-0.12, 0.12) * z, z])
        t = centre - R @ X.mean(axis=0)
        P = X @ R.T + t
        ids, pixels, exact = [], [], []
        for half in Half:
            proj = model.project(P, half)
            ok = np.flatnonzero(proj.status == 0)
            q = proj.pixels[ok] + noise_px * rng.standard_normal((ok.size, 2))
            keep = in_half(q, half, model.config.split, (width, height))
            ids.append(ok[keep])
            pixels.append(q[keep])
            exact.append(proj.pixels[ok][keep])
        if min(i.size for i in ids) < min_corners:
            continue
        views.append(ViewDetections(f"img{len(views):03d}", name, tuple(ids), tuple(pixels)))
        poses.append((R, t))
        truths.append(tuple(exact))
    return SyntheticSet(views, boards, poses, truths)


def with_fresh_noise(
    data: SyntheticSet,
    rng: np.random.Generator,
    noise_px: float,
    split: int,
    image_size: tuple[int, int],
) -> list[ViewDetections]:
    """The same views with new Gaussian pixel noise on the exact pixels (corners that the
    noise pushes over a half's edge are dropped)."""
    views = []
    for view, exact in zip(data.views, data.true_pixels, strict=True):
        ids, pixels = [], []
        for half in Half:
            q = exact[half] + noise_px * rng.standard_normal(exact[half].shape)
            keep = in_half(q, half, split, image_size)
            ids.append(view.ids[half][keep])
            pixels.append(q[keep])
        views.append(ViewDetections(view.name, view.board, tuple(ids), tuple(pixels)))
    return views


def board_spec(board_key: str) -> str:
    """The board spec of a synthetic board name (``sq<square mm>``)."""
    return f"chessboard:{BOARD_COLS}x{BOARD_ROWS}:{board_key.removeprefix('sq')}"


def write_session(path, data: SyntheticSet, sigma_px: float | None = None):
    """A 640x480 session (split 320) holding a synthetic set's boards and detections; with
    ``sigma_px`` every corner carries that isotropic noise as its detector covariance."""
    from endomeasure.io.session import Detection, edit_session

    def covariance(n):
        return None if sigma_px is None else np.tile(np.eye(2) * sigma_px**2, (n, 1, 1))

    with edit_session(path, create=True) as w:
        w.set_metadata(image_size=(640, 480), split=320)
        for key in sorted({v.board for v in data.views}):
            w.write_board(board_spec(key), board_spec(key))
        w.write_detections(
            Detection(v.name, board_spec(v.board), h, v.ids[h].astype(np.int32), v.pixels[h],
                      1.0, "", covariance=covariance(len(v.ids[h])))
            for v in data.views
            for h in Half
        )  # fmt: skip
    return path
