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

Planted pits (issue 20): ``--pits`` per scene image, each rendered alone into the scene
image's pose with the scene set's sensor noise (the scene image plus the pit). The rule
(seeded, ``--seed``): radius and depth uniform in :data:`PIT_RADIUS_MM` and
:data:`PIT_DEPTH_MM`; the centre uniform within :data:`PIT_REACH_MM` on the surface of the
point the left half sees at the centroid of the pixels both halves see, weighted by the
plain image's grey levels (the bright middle of the view), clear of the marks; the path
runs along the cylinder's generator (its straight direction, so the undamaged surface
between the ends is straight) through the centre, its ends a correlation window beyond the
rim, both seen by the right half. Measured as above (dense surface, best-fit plane near
the ends, profile); truth: the exact pitted surface through the truth optics against the
same construction on the true points; the profile's deepest sample against the true
profile's deepest, within its 2 sigma.
With ``--designs WORK`` the same on random probe designs: each design's calibrated session
``WORK/design_NNN.h5`` and the first ``--images`` of its scene set ``WORK/design_NNN_scene``
(as ``bench/accuracy_dense.py --designs`` reads them), the truth from the design's preset.
Writes the ``profile`` section of docs/accuracy.md unless ``--no-write``; target: issue 20.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import (  # noqa: E402
    ACCURACY,
    Report,
    Target,
    design_scenes,
    parse_seeds,
    scene_options,
    script_parser,
    window_range,
)

EXTREME_TARGET = Target(
    "profile extremes within 2 sigma of the true extreme", ">=", 90.0, " %", "issue 20"
)
PIT_TARGET = Target("planted pit depths within 2 sigma of the true depth", ">=", 90.0, " %",
                    "issue 20")  # fmt: skip
LENGTH_PX = (120, 220)
"""Random paths' lengths: across a good part of the left half's overlap."""
PIT_RADIUS_MM = (0.5, 1.5)
"""Planted pits' radii: a corrosion pit or an impact dent 1-3 mm across."""
PIT_DEPTH_MM = (0.2, 0.5)
"""Planted pits' depths below the cylinder."""
PIT_REACH_MM = 2.5
"""Pit centres lie within this (on the surface) of the point the left half sees at the
brightness-weighted centroid of the pixels both halves see: the bright middle of the view."""
MARK_CLEARANCE_MM = 0.3
"""A pit's rim keeps this clear of a mark's edge: the pits go on mark-free surface."""
SCENE_SEED = 0
"""The demo's scene set: ``plan_set(default, 'scene', 0)`` poses and its sensor noise."""


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


def _surface_coordinates(target, points: np.ndarray) -> np.ndarray:
    """Arc length and height (n, 2), mm, of camera-frame points on the cylinder."""
    x, y, z = ((points - target.t) @ target.R).T
    r = target.radius_mm
    return np.stack([r * np.arctan2(x, r - z), y], axis=-1)


def _left_pixels(preset, target, s, y) -> np.ndarray:
    """True left pixels (n, 2) of the plain cylinder's points (s, y) (NaN: not seen)."""
    from endomeasure.conventions import Half

    points = target.surface_points(np.asarray(s), np.asarray(y)) @ target.R.T + target.t
    proj = preset.truth_optics.project(points, Half.LEFT)
    return np.where((proj.status == 0)[:, None], proj.pixels, np.nan)


def _plant_pits(rng, preset, target, grey, mask: np.ndarray, window: int, count: int) -> list:
    """``count`` pits (s, y, radius, depth) by the module's rule, each with its path's ends
    (px) and its diameter in correlation windows."""
    vv, uu = np.nonzero(mask)
    weight = grey[vv, uu]
    bright = np.array([[np.average(uu, weights=weight), np.average(vv, weights=weight)]])
    centre = _true_points(preset, target, bright)
    s0, y0 = _surface_coordinates(target, centre)[0]
    marks = target.marks_sy
    h, w = mask.shape

    def seen(q):
        ok = np.all(np.isfinite(q), axis=1)
        ok &= (q[:, 0] >= window) & (q[:, 0] < w - window)
        ok &= (q[:, 1] >= window) & (q[:, 1] < h - window)
        i = np.where(ok[:, None], np.rint(q), 0).astype(int)
        return ok & mask[i[:, 1], i[:, 0]]

    pits = []
    for _ in range(1000):
        if len(pits) == count:
            return pits
        radius, depth = rng.uniform(*PIT_RADIUS_MM), rng.uniform(*PIT_DEPTH_MM)
        reach, angle = PIT_REACH_MM * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        s, y = s0 + reach * np.cos(angle), y0 + reach * np.sin(angle)
        gap = np.hypot(marks[:, 0] - s, marks[:, 1] - y) - target.mark_radius_mm - radius
        if np.any(gap < MARK_CLEARANCE_MM):
            continue
        # the ends: along the generator, a correlation window (in mm at the pit) off the rim
        q = _left_pixels(preset, target, [s, s], [y, y + 1.0])
        window_mm = window / float(np.linalg.norm(q[1] - q[0]))
        reach_mm = radius + window_mm
        ends = _left_pixels(preset, target, [s, s, s], [y - reach_mm, y, y + reach_mm])
        if np.all(seen(ends)):
            pits.append((np.array([s, y, radius, depth]), ends[0], ends[2], 2 * radius / window_mm))
    raise RuntimeError("no pit found by the rule where both halves see the surface")


