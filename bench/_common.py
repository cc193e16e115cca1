"""Helpers shared by the benchmark and accuracy scripts (not a script itself).

Every script in ``bench/`` has the same shape::

    TARGET = Target("what is measured", "<", 1.0, " s", "issue 7")

    def main(argv=None) -> int:
        parser = script_parser(__doc__, seed=SEED)     # --quick, --no-write, --seed
        args = parser.parse_args(argv)
        report = Report("bench/bench_x.py", args, BENCHMARKS)
        ... measure ...
        check = report.check(TARGET, seconds)          # str(check): "met" / "**missed**"
        return report.finish({"section-name": body})   # writes the doc, exit status

    if __name__ == "__main__":
        raise SystemExit(main())

``finish`` writes each section between its ``<!-- begin NAME -->`` / ``<!-- end NAME -->``
markers (unless ``--no-write`` or ``--quick``), adds a "Missed in this run" line to a
section whose target was missed, prints one line per missed target to stderr and returns
:data:`EXIT_MISSED` when one was missed (0 otherwise). ``--quick`` runs smaller sizes for
a smoke run: it never writes the docs, and its targets are reported but not enforced
(a figure from a smaller run is not the figure the target is about).
"""

from __future__ import annotations

import argparse
import operator
import platform
import re
import statistics
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "docs" / "benchmarks.md"
ACCURACY = ROOT / "docs" / "accuracy.md"

EXIT_MISSED = 3
"""Exit status of a script that ran to the end but missed a target (an exception gives 1,
a usage error 2), so ``make bench`` / ``make accuracy`` can tell the two apart."""

_OPS: dict[str, Callable[[float, float], bool]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
    "==": operator.eq,
}


@dataclass(frozen=True)
class Target:
    """A figure a script must reach: ``value OP limit``, and where it is asked for."""

    what: str
    """What is measured, e.g. "ML triangulation of 100,000 correspondences"."""
    op: str
    """One of ``<``, ``<=``, ``>``, ``>=``, ``==``."""
    limit: float
    unit: str = ""
    """Appended to the numbers as written, e.g. " s", " px", "x", " %"."""
    source: str = ""
    """The issue or spec that sets the target, e.g. "issue 7"."""

    def __post_init__(self) -> None:
        if self.op not in _OPS:
            raise ValueError(f"unknown comparison {self.op!r}; use one of {', '.join(_OPS)}")

    def met_by(self, value: float) -> bool:
        """Whether ``value`` reaches the target (NaN never does)."""
        return bool(_OPS[self.op](value, self.limit))

    def __str__(self) -> str:
        source = f" ({self.source})" if self.source else ""
        return f"{self.what} {self.op} {self.limit:g}{self.unit}{source}"


@dataclass(frozen=True)
class Check:
    """One target checked against one run's value."""

    target: Target
    value: float
    section: str | None = None
    """The docs section the figure is written to (None: every section of the report)."""

    @property
    def met(self) -> bool:
        return self.target.met_by(self.value)

    def __str__(self) -> str:
        """The verdict as it reads in a generated section: "met" or "**missed**"."""
        return "met" if self.met else "**missed**"

    def line(self) -> str:
        """One line for the terminal: verdict, target, this run's value."""
        verdict = "met" if self.met else "MISSED"
        return f"{verdict}: {self.target}; this run {self.value:.4g}{self.target.unit}"


def scene_options(parser: argparse.ArgumentParser) -> None:
    """The options of the scripts that measure scene images: the default preset's demo
    session and random designs' scene sets (``design_scenes``)."""
    parser.add_argument("--session", type=Path, default=ROOT / "out" / "demo" / "demo.h5")
    parser.add_argument("--designs", type=Path, default=None, help="random designs' WORK folder")
    parser.add_argument("--design-seeds", default="1-12", help="e.g. 1-12 or 1,5")
    parser.add_argument("--images", type=int, default=1, help="scene images per design")


def window_range(text: str) -> tuple[int, int]:
    """The dense refinement's window sides ``LO,HI`` (px) of a ``--window-range`` option."""
    lo, _, hi = text.partition(",")
    return int(lo), int(hi or lo)


def command_line(script: str, *options: tuple[str, object]) -> str:
    """``python bench/SCRIPT`` with each ``(flag, value)`` whose value is not None: the
    command a section quotes, as its run was given."""
    parts = [f"python bench/{script}"]
    parts += [f"{flag} {value}" for flag, value in options if value is not None]
    return " ".join(parts)


