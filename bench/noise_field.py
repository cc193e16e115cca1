"""How the detection noise of the test set varies over the image (issue 8 diagnosis).

    python bench/noise_field.py WORK [--max-mm 30]

WORK is the folder of a ``bench/accuracy_report.py --work WORK`` run (its session
``accuracy.h5`` and, with ``--test-seeds``, its merged set ``data/``; otherwise
``sample_sessions/``). For each board, over the test images nearer than ``--max-mm``,
prints the standard deviation of the disparity error (left minus right u error against
the simulator's true corners) and of the v error in thirds of the corners sorted by their
distance from the image's middle row and from the left half's middle column. A noise
that is the same everywhere gives the same figures in every third.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _samples import detection_errors  # noqa: E402
from endomeasure.simulate.manifest import load_manifest, load_truth  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--max-mm", type=float, default=30.0)
    args = ap.parse_args()
    data = args.work / "data" if (args.work / "data").exists() else ROOT / "sample_sessions"
    manifest = load_manifest(data)
    width, height = manifest["image_size"]
    centre = np.array([manifest["split"] / 2.0, (height - 1) / 2.0])
    by_image: dict[str, dict] = {}
    for h in detection_errors(data, args.work / "accuracy.h5", sets=("test",)):
        if h.found:
            by_image.setdefault(h.image, {})[h.half] = h
    rows: dict[str, list] = {}
    own_uv: dict[tuple[str, str], list] = {}
    pairs: dict[tuple[str, str], list] = {}
    for image, halves in by_image.items():
        truth = load_truth(data, image)
        if len(halves) < 2 or truth["distance_mm"] >= args.max_mm:
            continue
        board = truth["board_spec"]
        left, right = halves["left"], halves["right"]
        for h in (left, right):
            own_uv.setdefault((board, h.half), []).append(h.errors)
        right_errors = {int(i): e for i, e in zip(right.ids, right.errors, strict=True)}
        disparity, v_error = {}, {}
        for i, e, p in zip(left.ids, left.errors, left.detected, strict=True):
            if int(i) in right_errors:
                disparity[int(i)] = e[0] - right_errors[int(i)][0]
                v_error[int(i)] = e[1]
                rows.setdefault(board, []).append((*np.abs(p - centre), disparity[int(i)], e[1]))
        for i in disparity:
            right_of = -1 if (i % left.cols) + 1 == left.cols else i + 1
            for name, j in (("horizontal", right_of), ("vertical", i + left.cols)):
                if j in disparity:
                    pairs.setdefault((board, name), []).append(
                        (v_error[i], v_error[j], disparity[i], disparity[j])
                    )
    for board, values in sorted(rows.items()):
        r = finite(values)
        for column, name in ((1, "middle row"), (0, "middle column")):
            edges = np.quantile(r[:, column], [0, 1 / 3, 2 / 3, 1])
            parts = []
            for k in range(3):
                inside = (r[:, column] >= edges[k]) & (r[:, column] <= edges[k + 1])
                parts.append(
                    f"{edges[k]:.0f}-{edges[k + 1]:.0f} px: disparity {r[inside, 2].std():.4f}, "
                    f"v {r[inside, 3].std():.4f}"
                )
            print(f"{board}, < {args.max_mm:g} mm, distance from the {name}: " + " | ".join(parts))
    for (board, half), errors in sorted(own_uv.items()):
        e = finite(np.concatenate(errors))
        print(f"{board}, {half} half: correlation of a corner's u and v errors {corr(e, 0, 1)}")
    for (board, name), values in sorted(pairs.items()):
        r = finite(values)
        print(
            f"{board}, {name} neighbours: correlation of v errors {corr(r, 0, 1)}, "
            f"of disparity errors {corr(r, 2, 3)}"
        )


def finite(values) -> np.ndarray:
    r = np.asarray(values, dtype=np.float64)
    return r[np.all(np.isfinite(r), axis=1)]


def corr(r: np.ndarray, a: int, b: int) -> str:
    return f"{np.corrcoef(r[:, a], r[:, b])[0, 1]:+.2f}"


if __name__ == "__main__":
    main()
