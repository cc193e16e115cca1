"""The alternative to the dense search: OpenCV's StereoSGBM on a virtual rectification.

For each scene image of the demo session (``make demo``; ``--session``) both halves are
resampled into a rectified pinhole pair: one orientation (x along the line between the
halves' effective viewpoints), one focal length, each pixel's direction from its half's
viewpoint carried to the depth ``z0`` and projected through the calibrated ``raytrace``
model. The model is non-central and its epipolar lines are curves, so this rectification
is exact for points at ``z0`` only; ``z0`` is the frame's median true depth (the
alternative's best case). SGBM's disparity (1/16 px) gives the right rectified pixel, both
are mapped back to the halves and triangulated by the model (ML). Against the truth
optics' depth at the same left pixels, over the left rectified pixels whose surface point
both halves see: coverage, median |z error| / z, time; the same figures of
``endomeasure surface`` (``bench/accuracy_dense.py``) come from the same frames. Writes the
``dense-sgbm`` section of docs/accuracy.md unless ``--no-write``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import ACCURACY, Report, script_parser  # noqa: E402

BLOCK_PX = 9
"""SGBM's block side (its documentation's range 3-11)."""


def _frame(model, left_dir, right_dir):
    """Rotation (rows: rectified axes in the model frame) of the rectified pair: x along
    the baseline, z the left half's central viewing direction made orthogonal to it."""
    x = right_dir / np.linalg.norm(right_dir)
    z = left_dir - x * (left_dir @ x)
    z /= np.linalg.norm(z)
    return np.stack([x, np.cross(z, x), z])


def rectify(model, z0: float):
    """A virtual rectified pair exact at depth ``z0``: per half the (h, w, 2) table of
    original pixels of its rectified pixels, the focal length (px) and the baseline between
    the halves' effective viewpoints (mm)."""
    from endomeasure.conventions import Half
    from endomeasure.measure.diagnostics import _ray_centre

    width, height = model.config.image_size
    split = model.config.split
    size = min(split, width - split)
    centres = {h: _ray_centre(model, h) for h in Half}
    mid = np.array([[split / 2.0, height / 2.0], [split / 2.0 + 10.0, height / 2.0]])
    rays = model.rays(mid, Half.LEFT)
    d0, d1 = rays.directions
    focal = 10.0 / np.arccos(np.clip(d0 @ d1 / np.linalg.norm(d0) / np.linalg.norm(d1), -1, 1))
    rot = _frame(model, d0 / np.linalg.norm(d0), centres[Half.RIGHT] - centres[Half.LEFT])
    cx, cy = size / 2.0, height / 2.0
    xx, yy = np.meshgrid(np.arange(size, dtype=float), np.arange(height, dtype=float))
    dirs = np.stack([(xx - cx) / focal, (yy - cy) / focal, np.ones_like(xx)], -1) @ rot
    maps = {}
    for half in Half:
        c = centres[half]
        t = (z0 - c[2]) / dirs[..., 2]
        q = model.project(c + t[..., None] * dirs, half).pixels.astype(np.float32)
        maps[half] = q
    return maps, focal, float(np.linalg.norm(centres[Half.RIGHT] - centres[Half.LEFT]))


def sgbm_depth(model, image, z0: float, depth_range):
    """Left rectified pixels' original left pixel, depth (NaN: none) and the seconds."""
    import cv2

    from endomeasure.conventions import Half
    from endomeasure.solvers.triangulate import triangulate

    start = time.perf_counter()
    maps, focal, base = rectify(model, z0)
    grey = image.astype(np.float32)
    rect = {
        h: cv2.remap(
            grey,
            maps[h][..., 0],
            maps[h][..., 1],
            cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )  # fmt: skip
        for h in Half
    }
    # disparities of the searched depths at z0's rectification: d ~ f b / z, both ends
    lo = int(np.floor(focal * base / depth_range[1])) - 8
    hi = int(np.ceil(focal * base / depth_range[0])) + 8
    count = int(np.ceil((hi - lo) / 16.0)) * 16
    sgbm = cv2.StereoSGBM_create(
        minDisparity=lo, numDisparities=count, blockSize=BLOCK_PX, P1=8 * BLOCK_PX**2,
        P2=32 * BLOCK_PX**2, uniquenessRatio=5, disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )  # fmt: skip
    disp = (
        sgbm.compute(
            np.clip(rect[Half.LEFT], 0, 255).astype(np.uint8),
            np.clip(rect[Half.RIGHT], 0, 255).astype(np.uint8),
        ).astype(np.float64)
        / 16.0
    )
    valid = disp > lo - 1
    h, w = disp.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    xr = (xx - disp).astype(np.float32)
    right = np.stack([cv2.remap(maps[Half.RIGHT][..., k], xr, yy.astype(np.float32),
                                cv2.INTER_LINEAR, borderValue=np.nan)
                      for k in range(2)], -1)  # fmt: skip
    left = maps[Half.LEFT].astype(np.float64)
    valid &= np.isfinite(right).all(-1) & np.isfinite(left).all(-1)
    depth = np.full(disp.shape, np.nan)
    tri = triangulate(model, left[valid], right[valid].astype(np.float64))
    depth[valid] = tri.points[:, 2]
    return left, depth, time.perf_counter() - start


