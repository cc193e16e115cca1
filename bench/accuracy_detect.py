"""Corner detection and calibration against the simulator's exact truth (issues 5 and 6).

For the default preset's calibration and test sets, rendered once with the default
noise (the committed ``sample_sessions/``) and once noise-free (rendered here into a
temporary folder, same seed), this runs ``endomeasure detect`` per board, then compares
every detected corner with the true pixel of the same id from the ground-truth JSON:

- corner error: RMS over all detected corners of ``|detected - true|`` (px);
- id agreement: a detected id names the right physical corner when it lies within
  ``ID_MATCH_PX`` of that id's true pixel (and no other corner's);
- detection rate: halves with the board found / halves that show the whole board.

Then it calibrates both models on the noisy calibration set (``endomeasure calibrate
--model all``) and compares each model's residual RMS with the detection-noise floor
(the RMS of detected minus true corners of the same images), and the raytrace
parameters with the truth optics. Writes the ``detection-simulator`` and
``calibration-simulator`` sections of docs/accuracy.md unless ``--no-write``.

    .venv/bin/python bench/accuracy_detect.py [--keep DIR] [--quick] [--no-write]

Targets: issue 5's (listed under ``*_TARGET`` below) and issue 6's residual ratio.
``--quick``: the noisy sample set only (no noise-free render, no calibration).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from _common import ACCURACY, ROOT, Report, Target, script_parser
from _samples import SETS, detect_samples, detection_errors
from _samples import endomeasure as run_command
from endomeasure.simulate.manifest import MANIFEST_NAME, load_manifest

ID_MATCH_PX = 1.0  # true corners are >= 5 px apart in every image of the preset
SAMPLES = ROOT / "sample_sessions"
DETECTION, CALIBRATION = "detection-simulator", "calibration-simulator"
NOISE_FREE_RMS_TARGET = Target("corner RMS, noise-free render", "<=", 0.05, " px", "issue 5")
NOISY_RMS_TARGET = Target("corner RMS, default noise", "<=", 0.1, " px", "issue 5")
WRONG_IDS_TARGET = Target("wrong ids", "==", 0, "", "issue 5")
CALIB_HALVES_TARGET = Target("calibration halves detected", ">=", 95.0, " %", "issue 5")
RESIDUAL_TARGET = Target("raytrace residual RMS / detection noise floor", "<=", 1.1, "x", "issue 6")
RMS_TARGETS = {"default noise": NOISY_RMS_TARGET, "noise-free": NOISE_FREE_RMS_TARGET}


def endomeasure(*args: str) -> str:
    return run_command(*args, check=False).stdout


def compare(image_root: Path, session: Path) -> dict[str, dict]:
    halves = detection_errors(image_root, session)
    out = {}
    for set_name in SETS:
        errors, wrong_ids, halves_visible, halves_found = [], 0, 0, 0
        for h in (h for h in halves if h.set_name == set_name):
            halves_visible += h.visible
            if not h.found:
                continue
            halves_found += h.visible
            diff = h.errors
            dist = np.linalg.norm(diff, axis=-1)
            # the nearest true corner of every detection must be its own id
            all_d = np.linalg.norm(h.detected[:, None] - h.true_pixels[None], axis=-1)
            nearest = np.nanargmin(np.where(np.isnan(all_d), np.inf, all_d), axis=1)
            wrong_ids += int(np.sum((nearest != h.ids) | ~(dist < ID_MATCH_PX)))
            errors.append(diff[np.isfinite(dist)])
        e = np.concatenate(errors) if errors else np.empty((0, 2))
        out[set_name] = dict(
            corners=len(e),
            rms=float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
            rms_axis=float(np.sqrt(np.mean(e**2))),
            max=float(np.max(np.linalg.norm(e, axis=1))),
            wrong_ids=wrong_ids,
            halves=(halves_found, halves_visible),
        )
    return out


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--keep", type=Path, help="render and keep the noise-free set here")
    args = parser.parse_args(argv)
    report = Report("bench/accuracy_detect.py", args, ACCURACY)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        renders = [("default noise", SAMPLES)]
        if not args.quick:
            clean_root = args.keep or tmp / "noise_free"
            if not (clean_root / MANIFEST_NAME).exists():
                seed = load_manifest(SAMPLES)["seed"]
                endomeasure("simulate", str(clean_root), "--preset", "default",
                            "--set", "calib,test", "--seed", str(seed), "--noise-free")  # fmt: skip
            renders.append(("noise-free", clean_root))
        results = {}
        for label, root in renders:
            session = tmp / f"{label.replace(' ', '_')}.h5"
            detect_samples(root, session)
            results[label] = compare(root, session)
        calibration = None
        if not args.quick:
            calibration = json.loads(
                endomeasure("calibrate", str(tmp / "default_noise.h5"), "--model", "all", "--json")
            )

    rows = []
    for label, sets in results.items():
        for set_name, r in sets.items():
            found, visible = r["halves"]
            rms = RMS_TARGETS[label]
            report.check(
                Target(f"{rms.what}, {set_name}", rms.op, rms.limit, rms.unit, rms.source),
                r["rms"], DETECTION,
            )  # fmt: skip
            report.check(
                Target(f"{WRONG_IDS_TARGET.what}, {set_name}, {label}", "==", 0, "", "issue 5"),
                r["wrong_ids"], DETECTION,
            )  # fmt: skip
            if set_name == "calib":
                report.check(CALIB_HALVES_TARGET, 100 * found / visible, DETECTION)
            rows.append(
                f"| {set_name} | {label} | {r['corners']} | {r['rms']:.3f} | {r['rms_axis']:.3f} "
                f"| {r['max']:.3f} | {r['wrong_ids']} | {found}/{visible} ({found / visible:.0%}) |"
            )
    body = f"""## Detection against the simulator's truth

