"""The automatic split on random probe designs and the default preset (issues 15, 16).

Usage::

    python bench/accuracy_split.py [--designs 1-40] [--images 6] [--work DIR]
        [--quick] [--no-write]

For every design seed: the design ``endomeasure simulate OUT --preset random
--design-seed N`` would render, its calibration set planned as the simulator plans it
(seed 0), and ``--images`` of the images of its first board group (the group
``endomeasure detect`` fixes the split from, ``board_groups`` order), evenly spread, are
rendered with the simulator's noise through the simulate package's Python API (the same
pixels the command writes); ``--images 0``: every image of that group, the images the first
``detect`` call of ``bench/accuracy_designs.py`` receives and fixes the split from. The
split is found as ``detect`` finds it without ``--split``:
:func:`endomeasure.features.split.find_split_in_set` over the images'
:func:`~endomeasure.features.split.split_evidence`. The truth is the manifest's split,
``TruthOptics.apex_split()``: the column boundary nearest the apex image at the middle row.
The default preset is measured on the bundled renders of ``sample_sessions`` (the first
calibration board group, every image), as ``make demo`` detects it.

Renders go to ``WORK/split_NNN/`` and are reused (so are the full renders
``bench/accuracy_designs.py`` leaves in ``WORK/design_NNN/``); results are appended to
``WORK/split_designs.jsonl`` as each design finishes, and a rerun skips the designs found
there by the same finder (a changed ``features/split.py`` finds them again from the
renders). ``--quick``: designs 1-2, 3 images. Target (issue 16): within +-2 px on at least
39 of 40 designs and on the default preset.
"""

from __future__ import annotations

import hashlib
import json
import statistics
import time
import zlib
from pathlib import Path

import numpy as np

from _common import ACCURACY, ROOT, Report, Target, parse_seeds, script_parser

DEFAULT_DESIGNS = "1-40"
DEFAULT_IMAGES = 6
TOLERANCE_PX = 2
SAMPLES = ROOT / "sample_sessions"
FINDER = ROOT / "src" / "endomeasure" / "features" / "split.py"
TARGETS = {
    "designs": Target("random designs with the split within +-2 px", ">=", 39, "", "issue 16"),
    "default": Target("default preset: |split error|", "<=", TOLERANCE_PX, " px", "issue 16"),
}


def _finder_version() -> str:
    """The finder's source digest and its scene-misfit floor: results of another finder
    are found again."""
    from endomeasure.features import split

    digest = hashlib.sha256(FINDER.read_bytes()).hexdigest()[:12]
    return f"{digest}:{split.SCENE_MISFIT:g}"


def _spread(items: list, count: int) -> list:
    """``count`` items evenly spread over ``items`` (all of them if fewer, or if 0)."""
    if count <= 0 or count >= len(items):
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def _noise_rng(seed: int, set_name: str, index: int) -> np.random.Generator:
    # the generator ``endomeasure simulate`` gives each image (pipeline/simulate.py)
    return np.random.default_rng([int(seed), zlib.crc32(set_name.encode()), int(index),
                                  0x6E6F6973])  # fmt: skip


def _first_group(preset) -> tuple[str, list]:
    """The calibration set's first board group (``board_groups`` order) and its shots."""
    from endomeasure.simulate.scenes import plan_set

    groups: dict[str, list] = {}
    for shot in plan_set(preset, "calib", 0):
        # the spec the truth file and the manifest give (simulate/truth.py)
        groups.setdefault(shot.target.spec, []).append(shot)
    spec = sorted(groups)[0]
    return spec, groups[spec]


def _full_render(work: Path, seed: int, count: int) -> tuple[list[Path], int] | None:
    """Images and true split of a full render by ``accuracy_designs.py``, if present."""
    from endomeasure.simulate.manifest import board_groups, load_manifest

    folder = work / f"design_{seed:03d}"
    if not (folder / "simulation.json").exists():
        return None
    groups = board_groups(folder, "calib")
    if not groups:
        return None
    return _spread(groups[0][1], count), int(load_manifest(folder)["split"])


def _render(work: Path, seed: int, count: int) -> tuple[list[Path], int, float]:
    """Render (or reuse) ``count`` images of the design's first calibration group."""
    import cv2

    from endomeasure.simulate.design import draw_design
    from endomeasure.simulate.preset import Preset
    from endomeasure.simulate.render import render

    full = _full_render(work, seed, count)
    if full is not None:
        return *full, float("nan")  # rendered with the whole design, time not known
    folder = work / f"split_{seed:03d}"
    truth_file = folder / "split_truth.json"
    if truth_file.exists():
        truth = json.loads(truth_file.read_text())
        files = [folder / name for name in truth["images"]]
        if truth["count"] == count and all(f.exists() for f in files):
            return files, int(truth["split"]), float(truth.get("render_s", 0.0))
    start = time.perf_counter()
    preset = Preset.from_dict(draw_design(seed), source=f"random:design-seed={seed}")
    spec, shots = _first_group(preset)
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for shot in _spread(shots, count):
        image = render(preset, shot.target, rng=_noise_rng(0, "calib", shot.index)).image
        path = folder / f"{shot.name}.png"
        cv2.imwrite(str(path), image)
        files.append(path)
    split = int(preset.truth_optics.apex_split())
    seconds = time.perf_counter() - start
    truth_file.write_text(json.dumps({"split": split, "board_spec": spec, "count": count,
                                      "images": [f.name for f in files],
                                      "render_s": seconds}))  # fmt: skip
    return files, split, seconds


