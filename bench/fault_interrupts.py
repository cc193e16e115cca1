"""Ctrl-C (and SIGTERM) at random moments of add-images, detect --workers 2 and calibrate.

    python bench/fault_interrupts.py [--trials 50] [--sigterm 10] [--seed 0] [--work DIR]

Each command first runs once uninterrupted (its duration D and its new session). Then,
per trial, a fresh copy of the command's starting session, the real command line in a
process group of its own (as a terminal's foreground job), and after a seeded random
delay in [0, D) the signal: SIGINT to the whole group, as Ctrl-C sends it (``--trials``
per command), or SIGTERM to the command's process only, as ``kill`` sends it
(``--sigterm`` per command). Stderr is not a terminal, so no progress bar is drawn.

The contract for an interrupted command: exit 130 (SIGINT) or 143 (SIGTERM); exactly one
``error: interrupted ...`` line, the last on stderr, no traceback; the session as it was
byte for byte, or the new one (checksum ok, holding what the command adds); no temporary
file beside it; no process of its group alive 2 s after it ended. A command that had
already finished when the signal came exits as its uninterrupted run did (0 or 1), within
0.5 s of the signal, with the new session: anything later is a swallowed interrupt.

Trials go to ``WORK/interrupts.jsonl`` as they finish; the counts per outcome go to
stdout and to the "interrupts" section of docs/robustness.md (unless ``--no-write``);
exits 3 when a trial broke the contract.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import Report, Target, script_parser, session_state  # noqa: E402
from _samples import endomeasure as run_endomeasure  # noqa: E402

sys.path.insert(0, str(ROOT))  # for tests.processes
from tests.processes import alive_in_group  # noqa: E402

ROBUSTNESS = ROOT / "docs" / "robustness.md"
SECTION = "interrupts"
SAMPLES = ROOT / "sample_sessions" / "calib"
BOARD = "chessboard:8x6:0.5"
"""The board of the sample calibration images calib_000 ... calib_011."""
BOARD_IMAGES = 12
ADD_IMAGES = 24
TARGET = Target("interrupt trials that broke the contract", "==", 0, "", "issue 18")
FINISHED_WITHIN_S = 0.5
"""A command that exits 0/1 later than this after the signal went on working: swallowed."""
GROUP_GONE_S = 2.0
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
"""The commands run this checkout's code, whichever one the environment has installed."""
TMP_SUFFIX = ".endomeasure-tmp"


def endomeasure(*args: str, check: bool = False) -> subprocess.CompletedProcess:
    """The command line of this checkout (``ENV``), as :func:`_samples.endomeasure` runs it."""
    return run_endomeasure(*args, check=check, timeout=900, env=ENV)


def prepare(work: Path) -> dict:
    """Per command: its starting session, its arguments, and what its new session holds."""
    work.mkdir(parents=True, exist_ok=True)
    images, board_images = work / "images", work / "board"
    for folder, count in ((images, ADD_IMAGES), (board_images, BOARD_IMAGES)):
        folder.mkdir(exist_ok=True)
        for i in range(count):
            shutil.copyfile(SAMPLES / f"calib_{i:03d}.png", folder / f"calib_{i:03d}.png")
    first = work / "first"
    first.mkdir(exist_ok=True)
    shutil.copyfile(images / "calib_000.png", first / "calib_000.png")
    add_base = work / "add.h5"
    endomeasure("add-images", str(add_base), str(first), check=True)
    detect_base = work / "detect.h5"
    endomeasure("add-images", str(detect_base), str(board_images), check=True)
    calibrate_base = work / "calibrate.h5"
    shutil.copyfile(detect_base, calibrate_base)
    endomeasure("detect", str(calibrate_base), str(board_images), "--board", BOARD,
                "--workers", "2", check=True)  # fmt: skip

    def added(s) -> bool:
        return len(s.image_names()) == ADD_IMAGES

    def detected(s) -> bool:
        return bool(s.detections())

    def calibrated(s) -> bool:
        return bool(s.model_names())

    return {
        "add-images": (add_base, ["add-images", "{S}", str(images)], added),
        "detect": (
            detect_base,
            ["detect", "{S}", str(board_images), "--board", BOARD, "--workers", "2"],
            detected,
        ),
        "calibrate": (calibrate_base, ["calibrate", "{S}"], calibrated),
    }


SIGTERM_BIT = 1 << (signal.SIGTERM - 1)


