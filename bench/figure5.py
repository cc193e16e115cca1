"""The paper's Fig. 5 (predicted against actual board-test errors) for the default preset
and for one random design, into docs/figures/ and the "figure5" section of
docs/accuracy.md.

    .venv/bin/python bench/figure5.py DEFAULT_SESSION DESIGN_SESSION [--no-write]

DEFAULT_SESSION: the session ``make demo`` builds from the sample sets
(``out/demo/demo.h5``); DESIGN_SESSION: a random design's calibrated session from
``bench/accuracy_designs.py`` (e.g. ``WORK/design_005.h5``). Each is copied, and
``predict-error --board-test`` with its defaults (each test image's measured noise, the
calibration covariance; raytrace) draws the figure; zones with n >= 30 whose actual std
is within +-25 % of the predicted one and the share of errors inside the 2-sigma band
are quoted next to it.
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report, script_parser  # noqa: E402
from _samples import endomeasure  # noqa: E402
from accuracy_designs import MIN_ZONE_N, STD_RATIO_LIMIT  # noqa: E402

SECTION = "figure5"
FIGURES = ROOT / "docs" / "figures"


def figure(session: Path, png: Path) -> dict:
    """``predict-error --board-test --plot png`` on a copy of ``session``: its report."""
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / session.name
        shutil.copy(session, copy)
        out = endomeasure("predict-error", copy, "--board-test", "--plot", png, "--json")
    return json.loads(out.stdout)


def caption(name: str, doc: dict, png: Path) -> list[str]:
    zones = [z for z in doc["zones"] if z["n"] >= MIN_ZONE_N]
    close = sum(abs(z["std_ratio"] - 1.0) <= STD_RATIO_LIMIT for z in zones)
    return [
        f"**{name}** ({doc['sigma_source']}: {doc['sigma_px']:.4f} px; zones with n >= "
        f"{MIN_ZONE_N} within +-25 %: {close} of {len(zones)}; errors inside the "
        f"predicted 2-sigma band: {100 * doc['within_band']:.1f} %)",
        "",
        f"![Fig. 5, {name}](figures/{png.name})",
        "",
    ]


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("default", type=Path, help="the session of `make demo`")
    parser.add_argument("design", type=Path, help="a random design's calibrated session")
    args = parser.parse_args(argv)
    report = Report("bench/figure5.py", args, ACCURACY)
    folder = FIGURES if not args.no_write else Path(tempfile.mkdtemp())
    folder.mkdir(parents=True, exist_ok=True)
    lines = [
        f"Made by `python bench/figure5.py {args.default} {args.design}`: "
        "`predict-error --board-test` with its defaults (raytrace, UT, each test image's "
        "measured noise, the calibration covariance); predicted mean +- std per zone (line "
        "and band) against the actual errors' mean +- std (points and bars).",
        "",
    ]
    for name, session, png in (
        ("The default preset", args.default, folder / "fig5-default.png"),
        (f"Random design {args.design.stem}", args.design, folder / f"fig5-{args.design.stem}.png"),
    ):
        lines += caption(name, figure(session, png), png)
    return report.finish({SECTION: "\n".join(lines).rstrip()})


if __name__ == "__main__":
    raise SystemExit(main())
