"""The image sets: where the targets are for each simulated image (SPEC sections 2, 9).

- ``calib``: three flat chessboards (0.5, 1 and 2 mm squares) at 10-45 mm, tilted up
  to about 30 degrees about the horizontal and vertical axes, seen in both halves; a
  few images deliberately leave part of the board outside one half, as happens in
  practice (and exercises the detector's per-half failure path).
- ``test``: the 1 mm board perpendicular to the axis from 12 to 27 mm and the 2 mm
  board from 22 to 40 mm in 1 mm steps (the paper's protocol), with the small residual
  tilt and offset of a real stage.
- ``scene``: a textured metal cylinder with small marks at known positions.
- ``charuco``: a ChArUco board larger than the view at 10-20 mm, tilted and rolled, so
  each half sees only part of it (the detector must name corners by the board's ids).
  Not part of the default run (``make samples``); asked for with ``--set charuco``.

Poses are drawn from a generator seeded by the run seed and the set name, so a set is
reproducible on its own. Rotations compose as ``R = Rz(roll) Ry(tilt_y) Rx(tilt_x)``
(roll stays small so that the detector's canonical corner order equals the truth ids).
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.simulate.optics import apex_columns
from endomeasure.simulate.preset import Preset
from endomeasure.simulate.targets import (
    CharucoBoard,
    Chessboard,
    MetalCylinder,
    target_from_preset,
)

__all__ = ["Shot", "SET_NAMES", "plan_set", "visibility", "set_rng"]

SET_NAMES = ("calib", "test", "scene", "charuco")

BORDER_CLEARANCE_PX = 2.0
"""A board counts as fully visible when its checker outline stays this far inside the
image border, ..."""
APEX_CLEARANCE_SIGMAS = 2.5
"""... and this many apex-band sigmas away from the apex image (where the band has
darkened the image by less than 4 %, so the outer squares are intact)."""
_MAX_TRIES = 400


@dataclasses.dataclass(frozen=True, eq=False)
class Shot:
    """One image to render: a posed target and where it came from."""

    set_name: str
    index: int
    target: Chessboard | CharucoBoard | MetalCylinder
    tags: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return f"{self.set_name}_{self.index:03d}"


def set_rng(seed: int, set_name: str, purpose: str = "poses") -> np.random.Generator:
    """The generator of one set and purpose: independent of the other sets."""
    return np.random.default_rng(
        [int(seed), zlib.crc32(set_name.encode()), zlib.crc32(purpose.encode())]
    )


def _rotation(tilt_x: float, tilt_y: float, roll: float) -> np.ndarray:
    return (
        rotation_matrix(np.array([0.0, 0.0, roll]))
        @ rotation_matrix(np.array([0.0, tilt_y, 0.0]))
        @ rotation_matrix(np.array([tilt_x, 0.0, 0.0]))
    )


def _aim_point(spec: dict, z: float) -> np.ndarray:
    """Where a set's poses centre at depth z: on the direction ``centre_deg`` (x, y tilts
    of the common field's centre, default the optical axis)."""
    ax, ay = np.radians(spec.get("centre_deg", (0.0, 0.0)))
    return np.array([z * np.tan(ax), z * np.tan(ay), 0.0])


def _place_board(board, R: np.ndarray, centre: np.ndarray):
    return board.with_pose(R, centre - R @ board.centre_board)


class _Clearance:
    """Checks whether projected points keep clear of the image border and the apex band."""

    def __init__(self, preset: Preset):
        self.preset = preset
        self.model = preset.truth_optics
        height = preset.image_size[1]
        self.rows = np.linspace(0.0, height - 1.0, 9)
        self.apex = apex_columns(self.model, self.rows)
        self.apex_margin = APEX_CLEARANCE_SIGMAS * preset.apex_band_sigma_px

    def inside(self, points: np.ndarray, half: Half) -> tuple[np.ndarray, np.ndarray]:
        """(projected OK, OK and clear of border and band) per point."""
        proj = self.model.project(points, half)
        ok = proj.status == Status.OK
        q = proj.pixels
        width, height = self.preset.image_size
        m = BORDER_CLEARANCE_PX
        clear = ok.copy()
        with np.errstate(invalid="ignore"):
            clear &= (q[:, 0] >= -0.5 + m) & (q[:, 0] <= width - 0.5 - m)
            clear &= (q[:, 1] >= -0.5 + m) & (q[:, 1] <= height - 0.5 - m)
            u_apex = np.interp(q[:, 1], self.rows, self.apex)
            if half is Half.LEFT:
                clear &= q[:, 0] <= u_apex - self.apex_margin
            else:
                clear &= q[:, 0] >= u_apex + self.apex_margin
        return ok, clear