def parse_seeds(text: str) -> list[int]:
    """Design seeds from ``1-40``, ``1,5`` or ``1-3,7`` (ranges inclusive)."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


class DesignScenes(NamedTuple):
    """A random design's calibration and the first images of its scene set."""

    cm: object  # the calibrated ``raytrace`` model, with its misfit
    preset: object  # the design's preset (its truth optics)
    scene_seed: int  # the scene set's seed (its poses and sensor noise)
    shots: list  # the scene set's shots that have an image, in order
    images: dict  # shot name -> grey image (uint8)


def design_scenes(work: Path, seed: int, count: int) -> DesignScenes | None:
    """Design ``seed``'s calibrated session ``work/design_NNN.h5`` (from
    ``bench/accuracy_designs.py``) and the first ``count`` images of its scene set
    ``work/design_NNN_scene`` (``endomeasure simulate ... --set scene``); None without a
    usable calibration or a scene set."""
    import json

    import cv2

    from endomeasure.errors import EndomeasureError
    from endomeasure.io.session import open_session
    from endomeasure.pipeline import calibrated_model
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.scenes import plan_set

    session, folder = work / f"design_{seed:03d}.h5", work / f"design_{seed:03d}_scene"
    if not (folder / "simulation.json").exists():
        return None
    try:
        with open_session(session) as reader:
            cm = calibrated_model(reader, "raytrace", session)
    except (EndomeasureError, OSError):
        return None
    preset = load_preset(folder / "preset.json")
    scene_seed = json.loads((folder / "simulation.json").read_text())["seed"]
    shots, images = [], {}
    for shot in plan_set(preset, "scene", scene_seed)[:count]:
        image = cv2.imread(str(folder / "scene" / f"{shot.name}.png"), cv2.IMREAD_GRAYSCALE)
        if image is not None:
            shots.append(shot)
            images[shot.name] = image
    return DesignScenes(cm, preset, scene_seed, shots, images)


def calibration_dz(model, param_cov, depth_range_mm, truth) -> tuple[float, ...]:
    """A calibrated model's z error of true points at the nearest and the farthest depth
    its boards were seen at (median over a grid of the left half's field, mm), then its
    sigma of that z from ``param_cov`` (in ``model``'s ``free_mask`` order; median, mm):
    each point's true pixels in both halves (the ``truth`` optics) triangulated with the
    model, the sigma by the unscented transform, as every dense depth's calibration
    share. An error proportional to z is a scale error; one constant in mm is the model
    frame's origin set off the truth's along the axis, which no length sees."""
    import numpy as np

    from endomeasure.conventions import Half
    from endomeasure.measure.dense import _calibration_sigma
    from endomeasure.solvers.triangulate import triangulate

    split, height = model.config.split, model.config.image_size[1]
    gu, gv = np.meshgrid(np.linspace(0.1, 0.95, 12) * split, np.linspace(0.1, 0.9, 10) * height)
    left = np.stack([gu, gv], -1).reshape(-1, 2)
    rays = truth.rays(left, Half.LEFT)
    errors, sigmas = [], []
    for z in depth_range_mm or (np.nan, np.nan):
        t = (z - rays.origins[:, 2]) / rays.directions[:, 2]
        right = truth.project(rays.origins + t[:, None] * rays.directions, Half.RIGHT)
        seen = right.status == 0
        tri = triangulate(model, left[seen], right.pixels[seen])
        ok = tri.status == 0
        errors.append(float(np.median(tri.points[ok, 2] - z)) if ok.any() else np.nan)
        pairs = left[seen][ok], right.pixels[seen][ok]
        sigma = (_calibration_sigma(model, param_cov, None, *pairs)
                 if ok.any() and param_cov is not None else np.full(1, np.nan))  # fmt: skip
        sigmas.append(float(np.median(sigma)))
    return errors[0], errors[1], sigmas[0], sigmas[1]


def script_parser(
    doc: str | None, *, seed: int | None = None, work: bool = False
) -> argparse.ArgumentParser:
    """The argument parser every script starts from.

    Common options: ``--quick`` (smaller sizes, implies ``--no-write``, targets not
    enforced), ``--no-write`` (print the sections, leave the docs alone); with ``seed``,
    ``--seed`` defaulting to it; with ``work``, ``--work DIR`` (folder for sessions and
    renders, default a temporary one). The first line of ``doc`` is the description,
    the rest the help's epilog.
    """
    first, _, rest = (doc or "").strip().partition("\n")
    parser = argparse.ArgumentParser(
        description=first, epilog=rest.strip() or None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smaller sizes for a smoke run: implies --no-write, targets are not enforced",
    )
    parser.add_argument(
        "--no-write", action="store_true", help="print the results, do not update the docs"
    )
    if seed is not None:
        parser.add_argument("--seed", type=int, default=seed, help=f"random seed ({seed})")
    if work:
        parser.add_argument(
            "--work", type=Path, default=None, help="folder for sessions and renders (temp dir)"
        )
    return parser


