"""Huge images refused before the work: how fast, and in how much memory.

    python bench/fault_limits.py [--runs 5] [--work DIR] [--no-write]

A grey PNG whose header declares 30000 x 30000 pixels (a few kB of file) given to
``add-images`` and to ``detect``, and a session crafted with h5py whose scene image is
declared 64000 x 48000 (its checksum matches, as a knowledgeable forger would make it)
given to ``measure``. Each command line runs ``--runs`` times in a fresh process; the
wall time (from the process's start, interpreter and imports included) and the peak
resident memory of each run are measured. Every run must be refused with exit 2, one
``error:`` line naming the limit (``detect``'s per-image table above it) and no
traceback. Writes the "limits" section of docs/robustness.md.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import Report, Target, script_parser  # noqa: E402

sys.path.insert(0, str(ROOT))  # for the tests' hostile files
from tests.hostile_data import crafted, png_header_only, replace_image, run_measured  # noqa: E402

ROBUSTNESS = ROOT / "docs" / "robustness.md"
TIME = Target("slowest refusal of a huge image", "<", 1.0, " s", "issue 18")
MEMORY = Target("largest peak memory of a refusal", "<", 300.0, " MB", "issue 18")


def world(work: Path) -> dict[str, list[str]]:
    """The command lines, with the files they are given."""
    from tests.pipeline.measure_data import BOARD, build_session

    big = work / "big"
    big.mkdir(parents=True, exist_ok=True)
    png_header_only(big / "huge.png", 30000, 30000)
    session, _ = build_session(work / "s.h5")
    huge = crafted(session, work / "huge-image.h5",
                   lambda h5: replace_image(h5, "scene", (48000, 64000), "u1"))  # fmt: skip
    return {
        "add-images, 30000x30000 PNG": ["add-images", str(work / "new.h5"), str(big)],
        "detect, 30000x30000 PNG": ["detect", str(work / "new.h5"), str(big), "--board", BOARD],
        "measure, session image 64000x48000": [
            "measure", str(huge), "--image", "scene", "--left", "300,240", "--left", "310,240",
        ],
    }  # fmt: skip


def main(argv=None) -> int:
    parser = script_parser(__doc__, work=True)
    parser.add_argument("--runs", type=int, default=5, help="runs per command line")
    args = parser.parse_args(argv)
    if args.quick:
        args.runs = 1
    report = Report("bench/fault_limits.py", args, ROBUSTNESS)
    work = args.work or Path(tempfile.mkdtemp(prefix="limits-"))
    rows, wrong = [], []
    for label, argv_ in world(work).items():
        seconds, peaks = [], []
        for _ in range(args.runs):
            start = time.perf_counter()
            done, peak_mb = run_measured(*argv_)
            seconds.append(time.perf_counter() - start)
            peaks.append(peak_mb)
            errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
            refused = len(errors) == 1 and "beyond the limit" in errors[0]
            if done.returncode != 2 or not refused or "Traceback" in done.stderr:
                wrong.append(f"{label}: exit {done.returncode}, {done.stderr.strip()[-200:]}")
        rows.append((label, np.median(seconds), max(seconds), max(peaks), errors[-1]))
    slowest = max(r[2] for r in rows)
    largest = max(r[3] for r in rows)
    time_check = report.check(TIME, slowest)
    memory_check = report.check(MEMORY, largest)
    table = "\n".join(
        f"| {label} | {median:.2f} | {worst:.2f} | {peak:.0f} |"
        for label, median, worst, peak, _ in rows
    )
    lines_seen = "\n".join(f"- `{line}`" for *_, line in rows)
    failures = "".join(f"\n- not refused as it should be: {w}" for w in wrong)
    body = f"""Command: `python bench/fault_limits.py --runs {args.runs}`
(each command line {args.runs} times in a fresh process; time from the process's start,
the interpreter and its imports included, to its exit).

| command and input | median s | slowest s | peak memory MB |
|---|---:|---:|---:|
{table}

The lines:

{lines_seen}

Slowest refusal {slowest:.2f} s (target under 1 s) - {time_check}; largest peak memory
{largest:.0f} MB (target under 300 MB) - {memory_check}.{failures}
"""
    code = report.finish({"limits": body})
    return code if not wrong else max(code, 3)


if __name__ == "__main__":
    raise SystemExit(main())