def _pit_rows(cm, preset, shots, images, settings, per_image: int, seed: int,
              scene_seed: int = SCENE_SEED, label: str = "", matte: bool = False):  # fmt: skip
    """The planted-pit cases: table rows, within-2-sigma flags and refusals (``label``
    before each image's name; ``scene_seed``: the scene set's, for its sensor noise;
    ``matte``: the pitted part rendered without its specular reflection, a control)."""
    import dataclasses

    from endomeasure.pipeline.simulate import _noise_rng
    from endomeasure.simulate.render import render

    rng = np.random.default_rng([seed, 20])  # apart from the random paths' draws
    rows, ok, ratio, refused = [], [], [], []
    for name in images:
        shot = shots[name]
        mask = _seen_mask(preset, shot.target, cm.model.config.split)
        try:
            planted = _plant_pits(rng, preset, shot.target, images[name][:, : mask.shape[1]],
                                  mask, settings.window_px, per_image)  # fmt: skip
        except RuntimeError as exc:  # a scene with no room for the rule: said, not hidden
            refused.append(f"{label}{name}: {exc}")
            continue
        for k, (pit, a, b, windows) in enumerate(planted):
            target = shot.target.with_pits(pit[None])
            if matte:
                target = dataclasses.replace(target, specular=0.0)
            image = render(preset, target, rng=_noise_rng(scene_seed, "scene", shot.index)).image
            try:
                prof, truth = _case(cm, preset, target, image, a, b, settings)
            except Exception as exc:  # a refusal is a result: counted, not hidden
                refused.append(f"{label}{name} pit {k}: {exc}")
                continue
            valid = np.isfinite(prof.samples.height)
            e = prof.deepest
            true_deepest = float(np.nanmin(truth[valid]))
            ok.append(abs(e.height_mm - true_deepest) <= 2 * e.sigma_mm)
            ratio.append(e.height_mm / true_deepest)
            bottom = _left_pixels(preset, shot.target, pit[:1], pit[1:2])[0]
            rows.append(
                f"| {label}{name} | {k} | {pit[0]:+.2f}, {pit[1]:+.2f} | {pit[2]:.2f} | "
                f"{pit[3]:.3f} | {windows:.2f} | {a[0]:.0f},{a[1]:.0f} -> {b[0]:.0f},{b[1]:.0f} | "
                f"{100 * prof.coverage:.0f} | {e.height_mm:+.3f} | {e.sigma_mm:.3f} | "
                f"{true_deepest:+.3f} | {100 * ratio[-1]:.0f} | "
                f"{(e.height_mm - true_deepest) / e.sigma_mm:+.2f} | {'yes' if ok[-1] else 'no'} | "
                f"{np.linalg.norm(np.asarray(e.pixel) - bottom):.0f} |"
            )
    return rows, ok, np.array(ratio), refused


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


