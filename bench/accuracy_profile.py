"""Depth profiles across the simulator's cylinder against its exact surface.

For each scene image of the demo session (``make demo``; ``--session``, read only) and
``--paths`` random paths across the cylinder (seeded): the ``raytrace`` model's dense
surface over the path's region, the best-fit reference plane to the dense points near
the path's two ends and the profile (:mod:`endomeasure.measure.profile`), as ``measure
--kind profile`` without ``--ref`` computes them. Truth: where each sample pixel's ray
through the truth optics meets the posed cylinder (``plan_set``'s exact pose), against
the orthogonal best-fit plane of the true points of the same end pixels. Reported: the
share of profiles whose extreme (the deepest or highest sample, whichever is farther from
the plane) lies within its 2 sigma of the true profile's extreme over the samples with a
depth, and of the deepest and highest samples against the truth at their own pixel.
Writes the ``profile`` section of docs/accuracy.md unless ``--no-write``; target: issue 20.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import ACCURACY, Report, Target, script_parser  # noqa: E402

EXTREME_TARGET = Target(
    "profile extremes within 2 sigma of the true extreme", ">=", 90.0, " %", "issue 20"
)
LENGTH_PX = (120, 220)
"""Random paths' lengths: across a good part of the left half's overlap."""


def _true_points(preset, target, pixels: np.ndarray) -> np.ndarray:
    """Where the truth optics' left rays of ``pixels`` (n, 2) meet the target (NaN: miss)."""
    from endomeasure.conventions import Half

    rays = preset.truth_optics.rays(pixels, Half.LEFT)
    o, d = rays.origins, rays.directions
    hit = target.hit(tuple(o.T), tuple(d.T))
    return o + np.asarray(hit.t)[:, None] * d


def _seen_mask(preset, target, split: int) -> np.ndarray:
    """Left pixels whose true surface point the right half sees (H, split)."""
    from endomeasure.conventions import Half
    from endomeasure.simulate.truth import true_depth

    truth = true_depth(preset, target).astype(np.float64)[:, :split]
    vv, uu = np.indices(truth.shape)
    rays = preset.truth_optics.rays(np.stack([uu, vv], -1).reshape(-1, 2).astype(float), Half.LEFT)
    t = (truth.reshape(-1) - rays.origins[:, 2]) / rays.directions[:, 2]
    seen = preset.truth_optics.project(rays.origins + t[:, None] * rays.directions, Half.RIGHT)
    return np.isfinite(truth) & (seen.status == 0).reshape(truth.shape)


def _random_path(rng, mask: np.ndarray, margin: int):
    """A straight path whose ends and middle lie where both halves see the surface."""
    h, w = mask.shape
    for _ in range(1000):
        length = rng.uniform(*LENGTH_PX)
        angle = rng.uniform(0, np.pi)
        centre = rng.uniform([margin, margin], [w - margin, h - margin])
        half = 0.5 * length * np.array([np.cos(angle), np.sin(angle)])
        a, b = centre - half, centre + half
        probe = [a, b, centre]
        if all(margin <= p[0] < w - margin and margin <= p[1] < h - margin for p in probe) and all(
            mask[int(round(p[1])), int(round(p[0]))] for p in probe
        ):
            return a, b
    raise RuntimeError("no path found where both halves see the surface")


def _case(cm, preset, target, image, a, b, settings):
    from endomeasure.measure import profile as core
    from endomeasure.measure.dense import dense_surface
    from endomeasure.pipeline.profile import _region

    window = settings.window_px
    areas = [core.disc_pixels(p, window / 2) for p in (a, b)]
    path = core.path_pixels(a, b)
    region = _region(cm.model, np.vstack([path, *areas]), window)
    surface = dense_surface(cm.model, image, region, settings)
    measured = [core.area_points(cm.model, surface, q) for q in areas]
    plane = core.plane_fit(measured, window)
    prof = core.profile_of(cm.model, surface, plane, path)
    # the truth: the orthogonal plane of the true points of the valid end pixels
    from endomeasure.measure.dense import DenseStatus

    ends = []
    for q in areas:
        iv, iu = q[:, 1].astype(int) - region[1], q[:, 0].astype(int) - region[0]
        inside = (iv >= 0) & (iv < surface.status.shape[0]) & (iu >= 0)
        inside &= iu < surface.status.shape[1]
        ok = np.zeros(len(q), bool)
        ok[inside] = surface.status[iv[inside], iu[inside]] == DenseStatus.OK
        ends.append(_true_points(preset, target, q[ok].astype(float)))
    pts = np.vstack(ends)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    centre = pts.mean(axis=0)
    normal = np.linalg.svd(pts - centre)[2][2]
    normal = normal if normal @ (-centre) > 0 else -normal
    truth = (_true_points(preset, target, np.rint(prof.samples.pixels)) - centre) @ normal
    return prof, truth


