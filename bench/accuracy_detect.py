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

    .venv/bin/python bench/accuracy_detect.py [--no-write] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import ROOT, replace_section
from _samples import SETS, detect_samples, detection_errors
from _samples import endomeasure as run_command
from endomeasure.simulate.manifest import MANIFEST_NAME, load_manifest

ID_MATCH_PX = 1.0  # true corners are >= 5 px apart in every image of the preset
SAMPLES = ROOT / "sample_sessions"
ACCURACY_DOC = ROOT / "docs" / "accuracy.md"


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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--keep", type=Path, help="render and keep the noise-free set here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        clean_root = args.keep or tmp / "noise_free"
        if not (clean_root / MANIFEST_NAME).exists():
            seed = load_manifest(SAMPLES)["seed"]
            endomeasure("simulate", str(clean_root), "--preset", "default",
                        "--set", "calib,test", "--seed", str(seed), "--noise-free")  # fmt: skip
        results = {}
        for label, root in (("default noise", SAMPLES), ("noise-free", clean_root)):
            session = tmp / f"{label.replace(' ', '_')}.h5"
            detect_samples(root, session)
            results[label] = compare(root, session)
        calibration = json.loads(
            endomeasure("calibrate", str(tmp / "default_noise.h5"), "--model", "all", "--json")
        )

    rows = []
    for label, sets in results.items():
        for set_name, r in sets.items():
            found, visible = r["halves"]
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
>= 95% of calibration halves detected.
"""
    calib_body = calibration_section(calibration, results["default noise"]["calib"]["rms"])
    print(body)
    print(calib_body)
    if not args.no_write:
        text = ACCURACY_DOC.read_text() if ACCURACY_DOC.exists() else "# Accuracy\n"
        text = replace_section(text, "detection-simulator", body)
        ACCURACY_DOC.write_text(replace_section(text, "calibration-simulator", calib_body))
    return 0


def calibration_section(report: dict, floor: float) -> str:
    truth = load_manifest(SAMPLES)["truth_model"]
    truth = dict(zip(truth["param_names"], truth["params"], strict=True))
    rows = []
    for name, m in report["models"].items():
        rows.append(
            f"| {name} | {m['rms_px']:.4f} | {m['rms_px'] / floor:.2f} | {m['n_corners']} "
            f"| {m['n_outliers']} |"
        )
    for name, why in report.get("refused", {}).items():
        rows.append(f"| {name} | refused: {why} | | | |")
    ray = report["models"].get("raytrace", {})
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

| model | residual RMS px | ratio to the floor | corners | outliers dropped |
|---|---:|---:|---:|---:|
{chr(10).join(rows)}

Target (issue 6): raytrace at most 1.1 x the floor. The pinhole pair cannot follow the
prism's non-central, anamorphic mapping; its residual and the outliers its fit drops are
that model error (`endomeasure calibrate --plot DIR` draws the pattern).

Raytrace parameters against the truth optics (which also has k3, p1, p2 and is not in
the model's family; the deviation is in units of the predicted standard deviation):

| parameter | calibrated | std | truth | deviation / std |
|---|---:|---:|---:|---:|
{chr(10).join(prows)}
"""


if __name__ == "__main__":
    sys.exit(main())
