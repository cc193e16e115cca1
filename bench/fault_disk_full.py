"""A full disk at random moments of add-images, detect and calibrate (a small tmpfs).

    sudo .venv/bin/python bench/fault_disk_full.py [--trials 20] [--seed 0] [--no-write]

Needs root (it mounts a tmpfs of a few MB; without root it says so and exits 0 without
touching the docs). For each command and trial a fresh tmpfs holds a copy of the
command's starting session and a filler file; half of the trials leave a random amount
of free space (from none to 1.5x what the command's new session needs), the other half
start with room and let a second process fill the disk at a random moment (over 1.2x
the command's duration, so that some commands finish first). The real command line
runs on it and must either end as it does with room (the same exit code, a new session
whose checksum matches and which holds what the command adds) or exit 2 with exactly one
`error:` line and the old session byte for byte; never print a traceback or crash on a
signal; and leave no temporary file.

Trials go to ``WORK/disk_full.jsonl`` as they finish (``--rows`` that file writes the
section again without running them). Writes the "disk-full" section of
docs/robustness.md unless ``--no-write``; exits 3 when a trial broke the contract.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import Report, Target, script_parser, session_state  # noqa: E402
from _samples import endomeasure  # noqa: E402

ROBUSTNESS = ROOT / "docs" / "robustness.md"
SECTION = "disk-full"
SAMPLES = ROOT / "sample_sessions"
TARGET = Target("disk-full trials that broke the contract", "==", 0, "", "issue 18")
IMAGES = 6
"""Calibration images per board used here: enough for a pinhole calibration, few enough
that each trial takes seconds."""


def prepare(work: Path) -> dict:
    """The starting session and arguments of each command (built on the normal disk)."""
    from endomeasure.simulate.manifest import board_groups

    work.mkdir(parents=True, exist_ok=True)
    groups = [(spec, files[:IMAGES]) for spec, files in board_groups(SAMPLES, "calib")]
    spec, files = groups[0]
    half = len(files) // 2
    add_base = work / "add.h5"
    endomeasure("add-images", str(add_base), *map(str, files[:half]), "--set", "calib", check=True)
    detect_base = work / "detect.h5"
    shutil.copyfile(add_base, detect_base)
    calibrate_base = work / "calibrate.h5"
    for group_spec, group_files in groups:
        endomeasure(
            "detect", str(calibrate_base), *map(str, group_files), "--board", group_spec,
            check=True,
        )  # fmt: skip
    return {
        "add-images": (add_base, ["add-images", "{S}", *map(str, files[half:]), "--set", "calib"]),
        "detect": (detect_base, ["detect", "{S}", *map(str, files), "--board", spec]),
        "calibrate": (calibrate_base, ["calibrate", "{S}", "--model", "pinhole"]),
    }


def mount(point: Path, size: int) -> None:
    point.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(point)], check=True)


def umount(point: Path) -> None:
    subprocess.run(["umount", str(point)], check=True)


def fill(path: Path, leave: int) -> None:
    """Write a filler file until only ``leave`` bytes are free (or the disk is full)."""
    block = b"\0" * 65536
    with open(path, "ab") as filler:
        while True:
            free = shutil.disk_usage(path.parent).free - leave
            if free <= 0:
                return
            try:
                filler.write(block[: min(len(block), free)])
                filler.flush()
            except OSError:
                return


def additions(command: str):
    """What a session must hold after ``command`` completed: the model it calibrated, or
    more than the three images of the starting session."""
    if command == "calibrate":
        return lambda s: "pinhole" in s.model_names()
    return lambda s: len(s.image_names()) > 3


def trial(point: Path, command: str, base: Path, argv: list[str], rng, concurrent: bool,
          roomy: subprocess.CompletedProcess, needed: int, duration: float) -> dict:  # fmt: skip
    """One run on a tmpfs that is, or becomes, full; ``roomy`` is the same command's run
    with room (its exit code is what a completed trial must give)."""
    session = point / "s.h5"
    mount(point, 4 * base.stat().st_size + (8 << 20))
    try:
        shutil.copyfile(base, session)
        old = session.read_bytes()
        filler = point / "filler"
        row = {"command": command, "concurrent": concurrent}
        if concurrent:
            delay = float(rng.uniform(0, 1.2 * duration))  # some after the command ends
            row["fill_after_s"] = round(delay, 3)
            timer = threading.Timer(delay, fill, (filler, 0))
            timer.start()
        else:
            leave = int(rng.uniform(0, 1.5 * needed))
            row["free_bytes"] = leave
            fill(filler, leave)
        done = endomeasure(*(a.replace("{S}", str(session)) for a in argv), check=False,
                           timeout=600)  # fmt: skip
        if concurrent:
            timer.join()
        lines = done.stderr.strip().splitlines()
        row.update(
            exit=done.returncode,
            error=lines[-1] if done.returncode == 2 else "",
            one_line=len(lines) == 1 and lines[0].startswith("error:"),
            traceback="Traceback" in done.stderr or "bug" in done.stderr,
            state=session_state(session, old, additions(command)),
            temps=[p.name for p in point.iterdir() if p.name.endswith(".endomeasure-tmp")],
        )
        completed = row["state"] == "new" and row["exit"] == roomy.returncode
        refused = row["state"] == "old" and row["exit"] == 2 and row["one_line"]
        row["ok"] = (completed or refused) and not row["traceback"] and not row["temps"]
        return row
    finally:
        umount(point)


def run_trials(work: Path, trials: int, seed: int) -> list[dict]:
    """Every trial, each also appended to ``WORK/disk_full.jsonl`` as it ends."""
    commands = prepare(work / "bases")
    rng = np.random.default_rng(seed)
    point = work / "mnt"
    rows = []
    with (work / "disk_full.jsonl").open("w") as out:
        for command, (base, command_argv) in commands.items():
            # one run with room: how big its new session is and how long it takes
            probe = work / "probe.h5"
            shutil.copyfile(base, probe)
            start = time.perf_counter()
            roomy = endomeasure(*(a.replace("{S}", str(probe)) for a in command_argv), check=True)
            duration = time.perf_counter() - start
            needed = probe.stat().st_size
            for index in range(trials):
                concurrent = index % 2 == 1
                row = trial(point, command, base, command_argv, rng, concurrent, roomy, needed,
                            duration)  # fmt: skip
                out.write(json.dumps(row) + "\n")
                out.flush()
                rows.append(row)
    return rows


def main(argv=None) -> int:
    parser = script_parser(__doc__, seed=0, work=True)
    parser.add_argument("--trials", type=int, default=20, help="per command")
    parser.add_argument("--rows", type=Path, help="write the section from the trials of an "
                        "earlier run (its disk_full.jsonl) instead of running them")  # fmt: skip
    args = parser.parse_args(argv)
    if args.quick:
        args.trials = 2
    report = Report("bench/fault_disk_full.py", args, ROBUSTNESS)
    if args.rows is not None:
        rows = [json.loads(line) for line in args.rows.read_text().splitlines() if line]
    elif os.geteuid() != 0:
        print("bench/fault_disk_full.py: skipped, mounting a tmpfs needs root", file=sys.stderr)
        return 0
    else:
        work = args.work or Path(tempfile.mkdtemp(prefix="disk-full-"))
        work.mkdir(parents=True, exist_ok=True)
        rows = run_trials(work, args.trials, args.seed)
    commands = list(dict.fromkeys(r["command"] for r in rows))

    broken = sum(not r["ok"] for r in rows)
    check = report.check(TARGET, broken)
    table = ["| command | trials | new session | old session | broke the contract |",
             "|---|---:|---:|---:|---:|"]  # fmt: skip
    for command in commands:
        sub = [r for r in rows if r["command"] == command]
        table.append(
            f"| {command} | {len(sub)} | {sum(r['state'] == 'new' for r in sub)} "
            f"| {sum(r['state'] == 'old' for r in sub)} | {sum(not r['ok'] for r in sub)} |"
        )
    shapes: dict[str, list[str]] = {}
    for r in rows:
        if r["error"]:
            message = r["error"].split(" [")[0]
            shapes.setdefault(re.sub(r"\d+(\.\d+)?", "N", message), []).append(message)
    listed = "\n".join(
        f"- {len(seen)} trials: `{seen[0]}`" + (" (and the same with other figures)"
                                                 if len(set(seen)) > 1 else "")
        for seen in sorted(shapes.values(), key=len, reverse=True)
    )  # fmt: skip
    command_line = f"sudo python bench/fault_disk_full.py --trials {args.trials} --seed {args.seed}"
    body = f"""Command: `{command_line}`
({args.trials} trials per command, half with a random amount of free space, half with the
disk filled by another process at a random moment over 1.2x the command's duration).

{chr(10).join(table)}

The one-line errors seen:

{listed}

A trial keeps the contract when it ends as the same command does with room (same exit
code, new session) or refuses with one line, exit 2 and the old session byte for byte.
Trials that broke it (a crash, a traceback, another exit code, a session neither old nor
new, a temporary file left): **{broken}** (target 0, issue 18) - {check}.
"""
    return report.finish({SECTION: body})


if __name__ == "__main__":
    raise SystemExit(main())
