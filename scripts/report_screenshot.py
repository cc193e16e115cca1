"""The screenshot of the demo's calibration report in ``docs/report.md``.

    python scripts/report_screenshot.py [REPORT] [PNG]

Defaults: ``out/demo/report.html`` (written by ``make demo``) and
``docs/report-screenshot.png``. Needs Chromium (``apt-get install chromium``); the page
is rendered headless at 1200 px wide and its top 2400 px are kept.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def main() -> int:
    report = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "out" / "demo" / "report.html"
    png = Path(sys.argv[2]) if len(sys.argv) > 2 else ROOT / "docs" / "report-screenshot.png"
    browser = next((b for b in map(shutil.which, BROWSERS) if b), None)
    if browser is None:
        print("report_screenshot.py: no Chromium found (apt-get install chromium)", file=sys.stderr)
        return 2
    if not report.is_file():
        print(f"report_screenshot.py: {report} does not exist; run `make demo`", file=sys.stderr)
        return 2
    done = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
         "--window-size=1200,2400", f"--screenshot={png.resolve()}", report.resolve().as_uri()],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    if done.returncode != 0 or not png.is_file():
        why = done.stderr.strip()[-300:]
        print(f"report_screenshot.py: Chromium failed: {why}", file=sys.stderr)
        return 1
    print(f"{png} written from {report}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