def _paths(label, cm, preset, shots, images, settings, rng, paths: int):
    """The random paths' cases of one scene set: table rows, the extremes' and the deepest
    and highest samples' within-2-sigma flags, refusals and seconds per profile."""
    rows, extreme_ok, own_ok, refused, seconds = [], [], [], [], []
    for name, grey in images.items():
        mask = _seen_mask(preset, shots[name].target, cm.model.config.split)
        for k in range(paths):
            a, b = _random_path(rng, mask, settings.window_px)
            start = time.perf_counter()
            try:
                prof, truth = _case(cm, preset, shots[name].target, grey, a, b, settings)
            except Exception as exc:  # a refusal is a result: counted, not hidden
                refused.append(f"{label}{name} path {k}: {exc}")
                continue
            seconds.append(time.perf_counter() - start)
            valid = np.isfinite(prof.samples.height)
            e = prof.extreme
            true_extreme = np.nanmax(truth[valid]) if e is prof.highest else np.nanmin(truth[valid])
            extreme_ok.append(abs(e.height_mm - true_extreme) <= 2 * e.sigma_mm)
            for x in (prof.deepest, prof.highest):
                own_ok.append(abs(x.height_mm - truth[x.index]) <= 2 * x.sigma_mm)
            rows.append(
                f"| {label}{name} | {k} | {a[0]:.0f},{a[1]:.0f} -> {b[0]:.0f},{b[1]:.0f} | "
                f"{100 * prof.coverage:.0f} | {e.height_mm:+.3f} | {e.sigma_mm:.3f} | "
                f"{true_extreme:+.3f} | {(e.height_mm - true_extreme) / e.sigma_mm:+.2f} |"
            )
    return rows, extreme_ok, own_ok, refused, seconds


class _SceneSet(NamedTuple):
    """A calibration and the scene images it measures, with their truth."""

    label: str  # before each image's name in the tables
    cm: object
    preset: object
    shots: dict
    images: dict  # name -> grey image
    scene_seed: int


def _default_set(session: Path) -> _SceneSet:
    import shutil
    import tempfile

    from endomeasure.io.records import load_calibrated_model
    from endomeasure.io.session import open_session
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.scenes import plan_set

    preset = load_preset("default")
    shots = {s.name: s for s in plan_set(preset, "scene", SCENE_SEED)}
    with tempfile.TemporaryDirectory() as tmp:  # read a copy: the demo session stays as it is
        copy = Path(tmp) / "demo.h5"
        shutil.copyfile(session, copy)
        with open_session(copy) as reader:
            cm = load_calibrated_model(reader, "raytrace", copy)
            images = {n: reader.image(n) for n in sorted(shots) if n in reader.image_names()}
    images = {n: im[..., :3].mean(axis=2) if im.ndim == 3 else im for n, im in images.items()}
    return _SceneSet("", cm, preset, shots, images, SCENE_SEED)


def _design_set(work: Path, seed: int, count: int) -> _SceneSet | None:
    """A random design's calibration and its first ``count`` scene images
    (:func:`design_scenes`); None without either."""
    design = design_scenes(work, seed, count)
    if design is None:
        return None
    images = {n: im.astype(np.float64) for n, im in design.images.items()}
    return _SceneSet(f"design {seed} / ", design.cm, design.preset,
                     {s.name: s for s in design.shots}, images, design.scene_seed)  # fmt: skip