def visibility(
    preset: Preset, board: Chessboard | CharucoBoard, clearance: _Clearance | None = None
) -> dict[str, bool]:
    """Whether the whole checker area of a posed board is visible in each half.

    The outline of the checker area (the outer edges of the outer squares) must project
    into the half, clear of the image border and of the apex band.
    """
    clearance = clearance or _Clearance(preset)
    outline = board.outline_board() @ board.R.T + board.t
    return {h.label: bool(clearance.inside(outline, h)[1].all()) for h in Half}


def _any_visible(clearance: _Clearance, board: Chessboard) -> bool:
    pts = board.corners_camera
    return any(clearance.inside(pts, h)[1].any() for h in Half)


def _calib(preset: Preset, seed: int) -> list[Shot]:
    spec = preset.sets["calib"]
    rng = set_rng(seed, "calib")
    clearance = _Clearance(preset)
    max_tilt = np.radians(float(spec["max_tilt_deg"]))
    max_roll = np.radians(float(spec["max_roll_deg"]))
    groups = spec["boards"]
    default_reach = np.tan(np.radians(float(spec.get("max_offset_deg", 25.0))))
    total = sum(int(g["images"]) for g in groups)
    n_partial = int(spec.get("partial_images", 0))
    partial_at = set(
        np.linspace(0, total - 1, n_partial + 2)[1:-1].round().astype(int).tolist()
        if n_partial
        else []
    )
    shots: list[Shot] = []
    index = 0
    for group in groups:
        base = target_from_preset(group["target"], preset.targets[group["target"]])
        n = int(group["images"])
        lo, hi = (float(v) for v in group["distance_mm"])
        # stratified distances and tilt signs, so every set spans the range
        z_all = lo + (np.arange(n) + rng.uniform(0.15, 0.85, n)) / n * (hi - lo)
        rng.shuffle(z_all)
        for k in range(n):
            partial = index in partial_at
            board = None
            for attempt in range(_MAX_TRIES):
                shrink = 1.0 - 0.6 * attempt / _MAX_TRIES  # smaller tilts if nothing fits
                tx = rng.uniform(-1, 1) * max_tilt * shrink
                ty = rng.uniform(-1, 1) * max_tilt * shrink
                roll = rng.uniform(-1, 1) * max_roll
                R = _rotation(tx, ty, roll)
                z = z_all[k]
                reach = np.tan(np.radians(float(group["max_offset_deg"]))) if (
                    "max_offset_deg" in group) else default_reach  # fmt: skip
                reach *= z * (1.0 if partial else 0.5)
                centre = np.array([rng.uniform(-reach, reach), rng.uniform(-reach, reach) * 0.8, z])
                centre += _aim_point(group, z)
                candidate = _place_board(base, R, centre)
                vis = visibility(preset, candidate, clearance)
                if partial:
                    if (
                        not all(vis.values())
                        and any(vis.values())
                        and _any_visible(clearance, candidate)
                    ):
                        board = candidate
                        break
                elif all(vis.values()):
                    board = candidate
                    break
            if board is None:
                raise ValueError(
                    f"calib image {index}: no pose of {group['target']} at {z_all[k]:.1f} mm "
                    "shows the board in both halves; the preset's optics and boards do not fit"
                )
            shots.append(Shot("calib", index, board, ("partial",) if partial else ()))
            index += 1
    return shots


def _test(preset: Preset, seed: int) -> list[Shot]:
    spec = preset.sets["test"]
    rng = set_rng(seed, "test")
    max_tilt = np.radians(float(spec.get("max_tilt_deg", 0.0)))
    max_offset = float(spec.get("max_offset_mm", 0.0))
    shots: list[Shot] = []
    index = 0
    for group in spec["boards"]:
        base = target_from_preset(group["target"], preset.targets[group["target"]])
        lo, hi = (float(v) for v in group["distance_mm"])
        step = float(group["step_mm"])
        offset = float(group.get("max_offset_mm", max_offset))
        for z in np.arange(lo, hi + step / 2, step):
            tx, ty, roll = rng.uniform(-1, 1, 3) * max_tilt
            R = _rotation(tx, ty, roll)
            centre = np.array([*(rng.uniform(-1, 1, 2) * offset), z]) + _aim_point(group, z)
            shots.append(Shot("test", index, _place_board(base, R, centre)))
            index += 1
    return shots


