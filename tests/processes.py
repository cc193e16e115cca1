"""What /proc shows of processes (a test helper, not a test): state, CPU time, a
process group's live members, a process's children. Used by ``tests/test_signals.py``
and ``bench/fault_interrupts.py``."""

from __future__ import annotations

import os
from pathlib import Path

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def proc_stat(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command name (state first), or None."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()


def cpu_seconds(pid: int) -> float:
    """User and system CPU time of a process so far, s (0 once it is gone)."""
    fields = proc_stat(pid)
    return 0.0 if fields is None else (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def _living(field: int, value: int) -> list[int]:
    """Processes whose stat ``field`` (1 parent, 2 group) is ``value``, zombies left out
    (they are dead, waiting to be reaped)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            fields = proc_stat(int(entry))
            if fields is not None and int(fields[field]) == value and fields[0] != "Z":
                found.append(int(entry))
    return found


def alive_in_group(pgid: int) -> list[int]:
    """Processes of the group that still run."""
    return _living(2, pgid)


def children(pid: int) -> list[int]:
    """Child processes of ``pid`` that still run."""
    return _living(1, pid)
