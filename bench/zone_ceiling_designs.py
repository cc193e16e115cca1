"""How many board-test zones a perfect prediction keeps within +-25 %, on the random designs.

    .venv/bin/python bench/zone_ceiling_designs.py WORK [--designs 1-40] [--reps 5]

WORK is the folder of a ``bench/accuracy_designs.py --work WORK`` run. Issue 17 asks that
the actual std of at least 90 % of the board-test zones with n >= 30 lie within +-25 % of
the predicted one. A zone's actual std is itself a sample statistic: its measurements
share corners and images, so they are fewer independent values than measurements, and
even an exact prediction misses by their sampling spread. This script measures that
ceiling on each design's own test set: the simulator's *truth* optics measure the true
corner pixels plus Gaussian noise of each (board, zone)'s true detection noise (detected
minus true, per coordinate), ``--reps`` draws, and the UT predicts with exactly that
noise (the optics are exact: no calibration or model error to predict). The fraction of
zones a perfect model and a perfect noise prediction keep within +-25 % is the most any
prediction can reach on these test sets.

Each design's figures go to ``WORK/zone_ceiling.jsonl`` as it finishes (a rerun reuses
them). Writes the "zone-ceiling" section of docs/accuracy.md unless ``--no-write``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report  # noqa: E402
from accuracy_designs import MIN_ZONE_N, _seeds, work_parser  # noqa: E402
from accuracy_report import detection_noise, perfect_reference  # noqa: E402
from endomeasure import defaults  # noqa: E402

SECTION = "zone-ceiling"
TARGET_PERCENT = 90.0  # issue 17


def design_ceiling(work: Path, seed: int, reps: int) -> dict | None:
    """Zones (n >= 30) and those within +-25 % per draw of one design, or None when the
    design has no calibrated session or test set."""
    data, session = work / f"design_{seed:03d}", work / f"design_{seed:03d}.h5"
    if not (session.is_file() and (data / "test").is_dir()):
        return None
    groups = detection_noise(session, data, defaults.ZONE_MM)["board_zones"]
    ref = perfect_reference(data, groups, defaults.ZONE_MM, reps, min_n=MIN_ZONE_N)
    return {"seed": seed, "counts": [[int(n), int(ok)] for n, ok, _ in ref["counts"]]}


def main(argv=None) -> int:
    parser = work_parser(__doc__)
    parser.add_argument("--reps", type=int, default=5, help="noise draws per design")
    args = parser.parse_args(argv)
    report = Report("bench/zone_ceiling_designs.py", args, ACCURACY)
    store = args.work / "zone_ceiling.jsonl"
    done = {}
    if store.is_file() and not args.fresh:
        for line in store.read_text().splitlines():
            row = json.loads(line)
            if len(row["counts"]) == args.reps:
                done[row["seed"]] = row
    with store.open("a") as out:
        for seed in _seeds(args.designs):
            if seed in done:
                continue
            row = design_ceiling(args.work, seed, args.reps)
            if row is None:
                continue
            out.write(json.dumps(row) + "\n")
            out.flush()
            done[seed] = row
            print(f"design {seed}: {row['counts']}", file=sys.stderr, flush=True)
    rows = [done[s] for s in sorted(done) if s in _seeds(args.designs)]
    counts = np.array([r["counts"] for r in rows])  # (designs, reps, 2)
    per_draw = 100.0 * counts[..., 1].sum(axis=0) / np.maximum(counts[..., 0].sum(axis=0), 1)
    pooled = 100.0 * counts[..., 1].sum() / max(counts[..., 0].sum(), 1)

    def mean_percent(r: dict) -> float:
        return 100.0 * sum(ok for _, ok in r["counts"]) / max(sum(n for n, _ in r["counts"]), 1)

    table = "\n".join(
        f"| {r['seed']} | {r['counts'][0][0]} | "
        + " / ".join(str(ok) for _, ok in r["counts"])
        + f" | {mean_percent(r):.0f} % |"
        for r in rows
    )
    below = sum(mean_percent(r) < TARGET_PERCENT for r in rows)
    command = (f"python bench/zone_ceiling_designs.py WORK --designs {args.designs} "
               f"--reps {args.reps}")  # fmt: skip
    body = f"""Command: `{command}` (WORK: a `bench/accuracy_designs.py` run; {len(rows)}
designs with a test set, {args.reps} noise draws each).

A perfect model and a perfect noise prediction (the truth optics on the true corner
pixels plus Gaussian noise of each board and zone's true detection noise; the UT with
exactly that noise) keep **{pooled:.1f} %** of the {int(counts[..., 0].sum() / args.reps)}
zones with n >= {MIN_ZONE_N} per draw within +-25 % of the predicted std (per draw
{", ".join(f"{v:.1f} %" for v in per_draw)}); {below} of the {len(rows)} designs stay
below {TARGET_PERCENT:g} % on average. This is the ceiling of issue 17's "at least 90 % of
the zones within +-25 %" on these test sets: what the exact prediction still misses is
the sampling spread of a zone's std over measurements that share corners and images.

| seed | zones (n >= {MIN_ZONE_N}) | within +-25 %, per draw | mean |
|---|---:|---|---:|
{table}
"""
    return report.finish({SECTION: body})


if __name__ == "__main__":
    raise SystemExit(main())