Made by `bench/accuracy_detect.py`: `endomeasure detect` (default method) on the default
preset's calibration and test sets, rendered with the default noise (`sample_sessions/`,
seed 0) and noise-free (same seed, `--noise-free`), compared with the exact corner
pixels of the ground truth (ray aiming through the truth optics). RMS is over corners
of the 2-D error `|detected - true|`; per axis is that divided by sqrt(2), the figure
to compare with a calibration's per-axis residual sigma. Wrong ids: detections not
within {ID_MATCH_PX:g} px of their own id's true corner or nearer another corner.
Halves: halves where the board was found / halves that show the whole board.

| set | render | corners | RMS px | per axis px | max px | wrong ids | halves found |
|---|---|---:|---:|---:|---:|---:|---:|
{chr(10).join(rows)}

Targets (issue 5): <= 0.05 px RMS noise-free, <= 0.1 px RMS with noise, every id right,
>= 95% of calibration halves detected; this run: {"met" if not report.missed else "**missed**"}.
"""
    sections = {DETECTION: body}
    if calibration is not None:
        floor = results["default noise"]["calib"]["rms"]
        sections[CALIBRATION] = calibration_section(calibration, floor, report)
    return report.finish(sections)


TABLE_HEAD = (
    "| model | residual RMS px | ratio to the floor | corners | outliers dropped | formal floor px "
    "| scatter floor px | RMS / verdict's floor | verdict |\n"
    "|---|---:|---:|---:|---:|---:|---:|---:|---|"
)


def calibration_section(report: dict, floor: float, checks: Report) -> str:
    truth = load_manifest(SAMPLES)["truth_model"]
    truth = dict(zip(truth["param_names"], truth["params"], strict=True))
    rows = []
    for name, m in report["models"].items():
        rows.append(
            f"| {name} | {m['rms_px']:.4f} | {m['rms_px'] / floor:.2f} | {m['n_corners']} "
            f"| {m['n_outliers']} | {m['formal_floor_px']:.4f} | {m['scatter_floor_px']:.4f} "
            f"| {m['rms_ratio']:.2f} | {m['verdict']} |"
        )
    for name, why in report.get("refused", {}).items():
        rows.append(f"| {name} | refused: {why} | | | | | | | |")
    ray = report["models"].get("raytrace", {})
    check = checks.check(RESIDUAL_TARGET, ray.get("rms_px", float("nan")) / floor, CALIBRATION)
    prows = [
        f"| {p} | {v:.6g} | {ray['std'].get(p, float('nan')):.2g} | {truth[p]:.6g} "
        f"| {(v - truth[p]) / ray['std'][p]:+.1f} |"
        for p, v in ray.get("params", {}).items()
        if p in ray.get("std", {})
    ]
    return f"""## Calibration against the simulator's truth

Made by `bench/accuracy_detect.py`: `endomeasure calibrate --model all` on the detections
of the noisy sample calibration set (36 images, three boards). The noise floor is the
RMS of detected minus true corner pixels of the same images ({floor:.4f} px, section
above); RMS figures are of the 2-D residual per corner, inliers only.

{TABLE_HEAD}
{chr(10).join(rows)}

The verdict (`solvers/verdict.py`) cannot know the truth. Its floor is the larger of two
estimates: the formal floor, the RMS a correct model would leave if the detector's only
error were the pixel noise its formal covariance describes (`features/precision.py`),
and the scatter floor, from the second differences of the residuals along the boards'
rows and columns (independent per-corner errors show there, a model's smooth misfit
cancels). The formal floor misses the detector's deterministic error on these renders
(the noise-free rows of the section above); the scatter floor sees it, and its value
for the raytrace fit is the one to compare with the true floor above.

Target (issue 6): raytrace at most 1.1 x the floor; this run: {check}. The pinhole pair
cannot follow the prism's non-central, anamorphic mapping; its residual and the outliers
its fit drops are that model error (`endomeasure calibrate --plot DIR` draws the pattern).

Raytrace parameters against the truth optics (which also has k3, p1, p2 and is not in
the model's family; the deviation is in units of the predicted standard deviation):

| parameter | calibrated | std | truth | deviation / std |
|---|---:|---:|---:|---:|
{chr(10).join(prows)}
"""


if __name__ == "__main__":
    raise SystemExit(main())
