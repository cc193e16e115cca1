"""Start-up time of ``endomeasure --help``, against a bare Python start in the same run.

    .venv/bin/python bench/bench_cli.py [--quick] [--no-write]

Writes the ``cli-startup`` section of docs/benchmarks.md (``make bench`` runs it).
Target (issue 2): ``endomeasure --help`` under 300 ms.
"""

from __future__ import annotations

import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _common import BENCHMARKS, Report, Target, script_parser

RUNS = 15
QUICK_RUNS = 3
SECTION = "cli-startup"
HELP_TARGET = Target("`endomeasure --help` start-up", "<", 300.0, " ms", "issue 2")


def wall_times(argv: list[str], runs: int = RUNS) -> list[float]:
    subprocess.run(argv, capture_output=True, check=True)  # warm the file cache
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(argv, capture_output=True, check=True)
        times.append(time.perf_counter() - start)
    return times


def main(argv: list[str] | None = None) -> int:
    args = script_parser(__doc__).parse_args(argv)
    report = Report("bench/bench_cli.py", args, BENCHMARKS)
    runs = QUICK_RUNS if args.quick else RUNS
    script = shutil.which("endomeasure", path=str(Path(sys.executable).parent))
    help_argv = [script, "--help"] if script else [sys.executable, "-m", "endomeasure", "--help"]
    bare = statistics.median(wall_times([sys.executable, "-c", "pass"], runs))
    numpy = statistics.median(wall_times([sys.executable, "-c", "import numpy"], runs))
    help_ = statistics.median(wall_times(help_argv, runs))
    check = report.check(HELP_TARGET, help_ * 1e3)
    body = f"""## `endomeasure --help` start-up

Median wall time of {runs} runs each, measured by `bench/bench_cli.py` in one run
(Python {platform.python_version()}, {platform.machine()}). The help must come back fast, so
heavy imports (numpy, cv2, scipy, h5py, matplotlib) happen inside the commands;
`tests/test_architecture.py` checks that importing the CLI loads none of them.

| what | median wall time | ratio to bare Python |
|---|---:|---:|
| `python -c pass` (peer) | {bare * 1e3:.0f} ms | 1.0 |
| `python -c "import numpy"` (for scale) | {numpy * 1e3:.0f} ms | {numpy / bare:.1f} |
| `endomeasure --help` | {help_ * 1e3:.0f} ms | {help_ / bare:.1f} |

Target: under {HELP_TARGET.limit:g} ms ({HELP_TARGET.source}); this run: {check}.
"""
    return report.finish({SECTION: body})


if __name__ == "__main__":
    raise SystemExit(main())