def main() -> int:
    parser = script_parser(__doc__, seed=0)
    parser.add_argument("--session", type=Path, default=ROOT / "out" / "demo" / "demo.h5")
    parser.add_argument("--paths", type=int, default=8, help="random paths per scene image")
    args = parser.parse_args()
    import shutil
    import tempfile

    from endomeasure.io.records import load_calibrated_model
    from endomeasure.io.session import open_session
    from endomeasure.measure.dense import DenseSettings
    from endomeasure.pipeline.measure import search_depths
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.scenes import plan_set

    paths = 2 if args.quick else args.paths
    preset = load_preset("default")
    shots = {s.name: s for s in plan_set(preset, "scene", 0)}
    with tempfile.TemporaryDirectory() as tmp:  # read a copy: the demo session stays as it is
        copy = Path(tmp) / "demo.h5"
        shutil.copyfile(args.session, copy)
        with open_session(copy) as reader:
            cm = load_calibrated_model(reader, "raytrace", copy)
            images = {n: reader.image(n) for n in sorted(shots) if n in reader.image_names()}
    settings = DenseSettings(depth_range_mm=search_depths(cm))
    rng = np.random.default_rng(args.seed)
    rows, extreme_ok, own_ok, refused, seconds = [], [], [], [], []
    for name, image in images.items():
        grey = image[..., :3].mean(axis=2) if image.ndim == 3 else image
        mask = _seen_mask(preset, shots[name].target, cm.model.config.split)
        for k in range(paths):
            a, b = _random_path(rng, mask, settings.window_px)
            start = time.perf_counter()
            try:
                prof, truth = _case(cm, preset, shots[name].target, grey, a, b, settings)
            except Exception as exc:  # a refusal is a result: counted, not hidden
                refused.append(f"{name} path {k}: {exc}")
                continue
            seconds.append(time.perf_counter() - start)
            valid = np.isfinite(prof.samples.height)
            e = prof.extreme
            true_extreme = np.nanmax(truth[valid]) if e is prof.highest else np.nanmin(truth[valid])
            extreme_ok.append(abs(e.height_mm - true_extreme) <= 2 * e.sigma_mm)
            for x in (prof.deepest, prof.highest):
                own_ok.append(abs(x.height_mm - truth[x.index]) <= 2 * x.sigma_mm)
            rows.append(
                f"| {name} | {k} | {a[0]:.0f},{a[1]:.0f} -> {b[0]:.0f},{b[1]:.0f} | "
                f"{100 * prof.coverage:.0f} | {e.height_mm:+.3f} | {e.sigma_mm:.3f} | "
                f"{true_extreme:+.3f} | {(e.height_mm - true_extreme) / e.sigma_mm:+.2f} |"
            )
    share = 100 * float(np.mean(extreme_ok)) if extreme_ok else float("nan")
    own = 100 * float(np.mean(own_ok)) if own_ok else float("nan")
    report = Report("accuracy_profile", args, ACCURACY)
    check = report.check(EXTREME_TARGET, share)
    command = (f"{Path(sys.executable).name} bench/accuracy_profile.py --session {args.session} "
               f"--paths {args.paths} --seed {args.seed}")  # fmt: skip
    body = "\n".join([
        "## Depth profiles across the cylinder",
        "",
        f"`{command}` (the demo's raytrace calibration of the default preset, its scene "
        "images; random straight paths of "
        f"{LENGTH_PX[0]}-{LENGTH_PX[1]} px whose ends and middle the right half sees; the "
        "reference plane: the best fit near the path's ends, as `measure --kind profile` "
        "without `--ref`). Truth: the truth optics' rays against the exact posed cylinder, "
        "heights against the orthogonal plane of the true points of the same end pixels.",
        "",
        "| image | path | pixels | depth for % | extreme mm | sigma mm | true extreme mm | "
        "error / sigma |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
        *rows,
        "",
        f"- {check.target}: {share:.1f} % of {len(extreme_ok)} profiles ({check})",
        f"- deepest and highest samples within 2 sigma of the truth at their own pixel: "
        f"{own:.1f} % of {len(own_ok)}",
        f"- refused: {len(refused)}" + ("".join(f"; {r}" for r in refused) if refused else ""),
        f"- {np.median(seconds):.1f} s per profile (median; the dense search of its region)",
        "",
        "A planted pit of known depth (issue 20) is not measured here yet: the simulator's "
        "cylinder has no pits.",
    ])  # fmt: skip
    return report.finish({"profile": body})


if __name__ == "__main__":
    sys.exit(main())
