"""Start-up time of ``endomeasure --help``, against a bare Python start in the same run.

Writes the ``cli-startup`` section of docs/benchmarks.md. Run with ``make bench`` or
``.venv/bin/python bench/bench_cli.py``.
"""

from __future__ import annotations

import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _common import write_section

RUNS = 15
TARGET_S = 0.3
SECTION = "cli-startup"


def wall_times(argv: list[str], runs: int = RUNS) -> list[float]:
    subprocess.run(argv, capture_output=True, check=True)  # warm the file cache
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(argv, capture_output=True, check=True)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    script = shutil.which("endomeasure", path=str(Path(sys.executable).parent))
    help_argv = [script, "--help"] if script else [sys.executable, "-m", "endomeasure", "--help"]
    bare = statistics.median(wall_times([sys.executable, "-c", "pass"]))
    numpy = statistics.median(wall_times([sys.executable, "-c", "import numpy"]))
    help_ = statistics.median(wall_times(help_argv))
    verdict = "meets" if help_ < TARGET_S else "MISSES"
    body = f"""## `endomeasure --help` start-up

Median wall time of {RUNS} runs each, measured by `bench/bench_cli.py` in one run
(Python {platform.python_version()}, {platform.machine()}). The help must come back fast, so
heavy imports (numpy, cv2, scipy, h5py, matplotlib) happen inside the commands;
`tests/test_architecture.py` checks that importing the CLI loads none of them.

| what | median wall time | ratio to bare Python |
|---|---:|---:|
| `python -c pass` (peer) | {bare * 1e3:.0f} ms | 1.0 |
| `python -c "import numpy"` (for scale) | {numpy * 1e3:.0f} ms | {numpy / bare:.1f} |
| `endomeasure --help` | {help_ * 1e3:.0f} ms | {help_ / bare:.1f} |

Target: under {TARGET_S * 1e3:.0f} ms; this run {verdict} it.
"""
    write_section(SECTION, body)


if __name__ == "__main__":
    main()
