"""Ground truth of simulated images, as plain JSON-ready data.

Every image ``NAME.png`` has a truth file ``NAME.json`` next to it (format
``endomeasure-simulated-truth``, version 1; fields documented in ``docs/simulator.md``):
the target and its pose ``T_camera_<target>``, and for boards every inner corner's id,
true 3D position in the camera frame and true pixel in each half, computed by exact ray
aiming through the ground-truth optics of :mod:`.truth_optics` (``null`` where the corner
does not project into that half), plus the true values of the board-test measurements
(SPEC section 7). For the metal scene: the marks' 3D positions, pixels, and the
distances between them; with pits, each pit's deepest point and its pixels.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.geometry.rotations import rotation_vector
from endomeasure.simulate.preset import Preset
from endomeasure.simulate.scenes import Shot, visibility
from endomeasure.simulate.targets import CharucoBoard, Chessboard, MetalCylinder

__all__ = [
    "TRUTH_FORMAT",
    "TRUTH_VERSION",
    "CORNER_ID_RULE",
    "CHARUCO_CORNER_ID_RULE",
    "image_truth",
    "true_pixels",
    "true_depth",
    "DEPTH_SUFFIX",
]

DEPTH_SUFFIX = ".depth.npy"
"""File name ending of a scene image's true depth map (``scene_000.depth.npy``)."""

TRUTH_FORMAT = "endomeasure-simulated-truth"
TRUTH_VERSION = 1
CORNER_ID_RULE = (
    "id = row * cols + col; corner (col, row) at (col * square_mm, row * square_mm, 0) in the "
    "board frame; id 0 is the inner corner nearest the image's top-left, cols increase along "
    "+u (board +x), rows along +v (board +y), the same in both halves"
)

CHARUCO_CORNER_ID_RULE = (
    "OpenCV's ChArUco corner ids: id = row * (squares_x - 1) + col for inner corner (col, row), "
    "at (col * square_mm, row * square_mm, 0) in the board frame (OpenCV's ChArUco object "
    "points minus one square in x and y); the board's own ids, whatever part of the board a "
    "half shows and however it is turned"
)


def true_pixels(preset: Preset, points: np.ndarray) -> dict[str, list]:
    """True pixel of each point in each half by ray aiming, ``None`` where not OK.

    Parameters
    ----------
    points : ndarray, shape (N, 3), mm, camera frame

    Returns
    -------
    dict ``{'left': [[u, v] or None, ...], 'right': [...]}``
    """
    out = {}
    for half in Half:
        proj = preset.truth_optics.project(points, half)
        out[half.label] = [
            [float(q[0]), float(q[1])] if s == Status.OK else None
            for q, s in zip(proj.pixels, proj.status, strict=True)
        ]
    return out


def true_depth(preset: Preset, target, region=None) -> np.ndarray:
    """True depth of every pixel: z of the first scene surface its centre ray meets.

    Parameters
    ----------
    preset : Preset
        Its ground-truth optics trace the rays (never a fitted model).
    target : Chessboard, CharucoBoard or MetalCylinder
        The posed scene object (anything with the renderer's ``hit(o, d)``).
    region : Region, optional
        Full-image pixel rectangle; the default is the whole image.

    Returns
    -------
    ndarray, shape (H, W), float32, mm
        z in the camera frame (``docs/conventions.md``: the real camera's, which the
        ``raytrace`` model shares) of the point where the ray of the pixel centre meets
        the target, in both halves; NaN where the ray misses the target (the background)
        or fails in the optics.

    Notes
    -----
    One ray per pixel through its centre (:func:`~endomeasure.simulate.optics.ray_bundle`
    with one sample), traced in float64 here: the rendered pixel integrates its
    sub-pixel samples, so at a depth edge the truth is the centre's surface.
    """
    from endomeasure.simulate.optics import Region

    optics = preset.truth_optics
    region = region or Region.full(preset.image_size)
    region.check(optics.config.image_size)
    uu, vv = np.meshgrid(
        np.arange(region.u0, region.u1, dtype=np.float64),
        np.arange(region.v0, region.v1, dtype=np.float64),
    )
    depth = np.full(uu.shape, np.nan)
    for half in Half:
        mask = (uu < optics.config.split) if half is Half.LEFT else (uu >= optics.config.split)
        if not mask.any():
            continue
        rays = optics.rays(np.stack([uu[mask], vv[mask]], axis=-1), half)
        ok = rays.status == Status.OK
        o = tuple(np.where(ok, rays.origins[:, k], 0.0) for k in range(3))
        d = tuple(np.where(ok, rays.directions[:, k], 0.0) for k in range(3))
        with np.errstate(invalid="ignore", divide="ignore"):
            hit = target.hit(o, d)
            z = o[2] + hit.t * d[2]
        depth[mask] = np.where(ok & hit.hit, z, np.nan)
    return depth.astype(np.float32)