class Report:
    """The targets one run checks, and the sections it writes."""

    def __init__(self, script: str, args: argparse.Namespace | None, doc: Path) -> None:
        self.script = script
        self.doc = Path(doc)
        self.quick = bool(getattr(args, "quick", False))
        self.write = not (self.quick or getattr(args, "no_write", False))
        self.checks: list[Check] = []

    def check(self, target: Target, value: float, section: str | None = None) -> Check:
        """Record ``value`` against ``target``; the returned check reads "met" / "**missed**"."""
        result = Check(target, float(value), section)
        self.checks.append(result)
        return result

    @property
    def missed(self) -> list[Check]:
        return [c for c in self.checks if not c.met]

    def marked(self, name: str, body: str) -> str:
        """``body`` with a line naming the targets this run missed in section ``name``."""
        missed = [c for c in self.missed if c.section in (None, name)]
        if not missed:
            return body
        lines = "; ".join(f"{c.target} (this run {c.value:.4g}{c.target.unit})" for c in missed)
        return f"{body.rstrip()}\n\n**Missed in this run:** {lines}.\n"

    def finish(self, sections: Mapping[str, str]) -> int:
        """Print (and unless told not to, write) the sections; the exit status.

        Returns :data:`EXIT_MISSED` when a target was missed, 0 otherwise (always 0 with
        ``--quick``). The docs are written before the status is returned, so a missed
        target is on record, marked as missed.
        """
        for name, body in sections.items():
            body = self.marked(name, body)
            if self.write:
                write_section(name, body, self.doc)
            else:
                print(body)
        for c in self.checks:
            print(f"{self.script}: {c.line()}", file=sys.stderr)
        if not self.missed:
            return 0
        if self.quick:
            print(f"{self.script}: --quick, targets not enforced", file=sys.stderr)
            return 0
        return EXIT_MISSED


def replace_section(text: str, name: str, body: str) -> str:
    """Replace (or append) the block between this section's begin/end markers."""
    begin, end = f"<!-- begin {name} -->", f"<!-- end {name} -->"
    block = f"{begin}\n{body.rstrip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if pattern.search(text):
        return pattern.sub(lambda _: block, text)
    return text.rstrip() + "\n\n" + block + "\n"


def write_section(name: str, body: str, doc: Path) -> None:
    """Rewrite one section of ``doc`` and echo it."""
    doc = Path(doc)
    text = doc.read_text() if doc.exists() else f"# {doc.stem.title()}\n"
    doc.write_text(replace_section(text, name, body))
    print(body)


def session_state(path: Path, old: bytes, is_new: Callable[[object], bool]) -> str:
    """What a command left of a session it edited (fault-injection scripts): ``old`` (byte
    for byte), ``new`` (its checksum matches and ``is_new(open session)`` sees the
    command's additions) or what is wrong."""
    from endomeasure.errors import SessionError
    from endomeasure.io.session import open_session

    if not path.exists():
        return "session missing"
    if path.read_bytes() == old:
        return "old"
    try:
        with open_session(path) as s:
            if s.checksum != "ok":
                return "new without checksum"
            if not is_new(s):
                return "changed without the command's additions"
    except SessionError as exc:
        return f"unreadable: {exc.what}"
    return "new"


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


def stereo_calibrate_peer(views, boards, image_size, split):
    """``cv2.stereoCalibrate`` from scratch (``flags=0``) on the corners each image shows in
    both halves, the right half in its own coordinates: the peer calibration times are
    compared with. Returns its RMS (px) and the number of corner pairs."""
    import cv2
    import numpy as np

    objp, ql, qr = [], [], []
    for v in views:
        common = np.intersect1d(v.ids[0], v.ids[1])
        if common.size < 6:
            continue
        il = np.searchsorted(v.ids[0], common, sorter=np.argsort(v.ids[0]))
        ir = np.searchsorted(v.ids[1], common, sorter=np.argsort(v.ids[1]))
        il = np.argsort(v.ids[0])[il]
        ir = np.argsort(v.ids[1])[ir]
        objp.append(boards[v.board][common].astype(np.float32))
        ql.append(v.pixels[0][il].astype(np.float32))
        qr.append((v.pixels[1][ir] - [split, 0.0]).astype(np.float32))
    size = (max(split, image_size[0] - split), image_size[1])
    rms = cv2.stereoCalibrate(objp, ql, qr, None, None, None, None, size, flags=0)[0]
    return float(rms), sum(len(o) for o in objp)