def _scene(preset: Preset, seed: int) -> list[Shot]:
    spec = preset.sets["scene"]
    rng = set_rng(seed, "scene")
    clearance = _Clearance(preset)
    base: MetalCylinder = target_from_preset(spec["target"], preset.targets[spec["target"]])
    n = int(spec["images"])
    lo, hi = (float(v) for v in spec["distance_mm"])
    max_tilt = np.radians(float(spec["max_tilt_deg"]))
    offset = float(spec.get("max_offset_mm", 1.0))
    z_all = lo + (np.arange(n) + rng.uniform(0.2, 0.8, n)) / n * (hi - lo)
    shots = []
    for k in range(n):
        for _ in range(_MAX_TRIES):
            tx, ty = rng.uniform(-1, 1, 2) * max_tilt
            roll = rng.uniform(-np.pi / 8, np.pi / 8)
            R = _rotation(tx, ty, roll)
            t = np.array([*(rng.uniform(-1, 1, 2) * offset), z_all[k]]) + _aim_point(spec, z_all[k])
            surface = base.with_pose(R, t)
            marks = surface.marks_camera
            if all(clearance.inside(marks, h)[1].all() for h in Half):
                break
        else:
            raise ValueError(f"scene image {k}: no pose shows every mark in both halves")
        shots.append(Shot("scene", k, surface))
    return shots


def _charuco(preset: Preset, seed: int) -> list[Shot]:
    """A ChArUco board larger than the view: cut by the field in both halves.

    Each image puts the board's centre within ``max_offset_mm`` of the optical axis at a
    stratified distance, tilted uniformly up to ``max_tilt_deg`` about x and y and rolled
    up to ``max_roll_deg`` (ChArUco ids do not depend on the roll), and keeps the pose
    when in both halves the board is not whole and at least ``min_corners_per_half``
    inner corners are clear of the border and of the apex band.
    """
    spec = preset.sets["charuco"]
    rng = set_rng(seed, "charuco")
    clearance = _Clearance(preset)
    base = target_from_preset(spec["target"], preset.targets[spec["target"]])
    if not isinstance(base, CharucoBoard):
        raise ValueError(f"the charuco set's target {spec['target']!r} is not a charuco board")
    n = int(spec["images"])
    lo, hi = (float(v) for v in spec["distance_mm"])
    max_tilt = np.radians(float(spec["max_tilt_deg"]))
    max_roll = np.radians(float(spec["max_roll_deg"]))
    max_offset = float(spec["max_offset_mm"])
    min_corners = int(spec["min_corners_per_half"])
    z_all = lo + (np.arange(n) + rng.uniform(0.15, 0.85, n)) / n * (hi - lo)
    shots = []
    for k in range(n):
        for _ in range(_MAX_TRIES):
            tx, ty = rng.uniform(-1, 1, 2) * max_tilt
            roll = rng.uniform(-1, 1) * max_roll
            centre = np.array([*(rng.uniform(-1, 1, 2) * max_offset), z_all[k]])
            board = _place_board(base, _rotation(tx, ty, roll), centre)
            whole = visibility(preset, board, clearance)
            corners = board.corners_camera
            seen = [int(clearance.inside(corners, h)[1].sum()) for h in Half]
            if not any(whole.values()) and min(seen) >= min_corners:
                break
        else:
            raise ValueError(
                f"charuco image {k}: no pose at {z_all[k]:.1f} mm cuts the board in both halves "
                f"and shows {min_corners} corners in each; the board is too small or too large"
            )
        shots.append(Shot("charuco", k, board))
    return shots


_PLANNERS = {"calib": _calib, "test": _test, "scene": _scene, "charuco": _charuco}


def plan_set(preset: Preset, set_name: str, seed: int) -> list[Shot]:
    """The shots of one image set of a preset, deterministic for a seed."""
    if set_name not in _PLANNERS:
        raise ValueError(f"unknown image set {set_name!r}; known: {', '.join(SET_NAMES)}")
    if set_name not in preset.sets:
        raise ValueError(f"the preset {preset.name!r} defines no {set_name!r} set")
    return _PLANNERS[set_name](preset, seed)