def _find(files: list[Path], true_split: int) -> dict:
    """The split ``detect`` would find from these images, against the truth."""
    import cv2

    from endomeasure.errors import BadInputError
    from endomeasure.features.split import find_split_in_set, split_evidence

    start = time.perf_counter()
    evidence = []
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        evidence.append(split_evidence(image, path=str(path)))
    size = list(evidence[0].image_size)
    try:
        estimate = find_split_in_set(evidence)
    except BadInputError as exc:
        return {"sensor": size, "true_split": true_split, "found": None,
                "refused": exc.what, "find_s": time.perf_counter() - start}  # fmt: skip
    return {
        "sensor": size,
        "true_split": true_split,
        "found": estimate.split,
        "error": estimate.split - true_split,
        "centre_px": estimate.centre_px,
        "width_px": estimate.width_px,
        "significance": estimate.significance,
        "images": estimate.images,
        "find_s": time.perf_counter() - start,
    }


def run_design(seed: int, work: Path, count: int) -> dict:
    files, true_split, render_s = _render(work, seed, count)
    return {"seed": seed, "finder": _finder_version(), "render_s": render_s,
            **_find(files, true_split)}  # fmt: skip


def run_default() -> dict:
    """The bundled default renders: the first calibration board group, every image."""
    from endomeasure.simulate.manifest import board_groups, load_manifest

    spec, files = board_groups(SAMPLES, "calib")[0]
    return {"board": spec, **_find(files, int(load_manifest(SAMPLES)["split"]))}


def _within(r: dict) -> bool:
    return r.get("found") is not None and abs(r["error"]) <= TOLERANCE_PX


def _row(r: dict) -> str:
    size = "x".join(map(str, r["sensor"]))
    if r.get("found") is None:
        return f"| {r['seed']} | {size} | {r['true_split']} | refused | - | {r['refused'][:70]} |"
    return (
        f"| {r['seed']} | {size} | {r['true_split']} | {r['found']} | {r['error']:+d} | "
        f"centre {r['centre_px']:.2f}, band {r['width_px']:.1f} px wide, "
        f"{r['significance']:.0f} sigma, {r['find_s']:.1f} s |"
    )


def _summarise(results: list[dict], default: dict, report: Report, label: str, count: int):
    within = sum(_within(r) for r in results)
    errors = [abs(r["error"]) for r in results if r.get("found") is not None]
    refused = sum(r.get("found") is None for r in results)
    default_error = abs(default["error"]) if default.get("found") is not None else np.inf
    checks = {
        "designs": report.check(TARGETS["designs"], within),
        "default": report.check(TARGETS["default"], default_error),
    }
    find_s = [r["find_s"] for r in results]
    render_s = [r["render_s"] for r in results if np.isfinite(r["render_s"])]
    default_text = (
        f"{default['found']} against {default['true_split']} ({default['error']:+d} px; band "
        f"centre {default['centre_px']:.2f}, {default['width_px']:.1f} px wide)"
        if default.get("found") is not None
        else f"refused: {default['refused']}"
    )
    lines = [
        f"Designs {label}, {count or 'all'} images of each design's first calibration board group "
        f"(the images `endomeasure detect` fixes the split from); made by "
        "`python bench/accuracy_split.py --work out/split_designs`. The split is found as "
        "`detect` finds it without `--split`; the truth is the manifest's `split` "
        "(`TruthOptics.apex_split()`).",
        "",
        "| target | this run | verdict |",
        "|---|---|---|",
        f"| within +-2 px on >= 39 of 40 designs | {within} of {len(results)} | "
        f"{checks['designs']} |",
        f"| the default preset within +-2 px (`sample_sessions`, {default['board']}, "
        f"{default.get('images', 0)} images) | {default_text} | {checks['default']} |",
        "",
        f"Largest |error| {max(errors) if errors else float('nan'):.0f} px; "
        f"refused {refused}; finding the split took {statistics.median(find_s):.1f} s "
        f"(median, {max(find_s):.1f} s at most) per design; rendering the images took "
        f"{sum(render_s) / 60:.1f} min for {len(render_s)} designs (one core).",
        "",
        "| seed | sensor | true split | found | error px | fit |",
        "|---|---|---|---|---|---|",
        *(_row(r) for r in sorted(results, key=lambda r: r["seed"])),
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = script_parser(__doc__, work=True)
    parser.add_argument("--designs", default=DEFAULT_DESIGNS, help="seeds, e.g. 1-40 or 1,5")
    parser.add_argument("--images", type=int, default=DEFAULT_IMAGES,
                        help=f"images per design ({DEFAULT_IMAGES}; 0: all)")  # fmt: skip
    parser.add_argument(
        "--scene-misfit", type=float, default=None,
        help="another SCENE_MISFIT of the finder, for a sensitivity run (implies --no-write)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.scene_misfit is not None:
        from endomeasure.features import split

        split.SCENE_MISFIT = args.scene_misfit
        args.no_write = True
    report = Report("bench/accuracy_split.py", args, ACCURACY)
    seeds = parse_seeds("1-2" if args.quick else args.designs)
    count = 3 if args.quick else args.images
    work = args.work or ROOT / "out" / "split_designs"
    work.mkdir(parents=True, exist_ok=True)
    store = work / "split_designs.jsonl"
    version = _finder_version()
    done: dict[int, dict] = {}
    if store.exists():
        for line in store.read_text().splitlines():
            r = json.loads(line)
            if r.get("finder") == version and r.get("images_asked", count) == count:
                done[r["seed"]] = r
    for seed in seeds:
        if seed in done:
            continue
        r = {**run_design(seed, work, count), "images_asked": count}
        done[seed] = r
        with store.open("a") as f:
            f.write(json.dumps(r) + "\n")
        print(_row(r), flush=True)
    results = [done[s] for s in seeds]
    default = run_default()
    body = _summarise(results, default, report, "1-2" if args.quick else args.designs, count)
    return report.finish({"split-designs": body})


if __name__ == "__main__":
    raise SystemExit(main())
