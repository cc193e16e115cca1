"""Helpers shared by the benchmark scripts (not a benchmark itself)."""

from __future__ import annotations

import platform
import re
import statistics
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"


def replace_section(text: str, name: str, body: str) -> str:
    """Replace (or append) the block between this section's begin/end markers."""
    begin, end = f"<!-- begin {name} -->", f"<!-- end {name} -->"
    block = f"{begin}\n{body.rstrip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if pattern.search(text):
        return pattern.sub(lambda _: block, text)
    return text.rstrip() + "\n\n" + block + "\n"


def write_section(name: str, body: str) -> None:
    """Rewrite one section of docs/benchmarks.md and echo it."""
    text = DOC.read_text() if DOC.exists() else "# Benchmarks\n"
    DOC.write_text(replace_section(text, name, body))
    print(body)


def median_time(fn: Callable[[], object], runs: int = 5) -> float:
    """Median wall time of ``fn()`` over ``runs`` calls after one warm-up call, s."""
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def machine() -> str:
    return f"Python {platform.python_version()}, {platform.machine()}"