def _pose(R: np.ndarray, t: np.ndarray) -> dict[str, Any]:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return {
        "matrix": T.tolist(),
        "rvec": rotation_vector(R).tolist(),
        "tvec_mm": [float(v) for v in t],
    }


def _board_truth(preset: Preset, board: Chessboard | CharucoBoard) -> dict[str, Any]:
    s = board.square_mm
    corners = board.corners_camera
    normal = board.R[:, 2]
    tilt = float(np.degrees(np.arccos(min(1.0, abs(normal[2])))))
    rule = CHARUCO_CORNER_ID_RULE if isinstance(board, CharucoBoard) else CORNER_ID_RULE
    return {
        "target": {**board.to_dict(), "corner_ids": rule},
        "T_camera_board": _pose(board.R, board.t),
        "distance_mm": float((board.R @ board.centre_board + board.t)[2]),
        "tilt_deg": tilt,
        "board_fully_visible": visibility(preset, board),
        "corners": {
            "ids": list(range(board.rows * board.cols)),
            "points_mm": corners.tolist(),
            "pixels": true_pixels(preset, corners),
        },
        "measurements": {
            "x_segment_mm": s,
            "y_segment_mm": s,
            "point_to_plane_mm": 0.0,
            "square_area_mm2": s * s,
        },
    }


def _scene_truth(preset: Preset, surface: MetalCylinder) -> dict[str, Any]:
    marks = surface.marks_camera
    diff = marks[:, None, :] - marks[None, :, :]
    dist = np.linalg.norm(diff, axis=-1)
    pairs = [
        {"a": i, "b": j, "distance_mm": float(dist[i, j])}
        for i in range(len(marks))
        for j in range(i + 1, len(marks))
    ]
    return {
        "target": surface.to_dict(),
        "T_camera_surface": _pose(surface.R, surface.t),
        "distance_mm": float(surface.t[2]),
        "marks": {
            "ids": list(range(len(marks))),
            "surface_sy_mm": surface.marks_sy.tolist(),
            "points_mm": marks.tolist(),
            "pixels": true_pixels(preset, marks),
            "radius_mm": surface.mark_radius_mm,
        },
        "distances": pairs,
        **({"pits": _pit_truth(preset, surface)} if len(surface.pits) else {}),
    }


def _pit_truth(preset: Preset, surface: MetalCylinder) -> dict[str, Any]:
    bottoms = surface.pit_bottoms_camera
    return {
        "ids": list(range(len(bottoms))),
        "surface_sy_mm": surface.pits[:, :2].tolist(),
        "radius_mm": surface.pits[:, 2].tolist(),
        "depth_mm": surface.pits[:, 3].tolist(),
        "bottom_points_mm": bottoms.tolist(),
        "bottom_pixels": true_pixels(preset, bottoms),
    }


def image_truth(
    preset: Preset, shot: Shot, image_file: str, render_info: dict[str, Any]
) -> dict[str, Any]:
    """The truth document of one rendered image."""
    doc: dict[str, Any] = {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "image": image_file,
        "set": shot.set_name,
        "index": shot.index,
        "tags": list(shot.tags),
        "units": {"length": "mm", "pixel": "px", "angle": "rad unless _deg"},
        "image_size": list(preset.image_size),
        "split": preset.split,
    }
    if isinstance(shot.target, (Chessboard, CharucoBoard)):
        doc["board_spec"] = shot.target.spec
        doc.update(_board_truth(preset, shot.target))
    else:
        doc.update(_scene_truth(preset, shot.target))
    doc["render"] = render_info
    return doc