def wait_until_handled(proc: subprocess.Popen) -> float | None:
    """The moment the command's process catches SIGTERM (``SigCgt`` in /proc/PID/status):
    endomeasure installs its SIGINT and SIGTERM handlers together, as its first step.
    Before, the interpreter is still starting (tens of ms) and a signal ends it by its
    default action, before any code of endomeasure ran. None if the process ended first."""
    while proc.poll() is None:
        try:
            status = Path(f"/proc/{proc.pid}/status").read_text()
        except OSError:
            return None
        caught = int(next(x for x in status.splitlines() if x.startswith("SigCgt:")).split()[1], 16)
        if caught & SIGTERM_BIT:
            return time.monotonic()
        time.sleep(0.001)
    return None


def trial(work: Path, base: Path, argv: list[str], is_new, signum: int, delay: float,
          finished_code: int) -> dict:  # fmt: skip
    """One run with one signal; the row of what happened."""
    folder = Path(tempfile.mkdtemp(prefix="trial-", dir=work))
    session = folder / "s.h5"
    shutil.copyfile(base, session)
    old = session.read_bytes()
    proc = subprocess.Popen(
        [sys.executable, "-m", "endomeasure", *(a.replace("{S}", str(session)) for a in argv)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
        start_new_session=True,
    )  # fmt: skip
    started = time.monotonic()
    handled_at = wait_until_handled(proc)
    time.sleep(max(0.0, delay - (time.monotonic() - started)))
    sent = time.monotonic()
    try:
        if signum == signal.SIGINT:
            os.killpg(proc.pid, signum)  # Ctrl-C: the whole foreground group
        else:
            os.kill(proc.pid, signum)  # kill PID: the command only
        delivered = True
    except ProcessLookupError:
        delivered = False
    out, err = proc.communicate(timeout=900)
    after = time.monotonic() - sent
    deadline = time.monotonic() + GROUP_GONE_S
    while (orphans := alive_in_group(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.02)
    lines = err.splitlines()
    errors = [line for line in lines if line.startswith("error:")]
    row = {
        "signal": signal.Signals(signum).name,
        "delay_s": round(delay, 3),
        "handlers_after_s": None if handled_at is None else round(handled_at - started, 3),
        "moved_to_handlers": handled_at is not None and handled_at - started > delay,
        "delivered": delivered,
        "exit": proc.returncode,
        "after_signal_s": round(after, 3),
        "error_lines": errors,
        "last_line": lines[-1] if lines else "",
        "traceback": "Traceback" in err or "bug" in err,
        "state": session_state(session, old, is_new),
        "temps": sorted(p.name for p in folder.iterdir() if p.name.endswith(TMP_SUFFIX)),
        "orphans": orphans,
        "stderr_tail": err[-1500:],
        "stdout_tail": out[-500:],
    }
    row["outcome"] = outcome(row, signum, finished_code)
    row["ok"] = not row["outcome"].startswith("broke")
    shutil.rmtree(folder, ignore_errors=True)
    return row


def outcome(row: dict, signum: int, finished_code: int) -> str:
    """The class of a trial: 'interrupted, old session', 'interrupted, new session',
    'finished before the signal', or 'broke the contract: why'."""
    problems = []
    if row["traceback"]:
        problems.append("traceback")
    if row["stdout_tail"]:
        problems.append("output on stdout")
    if row["temps"]:
        problems.append("temporary file left")
    if row["orphans"]:
        problems.append("processes left")
    if row["state"] not in ("old", "new"):
        problems.append(f"session: {row['state']}")
    code = row["exit"]
    if code == 128 + signum:
        if len(row["error_lines"]) != 1 or row["last_line"] != row["error_lines"][0]:
            problems.append("not exactly one error line, last")
        elif not row["error_lines"][0].startswith("error: interrupted by "):
            problems.append("another message than interrupted")
        kind = f"interrupted, {row['state']} session"
    elif code == finished_code:
        if row["state"] != "new":
            problems.append("finished without the new session")
        if row["delivered"] and row["after_signal_s"] > FINISHED_WITHIN_S:
            problems.append("the interrupt was swallowed: the command went on")
        kind = "finished before the signal"
    else:
        problems.append(f"exit {code}")
        kind = ""
    return f"broke the contract: {', '.join(problems)}" if problems else kind


def main(argv=None) -> int:
    parser = script_parser(__doc__, seed=0, work=True)
    parser.add_argument("--trials", type=int, default=50, help="Ctrl-C trials per command")
    parser.add_argument("--sigterm", type=int, default=10, help="SIGTERM trials per command")
    args = parser.parse_args(argv)
    if args.quick:
        args.trials, args.sigterm = 3, 1
    if not Path("/proc/self/stat").exists():
        print("bench/fault_interrupts.py: skipped, needs /proc", file=sys.stderr)
        return 0
    report = Report("bench/fault_interrupts.py", args, ROBUSTNESS)
    # started in the background by a shell (`make ... &`, nohup), this process and its
    # children would ignore SIGINT, as POSIX asks: the commands must see it as at a terminal
    signal.signal(signal.SIGINT, signal.default_int_handler)
    work = args.work or Path(tempfile.mkdtemp(prefix="interrupts-"))
    work.mkdir(parents=True, exist_ok=True)
    commands = prepare(work / "bases")
    rng = np.random.default_rng(args.seed)
    rows = []
    durations = {}
    with (work / "interrupts.jsonl").open("w") as out:
        for command, (base, command_argv, is_new) in commands.items():
            probe = work / "probe.h5"
            shutil.copyfile(base, probe)
            start = time.perf_counter()
            done = endomeasure(*(a.replace("{S}", str(probe)) for a in command_argv), check=True)
            durations[command] = duration = time.perf_counter() - start
            signals = [signal.SIGINT] * args.trials + [signal.SIGTERM] * args.sigterm
            for signum in signals:
                delay = float(rng.uniform(0.0, duration))
                row = {"command": command, **trial(work, base, command_argv, is_new, signum,
                                                   delay, done.returncode)}  # fmt: skip
                out.write(json.dumps(row) + "\n")
                out.flush()
                rows.append(row)
                print(f"{command} {row['signal']} at {delay:.2f} s: {row['outcome']}", flush=True)

    classes = ["interrupted, old session", "interrupted, new session",
               "finished before the signal"]  # fmt: skip
    table = ["| command | signal | trials | " + " | ".join(classes) + " | broke the contract |",
             "|---|---|---:|" + "---:|" * (len(classes) + 1)]  # fmt: skip
    for command in commands:
        for name in ("SIGINT", "SIGTERM"):
            sub = [r for r in rows if r["command"] == command and r["signal"] == name]
            if not sub:
                continue
            counts = [sum(r["outcome"] == c for r in sub) for c in classes]
            table.append(
                f"| {command} | {name} | {len(sub)} | " + " | ".join(map(str, counts))
                + f" | {sum(not r['ok'] for r in sub)} |"
            )  # fmt: skip
    broken = [r for r in rows if not r["ok"]]
    check = report.check(TARGET, len(broken))
    why = sorted({r["outcome"] for r in broken})
    listed = "".join(f"\n- {w}" for w in why)
    timing = ", ".join(f"{c} {d:.1f} s" for c, d in durations.items())
    starts = sorted(r["handlers_after_s"] for r in rows if r["handlers_after_s"] is not None)
    startup = f"median {1000 * starts[len(starts) // 2]:.0f} ms" if starts else "-"
    moved = sum(r["moved_to_handlers"] for r in rows)
    waits = sorted(r["after_signal_s"] for r in rows if r["outcome"].startswith("interrupted"))
    latency = (
        f"a median {1000 * waits[len(waits) // 2]:.0f} ms and at most {waits[-1]:.2f} s"
        if waits
        else "-"
    )
    command_line = (
        f"python bench/fault_interrupts.py --trials {args.trials} --sigterm {args.sigterm} "
        f"--seed {args.seed}"
    )
    body = f"""Command: `{command_line}`
(uninterrupted runs: {timing}; the signal at a seeded random moment of that span: SIGINT
to the process group as Ctrl-C sends it, SIGTERM to the command's process only). A moment
before the process has installed its handlers (the interpreter's own start, {startup})
is moved to the moment it has: {moved} of {len(rows)} trials.

{chr(10).join(table)}

The line of every interrupted trial: `{_common_line(rows)}`.
An interrupted command ended {latency} after the signal.
Trials that broke the contract (another exit code, not exactly one line, a traceback, a
session neither old nor new, a temporary file or a worker process left, an interrupt
swallowed): **{len(broken)}** (target 0, issue 18) - {check}.{listed}
"""
    print("\n".join(table))
    return report.finish({SECTION: body})


def _common_line(rows: list[dict]) -> str:
    """The error line of the interrupted SIGINT trials (they are all the same)."""
    lines = sorted({r["error_lines"][0] for r in rows if r["exit"] == 130 and r["error_lines"]})
    return " / ".join(lines) or "-"


if __name__ == "__main__":
    raise SystemExit(main())
