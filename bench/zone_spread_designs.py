"""How often a zone's sample std lands within +-25 % of its true value, on the random designs.

    .venv/bin/python bench/zone_spread_designs.py WORK [--designs 1-40] [--draws 40]

WORK is the folder of a ``bench/accuracy_designs.py --work WORK`` run. Issue 17 asks the
actual std of at least 90 % of the board-test zones with n >= 30 to lie within +-25 % of
the predicted one. A zone's actual std is a sample statistic, and how far it scatters
about the truth depends on the error distribution: where the depth noise is a sizeable
fraction of a segment (far zones of a small-baseline probe), a length error holds a
squared term of the depth difference of its ends and is heavy-tailed, and segments that
share corners are few independent values. This script measures that scatter with the
prediction exact by construction, on each design's own test set and calibration:

1. the calibrated raytrace model is taken as the optics (it is the prediction's model;
   the truth's other effects do not matter to a sampling spread): the true corner pixels
   are triangulated with it and projected back, so that the model holds exactly;
2. ``--draws`` times, each test image half gets Gaussian noise of the standard deviation
   that ``predict-error`` measures on it by default (per coordinate), and the board test
   runs on the noisy pixels;
3. per zone (n >= 30), the true std of its errors is their std over all draws and
   measurements (about their common mean: a draw's sample std sees the spread of the
   measurements' own biases too); each draw's sample std is compared with it.

The fraction of (zone, draw) pairs within +-25 % is the most any prediction can reach on
these test sets; per zone, the excess kurtosis of its errors shows the heavy tails.
Each design's figures go to ``WORK/zone_spread.jsonl`` as it finishes (a rerun reuses
them). Writes the "zone-spread" section of docs/accuracy.md unless ``--no-write``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report, parse_seeds  # noqa: E402
from _samples import truth_board_sets  # noqa: E402
from accuracy_designs import MIN_ZONE_N, STD_RATIO_LIMIT, work_parser  # noqa: E402
from endomeasure import defaults  # noqa: E402
from endomeasure.simulate.manifest import load_truth  # noqa: E402

SECTION = "zone-spread"
TARGET_PERCENT = 90.0  # issue 17


def _consistent_pixels(model, left, right):
    """The true corner pixels moved onto the model: triangulated, projected back."""
    from endomeasure.solvers.triangulate import triangulate

    points = triangulate(model, left, right).points
    return model.project(points, "left").pixels, model.project(points, "right").pixels


def design_spread(work: Path, seed: int, draws: int) -> dict | None:
    """Per zone with n >= 30: the true std, each draw's sample std and the pooled excess
    kurtosis of the errors; None without a calibrated session and test set."""
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.io.records import BOARD_TEST_RECORD, board_test_fields
    from endomeasure.io.session import open_session
    from endomeasure.measure.board_runs import ModelBoardTest, run_board_test, test_image_noise
    from endomeasure.pipeline import calibrated_model

    data, session = work / f"design_{seed:03d}", work / f"design_{seed:03d}.h5"
    if not (session.is_file() and (data / "test").is_dir()):
        return None
    with open_session(session) as s:
        if "raytrace" not in s.record_names(BOARD_TEST_RECORD):
            return None
        model = calibrated_model(s, "raytrace", session, allow_failed=True).model
        stored = ModelBoardTest.from_fields(board_test_fields(s.record(BOARD_TEST_RECORD,
                                                                       "raytrace")))  # fmt: skip
    grids = {b: np.asarray(parse_board_spec(b).object_points) for b in dict.fromkeys(stored.board)}
    noise = test_image_noise(stored, model, grids)
    sigma = {image: noise.std[k] for k, image in enumerate(stored.images)}  # uL vL uR vR
    images = []
    for image in stored.images:
        t = load_truth(data, image)
        px = t["corners"]["pixels"]
        left, right = _consistent_pixels(model, np.asarray(px["left"], float),
                                         np.asarray(px["right"], float))  # fmt: skip
        images.append((image, t, left, right))
    rng = np.random.default_rng(seed)
    errors = []  # per draw: the board test's table errors
    keys = None
    for _ in range(draws):
        noisy = []
        for image, t, left, right in images:
            s4 = sigma[image]
            noisy.append((image, t, left + rng.normal(0.0, 1.0, left.shape) * s4[:2],
                          right + rng.normal(0.0, 1.0, right.shape) * s4[2:]))  # fmt: skip
        bt = run_board_test("raytrace", model, truth_board_sets(noisy), defaults.ZONE_MM)
        table = bt.table
        errors.append(np.asarray(table.error, dtype=float))
        if keys is None:
            from endomeasure.measure.board_test import zone_bounds, zone_index

            starts = np.array([zone_bounds(zone_index(z, defaults.ZONE_MM), defaults.ZONE_MM)[0]
                               if np.isfinite(z) else np.nan for z in table.z_mean])  # fmt: skip
            board = np.array([bt.board[i] for i in table.image])
            keys = list(zip(board, np.asarray(table.kind).astype(str), starts, strict=True))
    e = np.array(errors)  # (draws, rows)
    zones = []
    for key in sorted(set(k for k in keys if np.isfinite(k[2]))):
        sel = np.array([k == key for k in keys])
        x = e[:, sel]
        x = x[:, np.all(np.isfinite(x), axis=0)]
        if x.shape[1] < MIN_ZONE_N:
            continue
        # the zone's population: every measurement's errors over all draws, about their
        # common mean (what a draw's sample std estimates: the measurements' own biases
        # differ, and their spread is part of it)
        centred = x - x.mean()
        true_std = float(np.sqrt(np.mean(centred**2)))
        samples = x.std(axis=1, ddof=1)  # each draw's zone std (as the board test takes it)
        kurt = float(np.mean(centred**4) / np.mean(centred**2) ** 2 - 3.0)
        zones.append({"board": key[0], "kind": key[1], "zone_start": float(key[2]),
                      "n": int(x.shape[1]), "true_std": true_std,
                      "ratios": (samples / true_std).tolist(), "kurtosis": kurt})  # fmt: skip
    return {"seed": seed, "draws": draws, "zones": zones}


def main(argv=None) -> int:
    parser = work_parser(__doc__)
    parser.add_argument("--draws", type=int, default=40, help="noise draws per design")
    args = parser.parse_args(argv)
    report = Report("bench/zone_spread_designs.py", args, ACCURACY)
    store = args.work / "zone_spread.jsonl"
    done = {}
    if store.is_file() and not args.fresh:
        for line in store.read_text().splitlines():
            row = json.loads(line)
            if row["draws"] == args.draws:
                done[row["seed"]] = row
    seeds = parse_seeds(args.designs)
    with store.open("a") as out:
        for seed in seeds:
            if seed in done:
                continue
            row = design_spread(args.work, seed, args.draws)
            if row is None:
                continue
            out.write(json.dumps(row) + "\n")
            out.flush()
            done[seed] = row
            inside = [np.mean(np.abs(np.array(z["ratios"]) - 1) <= STD_RATIO_LIMIT)
                      for z in row["zones"]]  # fmt: skip
            share = f"{100 * np.mean(inside):.1f} % within" if inside else "none to judge"
            print(f"design {seed}: {len(inside)} zones, {share}", file=sys.stderr, flush=True)
    rows = [done[s] for s in seeds if s in done]
    zones = [z for r in rows for z in r["zones"]]
    within = np.array([np.mean(np.abs(np.array(z["ratios"]) - 1) <= STD_RATIO_LIMIT)
                       for z in zones])  # fmt: skip
    kurt = np.array([z["kurtosis"] for z in zones])
    kinds = sorted({z["kind"] for z in zones})
    by_kind = "\n".join(
        f"| {k} | {sum(z['kind'] == k for z in zones)} | "
        f"{100 * np.mean(within[[z['kind'] == k for z in zones]]):.1f} % | "
        f"{np.median(kurt[[z['kind'] == k for z in zones]]):+.2f} |"
        for k in kinds
    )
    heavy = kurt > 1.0
    command = (
        f"python bench/zone_spread_designs.py WORK --designs {args.designs} --draws {args.draws}"
    )
    body = f"""Command: `{command}`
(WORK: a `bench/accuracy_designs.py` run; {len(rows)} designs with a test set, {len(zones)}
zones with n >= {MIN_ZONE_N}).

With the prediction exact by construction (the calibrated model as the optics, each test
image half's default noise as the truth), a zone's sample std lands within +-25 % of its
true std in **{100 * within.mean():.1f} %** of the (zone, draw) pairs (issue 17's target for
the actual against the predicted std: {TARGET_PERCENT:g} %). Zones whose errors are
heavy-tailed (excess kurtosis > 1: {int(heavy.sum())} of {len(zones)}) reach
{100 * within[heavy].mean() if heavy.any() else float("nan"):.1f} %, the others
{100 * within[~heavy].mean() if (~heavy).any() else float("nan"):.1f} %.

| kind | zones | within +-25 % | median excess kurtosis |
|---|---:|---:|---:|
{by_kind}
"""
    return report.finish({SECTION: body})


if __name__ == "__main__":
    raise SystemExit(main())