def main() -> int:
    parser = script_parser(__doc__, seed=0)
    scene_options(parser)
    parser.add_argument("--paths", type=int, default=8, help="random paths per scene image")
    parser.add_argument("--pits", type=int, default=3, help="planted pits per scene image")
    parser.add_argument("--window-range", type=window_range, default=None,
                        help="refinement windows LO,HI px (default: profiles')")  # fmt: skip
    parser.add_argument("--matte", action="store_true",
                        help="render the pitted part without its specular reflection (a "
                             "control: what the view-dependent highlight costs); implies "
                             "--no-write")  # fmt: skip
    args = parser.parse_args()
    if args.matte:
        args.no_write = True

    from endomeasure import defaults
    from endomeasure.measure.dense import DenseSettings
    from endomeasure.pipeline.measure import search_depths

    paths = 2 if args.quick else args.paths
    pits = 1 if args.quick else args.pits
    windows = args.window_range or defaults.PROFILE_WINDOW_RANGE_PX
    sets = [_default_set(args.session)]
    if args.designs is not None:
        for seed in parse_seeds(args.design_seeds):
            found = _design_set(args.designs, seed, args.images)
            if found is not None:
                sets.append(found)
    rng = np.random.default_rng(args.seed)
    rows, extreme_ok, own_ok, refused, seconds = [], [], [], [], []
    pit_rows, pit_ok, pit_ratio, pit_refused = [], [], [], []
    for one in sets:
        settings = DenseSettings(  # as `measure --kind profile`
            depth_range_mm=search_depths(one.cm), window_range_px=windows
        )
        for into, got in zip((rows, extreme_ok, own_ok, refused, seconds),
                             _paths(one.label, one.cm, one.preset, one.shots, one.images,
                                    settings, rng, paths), strict=True):  # fmt: skip
            into.extend(got)
        got = _pit_rows(one.cm, one.preset, one.shots, one.images, settings, pits, args.seed,
                        one.scene_seed, one.label, args.matte)  # fmt: skip
        for into, part in zip((pit_rows, pit_ok, pit_ratio, pit_refused), got, strict=True):
            into.extend(part)
        print(f"{one.label.rstrip(' /') or 'default preset'}: {len(rows)} profiles, "
              f"{len(pit_ok)} pits so far",
              file=sys.stderr, flush=True)  # fmt: skip
    pit_ratio = np.array(pit_ratio)
    pit_share = 100 * float(np.mean(pit_ok)) if pit_ok else float("nan")
    share = 100 * float(np.mean(extreme_ok)) if extreme_ok else float("nan")
    own = 100 * float(np.mean(own_ok)) if own_ok else float("nan")
    report = Report("accuracy_profile", args, ACCURACY)
    check = report.check(EXTREME_TARGET, share)
    pit_check = report.check(PIT_TARGET, pit_share)
    command = (f"{Path(sys.executable).name} bench/accuracy_profile.py --session {args.session} "
               f"--paths {args.paths} --pits {args.pits} --seed {args.seed}")  # fmt: skip
    if args.window_range is not None:
        command += f" --window-range {windows[0]},{windows[1]}"
    if args.designs is not None:
        command += f" --designs {args.designs} --design-seeds {args.design_seeds}"
        command += f" --images {args.images}"
    body = "\n".join([
        "## Depth profiles across the cylinder",
        "",
        f"`{command}` (the demo's raytrace calibration of the default preset, its scene "
        "images; with `--designs`, each random design's own calibration and first scene "
        "images too; random straight paths of "
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
        "### Planted pits of known depth",
        "",
        f"{pits} pits per scene image, each rendered alone into the image's pose with the "
        "scene set's sensor noise (the scene image plus the pit; `MetalCylinder.pits`, a "
        "smooth bowl `depth (1 - (r/R)^2)^2` along the inward normal). Placed by a seeded "
        f"rule: radius {PIT_RADIUS_MM[0]}-{PIT_RADIUS_MM[1]} mm, depth "
        f"{PIT_DEPTH_MM[0]}-{PIT_DEPTH_MM[1]} mm, centre within {PIT_REACH_MM} mm (on the "
        "surface) of the point seen at the brightness-weighted centroid of the pixels both "
        "halves see (the plain image's grey levels), clear "
        f"of the marks by {MARK_CLEARANCE_MM} mm; the path runs along the cylinder's "
        "generator through the centre, its ends a correlation window beyond the rim. "
        "Measured as above (best-fit plane near the ends); truth: the exact pitted surface "
        "through the truth optics against the same construction on the true points. "
        "Deepest: the profile's deepest sample +- its 1-sigma; true deepest: the true "
        "profile's deepest over the samples with a depth; diameter / window: the pit's "
        "diameter over the correlation window's width on the surface at the pit; off centre: "
        "the deepest sample's distance from the pit centre's true pixel.",
        "",
        "| image | pit | centre s, y mm | radius mm | planted depth mm | diameter / window | "
        "path px | depth for % | deepest mm | sigma mm | true deepest mm | measured / true % | "
        "error / sigma | within 2 sigma | off centre px |",
        "|---|---:|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---:|",
        *pit_rows,
        "",
        f"- {pit_check.target}: {pit_share:.1f} % of {len(pit_ok)} pits ({pit_check})",
        f"- measured deepest / true deepest: median {100 * np.median(pit_ratio):.0f} %, "
        f"{100 * pit_ratio.min():.0f}-{100 * pit_ratio.max():.0f} %; shallower than the truth "
        f"in {int(np.sum(pit_ratio < 1))} of {pit_ratio.size}",
        f"- refused: {len(pit_refused)}"
        + ("".join(f"; {r}" for r in pit_refused) if pit_refused else ""),
        "",
        "A dense depth is that of its pixel's whole correlation window (docs/surface.md), "
        "so a pit about a window across comes out smoothed (compare measured / true with "
        "diameter / window); the sigma holds the chosen window's departure from the "
        "smaller windows beyond their noise, an estimate of that smoothing "
        f"(windows {windows[0]}-{windows[1]} px; `measure --kind profile` uses "
        f"`defaults.PROFILE_WINDOW_RANGE_PX`, {defaults.PROFILE_WINDOW_RANGE_PX[0]}-"
        f"{defaults.PROFILE_WINDOW_RANGE_PX[1]} px).",
    ])  # fmt: skip
    return report.finish({"profile": body})


if __name__ == "__main__":
    sys.exit(main())