def true_depth_at(preset, target, pixels):
    """The truth optics' depth of the surface each left pixel (N, 2) sees (NaN: none),
    and whether the right half sees that point."""
    from endomeasure.conventions import Half

    rays = preset.truth_optics.rays(pixels, Half.LEFT)
    ok = rays.status == 0
    o = tuple(np.where(ok, rays.origins[:, k], 0.0) for k in range(3))
    d = tuple(np.where(ok, rays.directions[:, k], 0.0) for k in range(3))
    with np.errstate(invalid="ignore", divide="ignore"):
        hit = target.hit(o, d)
        z = np.where(ok & hit.hit, o[2] + hit.t * d[2], np.nan)
        points = rays.origins + hit.t[:, None] * rays.directions
    seen = preset.truth_optics.project(np.nan_to_num(points), Half.RIGHT).status == 0
    return z, seen & np.isfinite(z)


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--session", type=Path, default=ROOT / "out" / "demo" / "demo.h5")
    args = parser.parse_args(argv)
    from endomeasure.io.records import load_calibrated_model
    from endomeasure.io.session import open_session
    from endomeasure.pipeline import search_depths
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.scenes import plan_set

    preset = load_preset("default")
    shots = {s.name: s for s in plan_set(preset, "scene", 0)}
    with open_session(args.session) as reader:
        cm = load_calibrated_model(reader, "raytrace", args.session)
        images = {n: reader.image(n) for n in sorted(shots) if n in reader.image_names()}
    rows, errors, counted, measured = [], [], 0, 0
    for name, image in images.items():
        split = cm.model.config.split
        probe = np.stack(np.meshgrid(np.arange(0, split, 8.0), np.arange(0, 480, 8.0)), -1)
        z_probe, _ = true_depth_at(preset, shots[name].target, probe.reshape(-1, 2))
        z0 = float(np.nanmedian(z_probe))
        left, depth, seconds = sgbm_depth(cm.model, image, z0, search_depths(cm))
        inside = np.isfinite(left).all(-1)
        z_true, both = true_depth_at(preset, shots[name].target, np.nan_to_num(left).reshape(-1, 2))
        both = both.reshape(depth.shape) & inside
        z_true = z_true.reshape(depth.shape)
        ok = both & np.isfinite(depth)
        rel = np.abs(depth[ok] - z_true[ok]) / z_true[ok]
        errors.append(rel)
        counted += int(both.sum())
        measured += int(ok.sum())
        rows.append(f"| {name} | {z0:.1f} | {100 * ok.sum() / both.sum():.1f} | "
                    f"{100 * np.median(rel):.3f} | {100 * np.mean(rel <= 0.01):.1f} | "
                    f"{seconds:.2f} |")  # fmt: skip
    rel = np.concatenate(errors)
    report = Report("accuracy_dense_sgbm", args, ACCURACY)
    body = "\n".join([
        "## The alternative: StereoSGBM on a virtual rectification",
        "",
        f"`python bench/accuracy_dense_sgbm.py --session {args.session}`: the default "
        "preset's scene images, the demo's raytrace calibration; the halves rectified "
        "exactly at each frame's median true depth z0 (the alternative's best case), SGBM "
        f"({BLOCK_PX} px blocks, 3-way, disparities for the searched depths), the matched "
        "rectified pixels mapped back and triangulated by the model.",
        "",
        "| image | z0 mm | depth for % | median abs z error % of z | within 1 % of z | s |",
        "|---|---:|---:|---:|---:|---:|",
        *rows,
        "",
        f"Overall: depth for {100 * measured / counted:.1f} % of the pixels both halves see, "
        f"median |z error| {100 * np.median(rel):.3f} % of z, no sigma per pixel. Compare "
        "the section above (the same frames): SGBM covers more of the dim periphery "
        "(it fills weak texture from its neighbours by its smoothness terms) but, "
        "rectified for one depth through a non-central model and matched to 1/16 px, "
        "its depth is several times less accurate and carries no sigma, so it could at "
        "most seed the search; the plane sweep gives that seed within the same budget.",
    ])  # fmt: skip
    return report.finish({"dense-sgbm": body})


if __name__ == "__main__":
    sys.exit(main())
