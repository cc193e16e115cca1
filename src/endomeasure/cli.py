"""The ``endomeasure`` command line: the only module that imports typer and rich.

Adding a command
----------------
Append a function decorated with ``@command()``. Its body imports its pipeline function
lazily (so ``endomeasure --help`` loads no numpy, cv2, scipy, h5py or matplotlib), calls
it, and renders the returned report: rich tables and progress on stderr, or with
``--json`` exactly one JSON document on stdout (use :func:`_print_json`; for progress,
pass the callback of :func:`_progress` to the pipeline function). No maths here.
The ``@command()`` wrapper is the error boundary: an
:class:`~endomeasure.errors.EndomeasureError` becomes one line ``error: ...`` on stderr
and its exit code (0 success, 1 ran but failed its goal, 2 bad usage or bad input); any
other exception is reported as a bug in one line; ``--debug`` adds the traceback. Ctrl-C
and SIGTERM (:mod:`endomeasure.interrupts`) give exit 130 / 143 and one line, also when a
library turned the interrupt into another error. Every command that can edit a session
takes ``--wait SECONDS``, the longest wait for another command's lock; the wrapper makes
every lock of the command obey it and print a ``note:`` line when it has to wait.

The output contract
-------------------
- stderr: messages only; a failure is exactly one line ``error: ...`` (a line longer
  than 300 characters is cut in the middle of what went wrong, never in its hint). Usage
  errors caught by the option parser (an unknown option, ``--workers abc``, a missing
  argument) are such lines too, with exit 2, instead of click's box. Warnings of the
  libraries (Python warnings, and whatever OpenCV, libpng, FFmpeg or HDF5 write to the
  process's stderr) are captured and dropped, so they never mix with the messages;
  ``--debug`` lets them through. Tables (:func:`_print_table`) print every number
  whole, also when piped.
- stdout with ``--json``: always exactly one strict JSON document (RFC 8259: a value
  that is not finite is ``null``, never ``NaN``), also when the command fails: then it
  holds ``"error"`` (the same text as the stderr line) and ``"exit_code"``, next to
  whatever the command's report already had (the automatic matches of a refused
  measurement, the per-image results of ``detect``). Without ``--json`` stdout stays
  empty except for ``--help`` and ``--version``.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import math
import os
import re
import sys
import tempfile
import traceback
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from endomeasure import interrupts

if os.path.basename(sys.argv[0]) == "endomeasure":  # the console script, before typer loads:
    interrupts.install()  # a Ctrl-C while it starts is remembered, never a traceback

import typer  # noqa: E402
from typer.core import TyperGroup  # noqa: E402

from endomeasure import __version__, defaults  # noqa: E402
from endomeasure.errors import EndomeasureError  # noqa: E402

if TYPE_CHECKING:
    from rich.console import Console

ERROR_LINE_LIMIT = 300
"""Characters of an error line: one terminal line or two, and a whole log entry."""


def _usage_line(exc: Exception) -> str:
    """A click usage error as the project's one line, with where to find help."""
    text = exc.format_message() if hasattr(exc, "format_message") else str(exc)
    ctx = getattr(exc, "ctx", None)
    command = ctx.command_path if ctx is not None else "endomeasure"
    return _compose(text.rstrip("."), f"see `{command} --help`")


class _Group(TyperGroup):
    """The command group, with click's usage errors turned into the project's one line."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        argv = list(sys.argv[1:] if args is None else args)
        with interrupts.handling():
            _STATE.outcome = False
            try:
                result = super().main(argv, prog_name, complete_var, standalone_mode=False,
                                      **extra)  # fmt: skip
            except typer.TyperException as exc:  # click's UsageError, BadParameter, ...
                _exit_if_interrupted()
                if type(exc).__name__ == "NoArgsIsHelpError":  # bare `endomeasure`: the
                    help_text = exc.format_message()  # help, which rich has already printed
                    if help_text.strip():
                        sys.stdout.write(help_text + "\n")
                    sys.exit(EXIT_USAGE)
                line = _usage_line(exc)
                if "--json" in argv:
                    _print_json({"error": line, "exit_code": EXIT_USAGE})
                sys.stderr.write(f"error: {line}\n")
                sys.stderr.flush()
                sys.exit(EXIT_USAGE)
            except (typer.Abort, KeyboardInterrupt) as exc:  # escaped every boundary
                interrupts.disarm()
                came = interrupts.received()
                _exit_interrupted(came if came is not None else exc)
            if not _STATE.outcome:  # no command ran (--help, --version): was it cut short?
                _exit_if_interrupted()
            sys.exit(result if isinstance(result, int) else 0)


def _interrupt_line(exc: BaseException) -> tuple[str, int]:
    """The one line and the exit code of an interrupt: 130 for SIGINT, 143 for SIGTERM."""
    code = getattr(exc, "exit_code", EXIT_INTERRUPTED)
    name = getattr(exc, "signal_name", "SIGINT")
    what = f"interrupted by {name}" + (" (Ctrl-C)" if name == "SIGINT" else "")
    return _compose(what, INTERRUPT_HINT), code


def _exit_interrupted(exc: BaseException) -> None:
    line, code = _interrupt_line(exc)
    if _STATE.json_output and not _STATE.json_printed:
        _print_json({"error": line, "exit_code": code})
    sys.stderr.write(f"error: {line}\n")
    sys.stderr.flush()
    sys.exit(code)


def _exit_if_interrupted() -> None:
    interrupts.disarm()
    came = interrupts.received()
    if came is not None:
        _exit_interrupted(came)


app = typer.Typer(
    cls=_Group,
    name="endomeasure",
    help=(
        "3D measurement with prism-based stereo video endoscopes.\n\n"
        "Exit codes: 0 success, 1 ran but failed its goal, 2 bad usage or bad input, "
        "130 interrupted (Ctrl-C), 143 terminated (SIGTERM)."
    ),
    context_settings={"help_option_names": ["-h", "--help"]},
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)

EXIT_BUG = 2
"""An unexpected exception is a bug; the job could not be done, as with bad input."""
EXIT_INTERRUPTED = 130
"""128 + SIGINT; SIGTERM gives 128 + 15 = 143 (``Interrupted.exit_code``)."""
EXIT_USAGE = 2
INTERRUPT_HINT = (
    "a session holds all of this command's changes or none of them; run it again to finish"
)


class _State:
    debug = False
    json_output = False  # the running command was asked for --json
    json_printed = False  # and has written its document
    outcome = False  # a command's boundary has decided how the process ends


_STATE = _State()


def _version_callback(value: bool) -> None:
    if value:
        sys.stdout.write(f"endomeasure {__version__}\n")
        raise typer.Exit()


@app.callback()
def _global_options(
    debug: Annotated[
        bool, typer.Option("--debug", help="Show the Python traceback of an error.")
    ] = False,
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version_callback, is_eager=True, help="Show the version."
        ),
    ] = False,
) -> None:
    """3D measurement with prism-based stereo video endoscopes."""
    _STATE.debug = debug


def _cut_middle(text: str, limit: int) -> str:
    """``text`` in at most ``limit`` characters: its start and its end, the middle cut."""
    if len(text) <= limit:
        return text
    keep = max(limit - 5, 2)
    tail = (2 * keep) // 5
    return text[: keep - tail] + " ... " + text[len(text) - tail :]


def _one_line(text: str, limit: int = ERROR_LINE_LIMIT) -> str:
    """``text`` on one line of at most ``limit`` characters, cut in the middle."""
    return _cut_middle(" ".join(str(text).split()), limit)


def _compose(
    what: str, hint: str | None, path: str | None = None, limit: int = ERROR_LINE_LIMIT
) -> str:
    """``what [path]; hint`` in at most ``limit`` characters: what went wrong is cut in
    its middle, so that its start and end, the file and the hint survive."""
    what = " ".join(str(what).split())
    tail = ""
    if path:
        tail += " [" + _cut_middle(" ".join(str(path).split()), limit // 3) + "]"
    if hint:
        tail += "; " + _cut_middle(" ".join(str(hint).split()), limit // 3)
    return _cut_middle(what, limit - len(tail)) + tail


def _fail(message: str, code: int, exc: BaseException) -> None:
    """The command's one error line, its exit code; an interrupt received on the way
    (also one a library turned into another error) is reported as the interrupt."""
    interrupts.disarm()
    _STATE.outcome = True
    came = interrupts.received()
    if came is not None and not isinstance(exc, KeyboardInterrupt):
        exc = came
    if isinstance(exc, KeyboardInterrupt):
        message, code = _interrupt_line(exc)
    if _STATE.debug:
        traceback.print_exception(exc, file=sys.stderr)
    if _STATE.json_output and not _STATE.json_printed:
        _print_json({"error": message, "exit_code": code})
    sys.stderr.write(f"error: {message}\n")
    sys.stderr.flush()
    raise typer.Exit(code)


def _error_text(exc: EndomeasureError) -> str:
    return _compose(exc.what, exc.hint, exc.path)


@contextlib.contextmanager
def _quiet_libraries():
    """Capture what the libraries would write to stderr while a command runs.

    Python warnings are ignored; the process's file descriptor 2 (where OpenCV, libpng,
    FFmpeg and HDF5 write from C, and where worker processes inherit it) points to a
    scratch file, while ``sys.stderr`` keeps writing to the real stderr. With ``--debug``
    nothing is captured.
    """
    if _STATE.debug:
        yield
        return
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")  # read when cv2 is first imported
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            sys.stderr.flush()
            real_fd = os.dup(2)
            scratch = tempfile.TemporaryFile()
        except OSError:  # no descriptors or no room for the scratch file: capture nothing
            yield
            return
        python_stderr = sys.stderr
        try:
            uses_fd2 = python_stderr.fileno() == 2
        except (AttributeError, OSError, ValueError):  # a test runner's buffer
            uses_fd2 = False
        if uses_fd2:
            sys.stderr = open(  # closed in the finally below
                real_fd,
                "w",
                buffering=1,
                encoding=python_stderr.encoding,
                errors="backslashreplace",
                closefd=False,
            )
        os.dup2(scratch.fileno(), 2)
        undone: list = []  # the restore steps done, so that it can run twice

        def restore() -> None:
            if "fd2" not in undone:
                with contextlib.suppress(Exception):
                    sys.stderr.flush()
                os.dup2(real_fd, 2)
                undone.append("fd2")
            if uses_fd2 and sys.stderr is not python_stderr:
                sys.stderr.close()
                sys.stderr = python_stderr
            if "real" not in undone:
                os.close(real_fd)
                undone.append("real")
            scratch.close()

        try:
            yield
        finally:
            try:
                restore()
            except KeyboardInterrupt:  # the first signal cut it short; no second one raises
                restore()
                raise


@contextlib.contextmanager
def _error_boundary(json_output: bool = False):
    """Turn exceptions into one line on stderr and an exit code (traceback with --debug),
    with the libraries' own warnings captured (:func:`_quiet_libraries`)."""
    _STATE.json_output, _STATE.json_printed = bool(json_output), False
    try:
        with _quiet_libraries():
            interrupts.arm()  # raises one that came while the process started
            yield
        interrupts.disarm()
        _STATE.outcome = True
        came = interrupts.received()
        if came is not None:  # swallowed on the way (the work may be stored or not)
            raise came
    except typer.Exit as exc:
        interrupts.disarm()
        _STATE.outcome = True
        if exc.exit_code != 0 and interrupts.received() is not None:
            _fail("", 0, exc)
        raise
    except EndomeasureError as exc:
        _fail(_error_text(exc), exc.exit_code, exc)
    except KeyboardInterrupt as exc:
        _fail("", EXIT_INTERRUPTED, exc)
    except MemoryError as exc:
        _fail(
            _compose("not enough memory for this command", "give smaller inputs or options"),
            EXIT_USAGE,
            exc,
        )
    except Exception as exc:
        _fail(
            _compose(
                f"internal error ({type(exc).__name__}: {exc})",
                "this is a bug in endomeasure, please report it; rerun as "
                "`endomeasure --debug ...` to see the traceback",
            ),
            EXIT_BUG,
            exc,
        )


_LIST_ITEM = re.compile(r"([-*]|\d+[.)])\s")
"""A line that starts a list item keeps its own line in a help text."""


def _reflowed(doc: str | None) -> str | None:
    """A docstring as a command's help text: the lines of each paragraph joined into one,
    so that the help reflows to the terminal's width instead of keeping the source's
    line breaks (typer keeps them after the first paragraph). Blank lines still part
    paragraphs, list items (``- ``, ``* ``, ``1. ``) start their own lines, and a block
    starting with ``\\b`` (click's "do not rewrap") is kept as written."""
    if not doc:
        return doc
    paragraphs = []
    for block in re.split(r"\n\s*\n", inspect.cleandoc(doc)):
        if block.startswith("\b"):
            paragraphs.append(block)
            continue
        lines: list[str] = []
        for line in block.splitlines():
            text = line.strip()
            if lines and not _LIST_ITEM.match(text):
                lines[-1] += " " + text
            else:
                lines.append(text)
        paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs)


def command(name: str | None = None, **kwargs: Any):
    """Register a command on the app, wrapped in the error boundary; its docstring is
    its help, reflowed (:func:`_reflowed`)."""

    def decorate(function):
        @functools.wraps(function)
        def wrapper(*args, **kw):
            wait_s = kw.pop("wait_s", defaults.LOCK_WAIT_S)
            try:
                with _error_boundary(json_output=kw.get("json_output", False)):
                    with _lock_waiting(wait_s):
                        return function(*args, **kw)
            except KeyboardInterrupt as exc:  # the first signal came while the boundary
                _fail("", EXIT_INTERRUPTED, exc)  # handled another error: it wins

        kwargs.setdefault("help", _reflowed(function.__doc__))
        app.command(name, **kwargs)(wrapper)
        return function

    return decorate


@contextlib.contextmanager
def _lock_waiting(wait_s: float):
    """Every session lock of the command waits at most ``wait_s`` (``--wait``) and says,
    once, on stderr when it has to wait for another command."""
    if not wait_s >= 0:
        raise _bad_input(f"--wait must be 0 or more seconds, not {wait_s}")
    from endomeasure.io._lock import LockWaiting, lock_waiting

    def on_wait(message: str) -> None:
        sys.stderr.write(f"note: {_one_line(message)}\n")
        sys.stderr.flush()

    with lock_waiting(LockWaiting(timeout_s=wait_s, on_wait=on_wait)):
        yield


def _stderr_console() -> Console:
    from rich.console import Console

    return Console(stderr=True)


MEASURE_WIDTH = 10_000
"""Columns offered to a table to measure its natural width (a bound it never meets)."""


def _print_table(console: Console, table: Any) -> None:
    """Print a rich table so that no number is ever cut ("147.30,264…").

    A right-aligned (numeric) column is never narrower than its widest cell and never
    wraps; a text column wraps at spaces, never narrower than its longest word (or its
    header's), and no cell ends in an ellipsis. Off a terminal (a pipe, a log, where
    rich assumes 80 columns) the table is printed at its natural width, however wide; on
    a terminal it is printed wider than the terminal only when even its narrowest
    layout does not fit.
    """
    from rich.measure import Measurement

    wide = console.options.update_width(MEASURE_WIDTH)
    for column in table.columns:
        column.overflow = "fold"
        column.no_wrap = column.justify == "right"
        cells = [Measurement.get(console, wide, c) for c in (column.header, *column.cells)]
        whole = [m.maximum if column.no_wrap else m.minimum for m in cells]
        column.min_width = max([column.min_width or 0, *whole])
    measure = Measurement.get(console, wide, table)
    need = measure.minimum if console.is_terminal else measure.maximum
    if need <= console.width:
        console.print(table)
        return
    width = console.width
    console.width = need
    try:
        console.print(table)
    finally:
        console.width = width


@contextlib.contextmanager
def _progress(console: Console, label: str, enabled: bool = True):
    """Yield an ``on_progress(done, total)`` callback drawing a bar on a terminal's stderr.

    Off a terminal (pipes, CI logs, tests) it draws nothing, so stderr keeps only messages.
    """
    if not (enabled and console.is_terminal):
        yield None
        return
    from rich.progress import Progress

    with Progress(console=console, transient=True) as progress:
        task = progress.add_task(label, total=None)
        yield lambda done, total: progress.update(task, completed=done, total=total)


def _json_safe(value: Any) -> Any:
    """``value`` with only what strict JSON holds: a float that is not finite becomes
    None, NumPy scalars and arrays plain numbers and lists, bytes text, tuples lists,
    anything else its ``str``."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).decode("utf-8", errors="replace")
    if hasattr(value, "tolist"):  # NumPy scalars and arrays, without importing NumPy
        return _json_safe(value.tolist())
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return str(value)


def _print_json(document: Any) -> None:
    """Write exactly one strict JSON document to stdout (no NaN, see the module docstring)."""
    sys.stdout.write(json.dumps(_json_safe(document), indent=2, allow_nan=False) + "\n")
    sys.stdout.flush()
    _STATE.json_printed = True


def _sigma_text(sigma: Any) -> str:
    """Image noise for display: one value, or u and v."""
    if isinstance(sigma, (int, float)):
        return f"{sigma:.4f} px"
    return f"u {sigma[0]:.4f}, v {sigma[1]:.4f} px"


SigmaOption = Annotated[
    str | None,
    typer.Option(
        "--sigma",
        metavar="PX|U,V",
        help="Image noise per coordinate, px, or separately for u and v (default: in a board "
        "test, each test image half's own, from the scatter of its neighbouring corners; "
        "otherwise from the calibration residuals).",
    ),
]

BoardOption = Annotated[
    str,
    typer.Option(
        "--board",
        help="Board spec: chessboard:COLSxROWS:SQUARE_MM (inner corners) or "
        "charuco:SXxSY:SQUARE_MM:MARKER_MM:DICT (SX, SY: squares).",
        show_default=False,
    ),
]
JsonOption = Annotated[
    bool, typer.Option("--json", help="Print one JSON document on stdout instead of tables.")
]
WaitOption = Annotated[
    float,
    typer.Option(
        "--wait",
        metavar="SECONDS",
        help="Longest wait for another command's lock on the session, s (0: do not wait).",
    ),
]
FrameStepOption = Annotated[
    int | None,
    typer.Option(
        "--frame-step",
        metavar="N",
        help="Take every N-th video frame instead of picking sharp, distinct frames that "
        "show the whole board in both halves.",
        show_default=False,
    ),
]


def main() -> None:
    """Console-script entry point.

    An interrupted command ends at once after its line: the interpreter's own exit
    would wait for library threads (a process pool's) that an interrupt can leave stuck;
    everything that matters (the session, temp files, worker processes) is settled by
    then.
    """
    try:
        app(prog_name="endomeasure")
    except SystemExit as exc:
        interrupts.settle()
        if interrupts.received() is not None and exc.code in (128 + s for s in interrupts.HANDLED):
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(exc.code)
        raise
    except KeyboardInterrupt as exc:
        interrupts.settle()
        line, code = _interrupt_line(exc)
        sys.stderr.write(f"error: {line}\n")
        sys.exit(code)
    except BaseException as exc:  # escaped the command boundary, e.g. in an option callback
        interrupts.settle()
        if "--debug" in sys.argv:
            raise
        line = _compose(
            f"internal error ({type(exc).__name__}: {exc})",
            "this is a bug in endomeasure; rerun as `endomeasure --debug ...` for the traceback",
        )
        sys.stderr.write(f"error: {line}\n")
        sys.exit(EXIT_BUG)


# --------------------------------------------------------------------------- values


def _refuse_given(ctx: typer.Context, names: tuple[str, ...], where: str, hint: str) -> None:
    """A BadInputError naming the options among ``names`` (parameter names) that the
    command line set although they have no effect ``where``: never silently ignored."""
    flags = []
    for param in ctx.command.params:
        if param.name in names:
            source = ctx.get_parameter_source(param.name)
            if source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP"):
                flags.append(max(param.opts, key=len))
    if flags:
        verb = "has" if len(flags) == 1 else "have"
        raise _bad_input(f"{', '.join(flags)} {verb} no effect {where}", hint=hint)


def _bad_input(what: str, hint: str | None = None) -> EndomeasureError:
    from endomeasure.errors import BadInputError

    return BadInputError(what, hint=hint)


def parse_pixel(text: str) -> tuple[float, float]:
    """``"U,V"`` -> ``(u, v)`` in px; anything else is a :class:`BadInputError`."""
    import math

    parts = str(text).replace(" ", "").split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        u, v = float(parts[0]), float(parts[1])
    except ValueError:
        raise _bad_input(
            f"cannot read the pixel {text!r}", hint="give pixels as U,V, e.g. --left 120.5,88"
        ) from None
    if not (math.isfinite(u) and math.isfinite(v)):
        raise _bad_input(f"the pixel {text!r} is not finite")
    return u, v


def parse_sigma(text: str | None) -> float | tuple[float, float] | None:
    """``"PX"`` (every coordinate) or ``"U,V"`` (u and v separately) -> the image noise in
    px; ``None`` stays ``None``; anything else is a :class:`BadInputError`."""
    if text is None:
        return None
    parts = str(text).replace(" ", "").split(",")
    try:
        if len(parts) not in (1, 2):
            raise ValueError
        values = [float(p) for p in parts]
    except ValueError:
        raise _bad_input(
            f"cannot read the image noise {text!r}",
            hint="give --sigma PX for every coordinate or --sigma U,V, e.g. --sigma 0.013,0.016",
        ) from None
    from endomeasure.solvers.uncertainty import checked_sigma

    return checked_sigma(values[0] if len(values) == 1 else values)


def parse_depths(text: str) -> list[float]:
    """``"start:stop:step"`` (stop included) or ``"z1,z2,..."`` -> depths, mm."""
    import numpy as np

    s = str(text).strip()
    try:
        if ":" in s:
            a, b, c = (float(x) for x in s.split(":"))
            if not (c > 0 and b >= a):
                raise ValueError
            n_planes = math.floor((b - a) / c) + 1  # before arange allocates them
            if not n_planes <= defaults.MAX_MAP_DEPTHS:
                raise _bad_input(
                    f"the depths {text!r} make {n_planes:g} planes, more than "
                    f"{defaults.MAX_MAP_DEPTHS}, more than a map can show",
                    hint="give a larger STEP",
                )
            depths = np.arange(a, b + 0.5 * c, c)
        else:
            depths = np.array([float(x) for x in s.split(",")])
    except ValueError:
        raise _bad_input(
            f"cannot read the depths {text!r}",
            hint="give START:STOP:STEP in mm (e.g. 10:45:5) or a list 12,20,30",
        ) from None
    if depths.size == 0 or not np.all(np.isfinite(depths) & (depths > 0)):
        raise _bad_input(f"depths must be positive numbers of mm, got {text!r}")
    return depths.tolist()


def parse_grid(text: str) -> tuple[int, int]:
    """``"NU,NV"`` -> ``(n_u, n_v)``."""
    try:
        n_u, n_v = (int(x) for x in text.split(","))
    except ValueError:
        raise _bad_input(f"cannot read the grid {text!r}", hint="give NU,NV, e.g. 24,18") from None
    return n_u, n_v


def parse_split(text: str) -> int | None:
    """``"auto"`` -> None, or a column number."""
    value = str(text).strip().lower()
    if value == "auto":
        return None
    try:
        return int(value)
    except ValueError:
        raise _bad_input(
            f"--split must be 'auto' or a column number, not {text!r}",
            hint="e.g. --split auto or --split 640",
        ) from None


def parse_sets(text: str) -> list[str]:
    """``'calib,test'`` -> ``['calib', 'test']`` (validated by the simulate pipeline)."""
    return [s.strip().lower() for s in str(text).split(",") if s.strip()]


# --------------------------------------------------------------------------- commands


@command("info")
def info(
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    json_output: JsonOption = False,
) -> None:
    """Summarise what a session holds: images, boards, detections, models, records."""
    from endomeasure.pipeline.info import summarise_session

    summary = summarise_session(session)
    if json_output:
        _print_json(summary.to_dict())
        return

    from rich.table import Table

    console = _stderr_console()
    size = "unknown" if summary.image_size is None else "{} x {} px".format(*summary.image_size)
    split = "unknown" if summary.split is None else f"column {summary.split}"
    console.print(f"[bold]{summary.path}[/bold]  (session format {summary.format_version})")
    console.print(f"image size {size}, split {split}, created by {summary.created_by}")
    console.print(
        "checksum: matches (SHA-256 of the whole file)"
        if summary.checksum == "ok"
        else "checksum: none (a format 1.0 file; its next edit adds one)"
    )
    images = ", ".join(f"{n} {name}" for name, n in summary.images.items())
    console.print(f"images: {images}")

    if summary.boards:
        table = Table(title="boards", title_justify="left")
        table.add_column("board")
        table.add_column("spec")
        for board in summary.boards:
            table.add_row(board["name"], board["spec"])
        _print_table(console, table)
    if summary.detections:
        table = Table(title="detections", title_justify="left")
        for column in ("board", "half", "images", "found", "failed", "corners"):
            table.add_column(column, justify="left" if column in ("board", "half") else "right")
        for det in summary.detections:
            table.add_row(
                det["board"],
                det["half"],
                *(str(det[k]) for k in ("images", "found", "failed", "corners")),
            )
        _print_table(console, table)
    if summary.models:
        table = Table(title="models", title_justify="left")
        for column in ("model", "type", "parameters", "RMS", "verdict"):
            table.add_column(column, justify="right" if column in ("parameters", "RMS") else "left")
        for model in summary.models:
            rms = f"{model['rms']:.4f} {model['rms_units']}" if "rms" in model else "-"
            table.add_row(model["name"], model["registry_name"], str(model["n_params"]), rms,
                          model["verdict"])  # fmt: skip
        _print_table(console, table)
        for model in summary.models:
            for reason in model["verdict_reasons"]:
                console.print(f"{model['name']} {model['verdict']}: {reason}", markup=False)
    if summary.records:
        records = ", ".join(f"{n} {kind}" for kind, n in summary.records.items())
        console.print(f"records: {records}")


@command("add-images")
def add_images(
    session: Annotated[
        Path, typer.Argument(help="Session file (.h5); created if missing.", show_default=False)
    ],
    paths: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Image files, directories of images, or video files (.avi, .mp4, .mkv, "
            ".mov, .mpg, ...: whatever OpenCV decodes).",
            show_default=False,
        ),
    ] = None,
    image_set: Annotated[
        str, typer.Option("--set", help="Image set: calib, test or scene.")
    ] = "calib",
    board: Annotated[
        str | None,
        typer.Option(
            "--board",
            help="Board spec for picking video frames (default: the session's only board).",
            show_default=False,
        ),
    ] = None,
    frame_step: FrameStepOption = None,
    split: Annotated[
        str,
        typer.Option(
            "--split",
            help="First column of the right half for checking video frames, or 'auto' (the "
            "session's split, else found from the clip's prism band).",
        ),
    ] = "auto",
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Embed image files, or frames picked from videos, in a session (compressed, with
    their path, SHA-256 and frame number).

    A file that cannot be used (unreadable, not an image, another size, a name clash) is
    listed and left out, the others are stored: exit code 1. Exit code 2 when no file is
    usable (nothing stored, no session created) or a video cannot be used.
    """
    from endomeasure.pipeline.images import add_images as run

    split_column = parse_split(split)
    console = _stderr_console()
    with _progress(console, "reading images", enabled=not json_output) as on_progress:
        report = run(
            session,
            paths or [],
            image_set,
            on_progress=on_progress,
            board=board,
            frame_step=frame_step,
            split=split_column,
        )
    from endomeasure.errors import GoalNotMetError

    failure = None
    if report.failed:
        failure = GoalNotMetError(report.failure, hint="the other images were stored")
    if json_output:
        error = "" if failure is None else _error_text(failure)
        _print_json(_with_error(report.to_dict(), error, report.exit_code))
    else:
        _print_videos(console, report.videos)
        for item in report.failed:
            console.print(f"not added: {item.path}: {item.error}", markup=False)
        console.print(
            f"{report.session}: added {len(report.added)} {report.image_set} image(s)"
            + (f", {len(report.unchanged)} already present" if report.unchanged else "")
        )
    if failure is not None:
        raise failure


@command("detect")
def detect(
    session: Annotated[
        Path, typer.Argument(help="Session file (.h5); created if missing.", show_default=False)
    ],
    images: Annotated[
        list[Path],
        typer.Argument(
            help="Image files, directories of images, or video files (.avi, .mp4, .mkv, "
            ".mov, .mpg, ...: whatever OpenCV decodes; sharp, distinct frames showing the "
            "whole board in both halves are picked).",
            show_default=False,
        ),
    ],
    board: BoardOption,
    image_set: Annotated[
        str, typer.Option("--set", help="Image set: calib, test or scene.")
    ] = "calib",
    split: Annotated[
        str,
        typer.Option(
            "--split",
            help="First column of the right half, or 'auto' (the session's split, else found "
            "from the dark prism band).",
        ),
    ] = "auto",
    workers: Annotated[int, typer.Option("--workers", help="Processes to use.")] = 1,
    frame_step: FrameStepOption = None,
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Find target corners in both halves of every image (and of the frames taken from
    videos) and store them in the session.

    Exit code 1 if any image failed (unreadable, wrong size, no board), 2 if nothing usable
    or a video cannot be used (unreadable, truncated, another frame size, no board).
    """
    from endomeasure.pipeline.detect import detect_images

    split_column = parse_split(split)
    if json_output:
        report = detect_images(session, images, board, image_set=image_set, split=split_column,
                               workers=workers, frame_step=frame_step)  # fmt: skip
        failure = _detect_failure(report)
        error = "" if failure is None else _error_text(failure)
        _print_json(_with_error(report.to_dict(), error, report.exit_code))
        if failure is not None:
            raise failure
        return

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    console = _stderr_console()
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn())
    # off a terminal rich would still end the (empty) live display with a newline, and
    # an error would no longer be one line on stderr
    bar = Progress(*columns, console=console, transient=True, disable=not console.is_terminal)
    with bar as progress:
        tasks: dict[str, Any] = {}

        def on_progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = progress.add_task(stage, total=total)
            progress.update(tasks[stage], completed=done, total=total)

        report = detect_images(
            session,
            images,
            board,
            image_set=image_set,
            split=split_column,
            workers=workers,
            frame_step=frame_step,
            on_progress=on_progress,
        )

    _render_detect(console, report)
    failure = _detect_failure(report)
    if failure is not None:
        raise failure


def _with_error(document: dict, error: str, exit_code: int) -> dict:
    """A failed command's JSON report: its fields plus the error line and the exit code."""
    if error:
        document = {**document, "error": error, "exit_code": exit_code}
    return document


def _detect_failure(report: Any) -> EndomeasureError | None:
    """``detect``'s one line: exit 1 when some image failed, 2 when nothing was usable."""
    from endomeasure.errors import BadInputError, GoalNotMetError

    if report.exit_code == 2:
        hint = (
            "give image files or folders of images"
            if not report.images
            else "each image's reason is in the table (with --json: in its report)"
        )
        return BadInputError(report.failure, hint=hint)
    if report.exit_code == 1:
        return GoalNotMetError(report.failure, hint="the usable images were stored")
    return None


def _print_videos(console: Console, videos: list[Any]) -> None:
    """One line per video: frames decoded, kept, and why the others were left out."""
    for video in videos:
        left_out = ", ".join(f"{reason} {n}" for reason, n in video.left_out.items() if n)
        console.print(
            f"{video.path}: {video.frames} frames, kept {len(video.picked)}"
            + (f" (left out: {left_out})" if left_out else ""),
            markup=False,
        )


def _render_detect(console: Console, report: Any) -> None:
    """The per-video lines, the per-image table and the summary line of ``detect``."""
    from rich.table import Table

    _print_videos(console, report.videos)
    table = Table(title=f"detect {report.board} ({report.image_set})", title_justify="left")
    for column in ("image", "status", "left", "right", "edge width px (L/R)"):
        table.add_column(column, justify="right" if column.startswith("edge") else "left")
    for image in report.images:
        if not image.halves:
            table.add_row(image.name or image.path, "[red]failed[/red]", image.error, "", "")
            continue
        cells = []
        for label in ("left", "right"):
            half = image.halves[label]
            text = f"[red]{half.failure}[/red]" if half.failure else f"{half.n_corners} corners"
            cells.append(text)
        widths = "/".join(
            "-" if image.halves[k].failure else f"{image.halves[k].edge_width_px:.2f}"
            for k in ("left", "right")
        )
        colour = {"ok": "green", "one-half": "yellow", "failed": "red"}[image.status]
        table.add_row(image.name, f"[{colour}]{image.status}[/{colour}]", *cells, widths)
    _print_table(console, table)
    counts = report.counts
    found, examined = report.halves_found
    split = "not found" if report.split is None else f"{report.split} ({report.split_source})"
    console.print(
        f"split column {split}; images: {counts['ok']} ok, "
        f"{counts['one-half']} one half, {counts['failed']} failed; halves with the board "
        f"{found}/{examined}; "
        + (f"stored in {report.session}" if report.stored else "nothing stored")
    )


@command("simulate")
def simulate(
    out_dir: Annotated[
        Path, typer.Argument(help="Output folder (created if missing).", show_default=False)
    ],
    preset: Annotated[
        str,
        typer.Option(
            "--preset",
            help="Built-in preset name, a preset JSON file, or 'random' (with --design-seed).",
        ),
    ] = "default",
    sets: Annotated[
        str,
        typer.Option(
            "--set", help="Comma-separated image sets: calib, test, scene, charuco (not default)."
        ),
    ] = "calib,test,scene",
    seed: Annotated[int, typer.Option("--seed", help="Seed of poses and noise (>= 0).")] = 0,
    noise_free: Annotated[
        bool, typer.Option("--noise-free", help="Render without shot and read noise.")
    ] = False,
    design_seed: Annotated[
        int | None,
        typer.Option(
            "--design-seed",
            help="With --preset random: the seed of the probe design drawn (>= 0).",
            show_default=False,
        ),
    ] = None,
    json_output: JsonOption = False,
) -> None:
    """Render prism-stereo image sets with exact ground truth (the digital twin)."""
    from endomeasure.pipeline.simulate import simulate as run

    console = _stderr_console()
    with _progress(console, "rendering", enabled=not json_output) as on_progress:
        report = run(
            out_dir,
            preset,
            parse_sets(sets),
            seed=seed,
            noise_free=noise_free,
            design_seed=design_seed,
            on_progress=(
                None if on_progress is None else lambda done, total, _: on_progress(done, total)
            ),
        )
    if json_output:
        _print_json(report.to_dict())
        return

    from rich.table import Table

    table = Table(title=f"simulate {report.preset} (seed {report.seed})", title_justify="left")
    for column in ("set", "images", "board whole in both halves"):
        table.add_column(column, justify="left" if column == "set" else "right")
    for name, info in report.sets.items():
        visible = info["fully_visible"]
        whole = "-" if visible is None else f"{visible}/{info['images']}"
        table.add_row(name, str(info["images"]), whole)
    _print_table(console, table)
    noise = "noise-free" if report.noise_free else "with sensor noise"
    console.print(
        f"{report.out_dir}: images {noise}, split column {report.split}, ground truth in "
        f"*.json next to each image and simulation.json; {report.seconds:.1f} s"
    )


@command("calibrate")
def calibrate(
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    model: Annotated[
        str, typer.Option("--model", help="A registered camera model, or all.")
    ] = defaults.ALL_MODELS,
    glass_index: Annotated[
        float | None,
        typer.Option("--glass-index", help="Known prism glass index, held (default: estimated)."),
    ] = None,
    free_index: Annotated[
        bool, typer.Option("--free-index", help="Estimate the index from --glass-index.")
    ] = False,
    seed: Annotated[
        Path | None,
        typer.Option("--seed", help="JSON model with nominal design values (seeds its kind)."),
    ] = None,
    plot: Annotated[
        Path | None, typer.Option("--plot", help="Folder for residual plots (PNG).")
    ] = None,
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Fit camera models to the session's detections (both halves, one cost) and store them."""
    from endomeasure.errors import BadInputError
    from endomeasure.pipeline.calibrate import calibrate_session

    if glass_index is not None and not glass_index > 1.0:
        raise BadInputError(f"the glass index must exceed 1, not {glass_index}")
    console = _stderr_console()
    with (
        console.status("calibrating", spinner="dots")
        if (console.is_terminal and not json_output)
        else contextlib.nullcontext()
    ):
        report = calibrate_session(
            session,
            model,
            values={} if glass_index is None else {"n_glass": glass_index},
            free=("n_glass",) if free_index else (),
            hold=("n_glass",) if glass_index is not None and not free_index else (),
            seed=seed,
            plot_dir=plot,
        )
    problems = [f"{name}: {why}" for name, why in report.refused.items()]
    problems += [
        f"{name}: calibration failed, stored as not usable: {why}"
        for name, why in report.failed.items()
    ]
    error = "" if report.ok else _one_line(" | ".join(problems) or "no usable model")
    if json_output:
        _print_json(_with_error(report.to_dict(), error, 1))
    else:
        _render_calibration(console, report)
    if report.ok:  # failed models that another usable one makes up for: notes, exit 0
        for line in problems:
            sys.stderr.write(f"note: {_one_line(line)}\n")
        return
    from endomeasure.errors import GoalNotMetError

    raise GoalNotMetError(error)


def _render_calibration(console: Console, report: Any) -> None:
    from rich.table import Table

    models = report.models
    if models:
        table = Table(title=f"calibration of {report.session}", title_justify="left")
        for column in ("model", "verdict", "RMS px", "left px", "right px", "noise floor px",
                       "RMS/floor", "corners", "outliers", "worst images (RMS px)"):  # fmt: skip
            table.add_column(column, justify="left" if column in ("model", "verdict") else "right")
        for s in models.values():
            worst = ", ".join(f"{n} {r:.3f}" for n, r in s.worst_images)
            figures = (s.rms, s.rms_half[0], s.rms_half[1], s.noise_floor)
            table.add_row(s.name, s.verdict, *(f"{v:.4f}" for v in figures),
                          f"{s.rms_ratio:.2f}", str(s.n_corners), str(s.n_outliers),
                          worst)  # fmt: skip
        _print_table(console, table)
        for s in models.values():
            for reason in s.reasons:
                console.print(f"{s.name} {s.verdict}: {reason}", markup=False)
            for line in s.selection:
                console.print(f"{s.name} lens/model terms: {line}", markup=False)
            if s.uncertain_std:
                held = ", ".join(f"{n} +-{v:.2g}" for n, v in s.uncertain_std.items())
                console.print(
                    f"{s.name} terms held by the fit but not ruled out by the data "
                    f"(every measurement's +- varies them): {held}",
                    markup=False,
                )
    for s in models.values():
        table = Table(title=f"{s.name} parameters (+- 1 sigma)", title_justify="left")
        table.add_column("parameter")
        table.add_column("value", justify="right")
        table.add_column("std", justify="right")
        for name, value in s.params.items():
            std = s.std.get(name)
            table.add_row(name, f"{value:.6g}", "fixed" if std is None else f"{std:.2g}")
        _print_table(console, table)
        strongest = ", ".join(f"{a}~{b} {r:+.3f}" for a, b, r in s.correlations)
        console.print(f"strongest correlations: {strongest}")
        for path in s.plots:
            console.print(f"plot: {path}")
    console.print(
        f"{report.n_images} images, split column {report.split}; stored: "
        + (", ".join(models) if models else "nothing")
    )


@command("export")
def export(
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    out: Annotated[
        Path,
        typer.Argument(
            help="Output file; for ros-yaml and mrcal the name of the pair: probe.yaml "
            "gives probe_left.yaml and probe_right.yaml.",
            show_default=False,
        ),
    ],
    model: Annotated[str, typer.Option("--model", help="Stored model name.")] = "pinhole",
    fmt: Annotated[
        str,
        typer.Option(
            "--format",
            help="json (any model); opencv-yaml, ros-yaml (ROS CameraInfo, one file per "
            "half) or mrcal (.cameramodel, one per half), pinhole only; ray-table (.h5: "
            "the ray of every pixel, any model).",
        ),
    ] = "json",
    json_output: JsonOption = False,
) -> None:
    """Write a calibrated model to a file other tools read (docs/exports.md).

    JSON for any model and endomeasure itself; the pinhole pair as OpenCV, ROS or mrcal
    calibration files; any model, also the non-central raytrace one, as a table of the
    ray through every pixel centre.
    """
    from endomeasure.pipeline.calibrate import export_session_model

    files = export_session_model(session, model, fmt, out)
    if json_output:
        given = files[0] if len(files) == 1 else out
        _print_json(
            {"session": str(session), "model": model, "format": fmt, "out": str(given),
             "files": [str(f) for f in files]}
        )  # fmt: skip
        return
    written = " and ".join(str(f) for f in files)
    _stderr_console().print(f"{model} from {session} written to {written} ({fmt})", markup=False)


@command("repair")
def repair(
    session: Annotated[Path, typer.Argument(help="Damaged session file.", show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", help="New session file for what is intact.")],
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Copy the intact items of a damaged session into a new session file.

    Each item (an image, a detection, a model, a record ...) is kept when its digest
    matches the session's manifest. Exit 0 when everything was kept, 1 when some items
    were damaged and left out (they are listed), 2 when nothing could be read.
    """
    from endomeasure.pipeline.info import repair_session

    report = repair_session(session, out)
    if json_output:
        _print_json(report.to_dict())
    else:
        console = _stderr_console()
        for item, why in report.dropped.items():
            console.print(f"left out {item}: {why}", markup=False)
        console.print(
            f"{len(report.kept)} items of {session} written to {out}"
            + ("" if report.complete else f", {len(report.dropped)} damaged ones left out"),
            markup=False,
        )
    if not report.complete:
        raise typer.Exit(1)


@command("report")
def report(
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    out: Annotated[
        Path | None,
        typer.Option("-o", "--out", help="HTML file (default: the session's name with .html)."),
    ] = None,
    depths: Annotated[
        str | None,
        typer.Option(
            "--depths",
            help="Trust map: z1,z2,... or START:STOP:STEP in mm (default: the nearest, middle "
            "and farthest depth where the calibration saw the board).",
        ),
    ] = None,
    bands: Annotated[
        str,
        typer.Option(
            "--bands",
            help="Trust map: GREEN,YELLOW limits of the predicted 95 % error of a 1 mm length, "
            "percent.",
        ),
    ] = ",".join(f"{b:g}" for b in defaults.TRUST_BANDS_PERCENT),
    json_output: JsonOption = False,
) -> None:
    """Write a self-contained HTML report of the session's calibrations for a browser.

    Per calibrated model: the verdict and its reasons, the field the calibration covered,
    residual vectors, bias per region and histogram against the noise, outliers, per-image
    RMS (worst first), parameters with their +- and strong correlations, the baseline, and
    a map of where to trust it. Then the board test, predicted against actual errors and
    the stored measurements. A section the session cannot fill says what to run instead.
    The session is only read.
    """
    from endomeasure.pipeline.report import write_report

    try:
        limits = tuple(float(b) for b in bands.split(","))
    except ValueError:
        limits = ()
    if len(limits) != 2:
        raise _bad_input(f"cannot read the bands {bands!r}", hint="give two percentages: 1,5")
    summary = write_report(
        session, out, depths=None if depths is None else parse_depths(depths), bands=limits
    )
    if json_output:
        _print_json(summary.to_dict())
        return
    console = _stderr_console()
    for section, state in summary.sections.items():
        if state != "present":
            console.print(f"{section}: {state}", markup=False)
    console.print(f"report of {session} written to {summary.out}", markup=False)


PlaneOption = Annotated[
    list[str] | None,
    typer.Option(
        "--plane",
        help="A point of the measurement plane in the left half, U,V px (three times): "
        "the --left points (a depth's 4th) are placed where their ray meets it.",
    ),
]
PlaneRightOption = Annotated[
    list[str] | None,
    typer.Option(
        "--plane-right",
        help="The --plane points in the right half, U,V px (three times); leave out to find them.",
    ),
]


RightOption = Annotated[
    list[str] | None,
    typer.Option(
        "--right",
        help="The same point in the right half, U,V px (repeat); leave out to find it.",
    ),
]
KindOption = Annotated[
    str,
    typer.Option(
        "--kind", help="length, point-line, depth, area, polyline, profile or area-profile."
    ),
]
SamplesOption = Annotated[
    int | None,
    typer.Option("--samples", help="profile: samples per profile (default ~1 per px)."),
]
SlicesOption = Annotated[
    int | None,
    typer.Option("--slices", help="area-profile: slices between the lines (default 5)."),
]
RefOption = Annotated[
    list[str] | None,
    typer.Option(
        "--ref",
        help="profile: a reference-plane point in the left half, U,V px (three times); "
        "default: the best-fit plane.",
    ),
]


@command("measure")
def measure(
    ctx: typer.Context,
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    model: Annotated[
        str,
        typer.Option("--model", help="Calibrated model (with --board-test also 'all')."),
    ] = "raytrace",
    image: Annotated[
        str | None, typer.Option("--image", help="Name of the image the points are on.")
    ] = None,
    left: Annotated[
        list[str] | None,
        typer.Option("--left", help="A point in the left half, U,V px (repeat per point)."),
    ] = None,
    right: RightOption = None,
    kind: KindOption = "length",
    plane: PlaneOption = None,
    plane_right: PlaneRightOption = None,
    warn_percent: Annotated[
        float,
        typer.Option(
            "--warn-percent",
            help="Warn when the predicted 95% error exceeds this percentage of the value.",
        ),
    ] = defaults.WARN_PERCENT,
    sigma: SigmaOption = None,
    board_test: Annotated[
        bool,
        typer.Option("--board-test", help="Measure every test image of a known board instead."),
    ] = False,
    zone_mm: Annotated[
        float, typer.Option("--zone-mm", help="Board test: width of the distance zones, mm.")
    ] = defaults.ZONE_MM,
    plot: Annotated[
        Path | None,
        typer.Option(
            "--plot",
            help="PNG: the automatic matches and epipolar curves, or the board test's "
            "errors (paper Fig. 4).",
        ),
    ] = None,
    patch: Annotated[
        int,
        typer.Option("--patch", help="Automatic matching: correlation patch side, px (odd)."),
    ] = defaults.PATCH_PX,
    ref: RefOption = None,
    samples: SamplesOption = None,
    slices: SlicesOption = None,
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Triangulate points and measure them with a predicted +-, or run the board test.

    A measurement: --image, one --left and one --right per point, --kind. Without --right
    each left point's match is found in the right half automatically (and the other way
    round without --left); a point the search refuses (untextured, repeated texture,
    not seen by both halves) stops the measurement with exit 1. It is stored in the
    session with its uncertainty (unscented transform of the image noise and the
    calibration covariance). --kind profile / area-profile: docs/profile.md. --plane x3:
    the points are placed where their left ray meets
    the plane through three other points (a depth's 4th point only), e.g. a missing
    corner. --board-test: x-/y-segments, point-to-plane distances and square areas on
    every test image, mean error and std per zone, kind and model.
    """
    if board_test:
        points_only = ("image", "left", "right", "kind", "warn_percent", "sigma", "patch",
                       "plane", "plane_right", "ref", "samples", "slices")  # fmt: skip
        _refuse_given(ctx, points_only, "with --board-test", "leave them out")
        _measure_board_test(session, model, zone_mm, plot, json_output)
        return

    from endomeasure.errors import BadInputError
    from endomeasure.pipeline.measure import measure_points

    _refuse_given(ctx, ("zone_mm",), "without --board-test", "leave it out")
    if kind in ("profile", "area-profile"):
        return _measure_profile(ctx, session, model, image, left, kind, ref, samples, slices,
                                patch, plot, json_output)  # fmt: skip
    _refuse_given(ctx, ("ref", "samples", "slices"), f"with --kind {kind}", "they are a profile's")

    if image is None:
        raise BadInputError("a measurement needs --image NAME", hint="or use --board-test")
    if not left and not right:
        raise BadInputError(
            "a measurement needs its points: --left U,V per point (and optionally --right U,V)"
        )

    def run():
        return measure_points(
            session,
            model,
            image,
            None if not left else [parse_pixel(t) for t in left],
            None if not right else [parse_pixel(t) for t in right],
            kind,
            warn_percent=warn_percent,
            sigma=parse_sigma(sigma),
            patch=patch,
            plot=plot,
            plane=None if not plane else [parse_pixel(t) for t in plane],
            plane_right=None if not plane_right else [parse_pixel(t) for t in plane_right],
        )

    _run_measurement(run, _render_points, json_output, session=str(session), model=model,
                     image=image, kind=kind)  # fmt: skip


def _render_points(console: Console, report: Any) -> None:
    if report.matched:
        _render_matches(console, report.matches)
    _render_measurement(console, report)
    if report.plot:
        console.print(f"plot: {report.plot}")


def _run_measurement(run, render, json_output: bool, **context) -> None:
    """Run a measurement; on a refused match show what the search found before the
    one-line error (exit 1); print the JSON document or render the report."""
    from endomeasure.pipeline.measure import MatchRefusedError

    try:
        report = run()
    except MatchRefusedError as exc:
        _report_refusal(exc, json_output, **context)
        raise
    if json_output:
        document = report.to_dict()
        document["measured"] = True
        _print_json(document)
        return
    render(_stderr_console(), report)


def _measure_profile(ctx, session, model, image, left, kind, ref, samples, slices, patch, plot,
                     json_output) -> None:  # fmt: skip
    from endomeasure.errors import BadInputError
    from endomeasure.pipeline.profile import measure_profile

    _refuse_given(ctx, ("right", "sigma", "warn_percent", "plane", "plane_right"),
                  f"with --kind {kind}", "a profile's path is left-half pixels; its +- comes "
                  "from the dense surface")  # fmt: skip
    if image is None:
        raise BadInputError("a measurement needs --image NAME", hint="or use --board-test")

    def run():
        return measure_profile(
            session, model, image, None if not left else [parse_pixel(t) for t in left], kind,
            refs=None if not ref else [parse_pixel(t) for t in ref], samples=samples,
            slices=slices, patch=patch, plot=plot,
        )  # fmt: skip

    _run_measurement(run, _render_profile, json_output, session=str(session), model=model,
                     image=image, kind=kind)  # fmt: skip


def _render_profile(console: Console, r: Any) -> None:
    from rich.table import Table

    plane = r.plane
    table = Table(title=f"{r.kind} on {r.image} ({r.model})", title_justify="left")
    for column in ("slice", "point", "height mm", "+- mm (1 sigma)", "position mm",
                   "position px", "pixel", "coverage %", "gaps"):  # fmt: skip
        table.add_column(column, justify="left" if column in ("point", "gaps") else "right")
    for k, p in enumerate(r.profiles, 1):
        for name, e in (("deepest", p.deepest), ("highest", p.highest)):
            table.add_row(
                str(k) + (" *" if k - 1 == r.extreme_slice else ""), name,
                f"{e.height_mm:+.4f}", f"{e.sigma_mm:.4f}", f"{e.position_mm:.3f}",
                f"{e.position_px:.1f}", "{:.1f},{:.1f}".format(*e.pixel),
                f"{100 * p.coverage:.1f}", str(len(p.gaps)) + (" (touches it)" if e.at_gap else ""),
            )  # fmt: skip
    _print_table(console, table)
    e = r.extreme
    console.print(
        f"extreme: {e.height_mm:+.4f} mm +- {e.sigma_mm:.4f} mm (1 sigma) at "
        f"{e.position_mm:.3f} mm along slice {r.extreme_slice + 1} (pixel "
        f"{e.pixel[0]:.1f},{e.pixel[1]:.1f}); heights positive towards the probe",
        markup=False,
    )
    console.print(
        f"reference plane: {plane.source} ({plane.points} points"
        + (f", {plane.rejected} outliers left out" if plane.rejected else "")
        + (f", RMS {plane.rms_mm:.4f} mm" if plane.source == "best fit" else "")
        + f"), offset +- {plane.cov[2, 2] ** 0.5:.4f} mm",
        markup=False,
    )
    if r.warning:
        console.print(f"[bold red]WARNING: {r.warning}[/bold red]")
    if r.record:
        console.print(f"stored as profile {r.record} in {r.session}", markup=False)
    if r.plot:
        console.print(f"plot: {r.plot}", markup=False)


def _measure_board_test(session, model, zone_mm, plot, json_output) -> None:
    from endomeasure.pipeline.measure import board_test as run_board_test

    console = _stderr_console()
    with _progress(console, "board test", enabled=not json_output) as on_progress:
        report = run_board_test(
            session, model if model else defaults.ALL_MODELS, zone_mm, plot, on_progress=on_progress
        )
    if json_output:
        _print_json(report.to_dict())
    else:
        _render_board_test(console, report)


def _report_refusal(exc: Any, json_output: bool, **request: str) -> None:
    """What the automatic search found, before the refusal's one-line error."""
    if json_output:
        _print_json(
            {
                **request,
                "measured": False,
                "error": _error_text(exc),
                "exit_code": exc.exit_code,
                "matches": [m.to_dict() for m in exc.matches],
                "plot": exc.plot,
            }
        )
        return
    console = _stderr_console()
    _render_matches(console, exc.matches)
    if exc.plot:
        console.print(f"plot: {exc.plot}")


def _render_matches(console: Console, matches: list[Any]) -> None:
    from rich.table import Table

    half = matches[0].half.label if matches else "left"
    other = "right" if half == "left" else "left"
    table = Table(title=f"automatic matches in the {other} half", title_justify="left")
    for column in ("point", f"{half} px", f"{other} px", "score", "precision px",
                   "ray gap mm", "status"):  # fmt: skip
        table.add_column(column, justify="left" if column == "status" else "right")
    for i, m in enumerate(matches, 1):
        found = "{:.2f},{:.2f}".format(*m.match) if m.ok else "-"
        table.add_row(
            str(i),
            "{:.2f},{:.2f}".format(*m.pixel),
            found,
            "-" if m.score != m.score else f"{m.score:.3f}",
            "-" if m.precision_px != m.precision_px else f"{m.precision_px:.3f}",
            f"{m.ray_gap_mm:.4f}" if m.ok else "-",
            m.status.value if m.ok else f"[red]{m.status.value}[/red]",
        )
    _print_table(console, table)


def _render_measurement(console: Console, r: Any) -> None:
    from rich.table import Table

    table = Table(title=f"{r.kind} on {r.image} ({r.model})", title_justify="left")
    for column in (
        "point",
        "left px",
        "right px",
        "x mm",
        "y mm",
        "z mm",
        "ray gap mm",
        "reproj. RMS px",
    ):
        table.add_column(column, justify="right")
    rows = [(f"plane {i}", p) for i, p in enumerate(r.plane or [], 1)]
    for name, p in rows + [(str(i), p) for i, p in enumerate(r.points, 1)]:
        table.add_row(
            name,
            "{:.2f},{:.2f}".format(*p.left),
            "on the plane" if p.projected else "{:.2f},{:.2f}".format(*p.right),
            *(f"{v:.4f}" for v in p.xyz),
            "-" if p.projected else f"{p.gap_mm:.4f}",
            "-" if p.projected else f"{p.rms_px:.3f}",
        )
    _print_table(console, table)
    if r.plane is not None:
        placed = [str(i) for i, p in enumerate(r.points, 1) if p.projected]
        console.print(
            f"point{'s' if len(placed) > 1 else ''} {', '.join(placed)} projected onto the "
            "plane through plane 1-3 along the left ray, not triangulated",
            markup=False,
        )
    e = r.error
    console.print(
        f"[bold]{r.kind} = {e.value:.4f} {r.unit}[/bold]  +- {e.std:.4f} {r.unit} (1 sigma), "
        f"+- {e.ci95:.4f} {r.unit} (95%), predicted bias {e.bias:+.4f} {r.unit}"
    )
    console.print(
        f"uncertainty: {_budget_text(e)} {r.unit} (sigma {_sigma_text(r.noise.sigma)} from "
        f"{r.noise.source}; {r.method.upper()})"
    )
    if r.warning:
        console.print(
            f"[bold red]WARNING: not accurate enough: the predicted 95% error is "
            f"{e.relative_percent:.1f}% of the value (threshold {r.warn_percent:g}%)[/bold red]"
        )
    else:
        console.print(f"accuracy index {e.relative_percent:.2f}% (threshold {r.warn_percent:g}%)")
    if r.record:
        console.print(f"stored as measurement {r.record} in {r.session}")


def _render_board_test(console: Console, report: Any) -> None:
    from rich.table import Table

    table = Table(
        title=f"board test of {report.session} (zones of {report.zone_mm:g} mm)",
        title_justify="left",
    )
    for column in (
        "model",
        "board",
        "kind",
        "zone z mm",
        "n",
        "mean error",
        "std",
        "mean % of true",
    ):
        table.add_column(
            column, justify="left" if column in ("model", "board", "kind") else "right"
        )
    for row in report.summary_rows():
        rel = row["relative_mean_percent"]
        table.add_row(
            row["model"],
            row["board"].removeprefix("chessboard:"),
            row["kind"],
            f"{row['zone_start']:g}-{row['zone_end']:g}",
            str(row["n"]),
            f"{row['mean_error']:+.5f}",
            f"{row['std_error']:.5f}",
            "-" if rel is None else f"{rel:+.3f}",
        )
    _print_table(console, table)
    for name, verdict in report.verdicts.items():
        if verdict == "failed":
            console.print(f"{name}: its calibration failed; figures for comparison only")
    n_images = {name: len(m.images) for name, m in report.models.items()}
    console.print(
        "test images per model: "
        + ", ".join(f"{k} {v}" for k, v in n_images.items())
        + f"; stored in {report.session}"
    )
    if report.plot:
        console.print(f"plot: {report.plot}")


@command("surface")
def surface_command(
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    image: Annotated[str, typer.Option("--image", help="Name of the image.", show_default=False)],
    region: Annotated[
        str | None,
        typer.Option("--region", help="Left-half region U0,V0,U1,V1 px (default: the half)."),
    ] = None,
    model: Annotated[str, typer.Option("--model", help="Calibrated model.")] = "raytrace",
    ply: Annotated[
        Path | None, typer.Option("--ply", help="Write the point cloud (binary PLY).")
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option("--plot", help="PNG: shaded depth and the red/yellow/green mask."),
    ] = None,
    window: Annotated[
        int,
        typer.Option(
            "--window",
            help="Plane-sweep window side, px (odd); the refinement picks its windows per pixel.",
        ),
    ] = defaults.DENSE_WINDOW_PX,
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Dense 3D of a region: depth per left pixel with its sigma, stored in the session.

    Pixels that cannot be measured (untextured, not seen by the right half, a correlation
    too low or a peak beyond the searched stretch) are marked, not guessed. The record
    ``surface/IMAGE.MODEL`` holds the depth map, its sigma and the status per pixel.
    """
    from endomeasure.pipeline.surface import check_region_text, surface

    report = surface(session, image, model, check_region_text(region), ply=ply, plot=plot,
                     window_px=window)  # fmt: skip
    if json_output:
        _print_json(report.to_dict())
        return
    console = _stderr_console()
    u0, v0, u1, v1 = report.region
    console.print(
        f"{report.image} ({report.model}), region {u0},{v0},{u1},{v1}: depth for "
        f"{report.measured} of {report.pixels} px ({100 * report.measured / report.pixels:.1f} %), "
        f"median z {report.median_depth_mm:.3f} mm +- {report.median_sigma_mm:.4f} mm (1 sigma); "
        f"{report.seconds:.1f} s",
        markup=False,
    )
    refused = ", ".join(f"{k} {v}" for k, v in report.counts.items() if k != "ok" and v)
    console.print(f"no depth: {refused or 'none'}", markup=False)
    console.print("mask: " + ", ".join(f"{k} {v}" for k, v in report.classes.items()), markup=False)
    if report.record:
        console.print(f"stored as records/surface/{report.record}", markup=False)
    for what, path in (("point cloud", report.ply), ("plot", report.plot)):
        if path:
            console.print(f"{what}: {path}", markup=False)


@command("predict-error")
def predict_error(
    ctx: typer.Context,
    session: Annotated[
        Path | None,
        typer.Argument(
            help="Session file (.h5); optional with --map --model-file.", show_default=False
        ),
    ] = None,
    model: Annotated[str, typer.Option("--model", help="Calibrated model.")] = "raytrace",
    sigma: SigmaOption = None,
    rho_images: Annotated[
        float, typer.Option("--rho-images", help="Correlation of a point's left/right errors.")
    ] = 0.0,
    rho_points: Annotated[
        float, typer.Option("--rho-points", help="Correlation between different points' errors.")
    ] = 0.0,
    method: Annotated[str, typer.Option("--method", help="ut, linear or mc.")] = "ut",
    samples: Annotated[
        int | None, typer.Option("--samples", help="Monte Carlo samples (default 20000).")
    ] = None,
    no_calibration: Annotated[
        bool,
        typer.Option("--no-calibration", help="Leave the calibration covariance out."),
    ] = False,
    no_model_error: Annotated[
        bool, typer.Option("--no-model-error", help="Leave the calibration's model misfit out.")
    ] = False,
    board_test: Annotated[
        bool, typer.Option("--board-test", help="Predicted vs actual board-test errors.")
    ] = False,
    measurement: Annotated[
        str | None, typer.Option("--measurement", help="Predict one stored measurement (id).")
    ] = None,
    map_mode: Annotated[
        bool, typer.Option("--map", help="Predicted std of a template over the working volume.")
    ] = False,
    model_file: Annotated[
        Path | None,
        typer.Option("--model-file", help="Map: JSON model with nominal parameters."),
    ] = None,
    template: Annotated[
        str,
        typer.Option("--template", help="Map: x-segment, y-segment, z-segment, point-plane, area."),
    ] = "x-segment",
    size_mm: Annotated[float, typer.Option("--size-mm", help="Map: template size, mm.")] = 1.0,
    depths: Annotated[
        str | None,
        typer.Option(
            "--depths",
            help="Map: START:STOP:STEP or z1,z2,... in mm (default: 8 planes over the "
            "calibration's depths; 10:45:5 for a model file).",
        ),
    ] = None,
    grid: Annotated[
        str, typer.Option("--grid", help="Map: NU,NV grid over the left half.")
    ] = "24,18",
    zone_mm: Annotated[
        float | None, typer.Option("--zone-mm", help="Board test: zone width, mm.")
    ] = None,
    plot: Annotated[Path | None, typer.Option("--plot", help="PNG (board test or map).")] = None,
    csv: Annotated[Path | None, typer.Option("--csv", help="Map: data as CSV.")] = None,
    wait_s: WaitOption = defaults.LOCK_WAIT_S,
    json_output: JsonOption = False,
) -> None:
    """Predict measurement errors (bias and std) by the unscented transform.

    Modes: --board-test (predicted vs actual per zone and kind, paper Fig. 5),
    --measurement ID (a stored measurement), --map (a template over the working volume;
    also from --model-file with nominal parameters and no calibration).
    """
    from endomeasure.errors import BadInputError

    _check_predict_mode(ctx, board_test, measurement, map_mode, model_file, method)
    if session is None and not (map_mode and model_file is not None):
        raise BadInputError("a session is needed (only --map --model-file works without one)")
    console = _stderr_console()
    from endomeasure.pipeline.predict import NoiseAssumptions

    noise = NoiseAssumptions(
        sigma=parse_sigma(sigma),
        rho_images=rho_images,
        rho_points=rho_points,
        method=method,
        calibration=not no_calibration,
        model_error=not no_model_error,
        n_samples=samples,
    )
    if board_test:
        from endomeasure.pipeline.predict import predict_board_test

        report = predict_board_test(session, model, noise, zone_mm=zone_mm, plot=plot)
        return _emit(report, json_output, console, _render_board_prediction)
    if measurement is not None:
        from endomeasure.pipeline.predict import predict_stored_measurement

        r = predict_stored_measurement(session, measurement, noise)
        return _emit(r, json_output, console, _render_stored_prediction)
    from endomeasure.pipeline.predict import predict_map

    r = predict_map(
        session,
        model=model,
        model_file=model_file,
        template=template,
        size_mm=size_mm,
        depths=None if depths is None else parse_depths(depths),
        grid=parse_grid(grid),
        noise=noise,
        plot=plot,
        csv=csv,
    )
    _emit(r, json_output, console, _render_map)


def _emit(report: Any, json_output: bool, console: Console, render) -> None:
    """A report as its JSON document on stdout, or rendered for a person on stderr."""
    if json_output:
        _print_json(report.to_dict())
    else:
        render(console, report)


def _budget_text(e: Any) -> str:
    """The std's parts of a PredictedError that were propagated: image noise,
    calibration, model misfit."""
    parts = (("image noise", e.std_image), ("calibration", e.std_calibration),
             ("model", e.std_model))  # fmt: skip
    return ", ".join(f"{name} {v:.4f}" for name, v in parts if v == v)


def _check_predict_mode(ctx, board_test, measurement, map_mode, model_file, method) -> None:
    """One mode of ``predict-error``, and no option that has no effect in it."""
    from endomeasure.errors import BadInputError

    modes = [board_test, measurement is not None, map_mode]
    if sum(modes) != 1:
        raise BadInputError("choose one mode: --board-test, --measurement ID or --map")
    map_only = ("model_file", "template", "size_mm", "depths", "grid", "csv")
    if board_test:
        _refuse_given(ctx, map_only, "with --board-test", "those options are for --map")
    elif measurement is not None:
        _refuse_given(ctx, ("model", *map_only, "zone_mm", "plot"), "with --measurement",
                      "a stored measurement keeps its model and points")  # fmt: skip
    else:
        _refuse_given(ctx, ("zone_mm",), "with --map", "it belongs to --board-test")
        if model_file is not None:
            _refuse_given(ctx, ("model",), "with --model-file", "the file is the model")
    if method != "mc":
        _refuse_given(ctx, ("samples",), f"with --method {method}", "it is for --method mc")


def _noise_text(noise: Any) -> str:
    return (
        f"sigma {_sigma_text(noise.sigma)} ({noise.source}), rho images {noise.rho_images:g}, "
        f"rho points {noise.rho_points:g}"
    )


def _render_stored_prediction(console: Console, r: Any) -> None:
    e = r.error
    console.print(
        f"[bold]{r.measurement}: {r.kind} = {e.value:.4f} {r.unit}[/bold] ({r.model}); "
        f"predicted bias {e.bias:+.4f}, std {e.std:.4f} {r.unit} ({_budget_text(e)}), "
        f"95% +-{e.ci95:.4f} = "
        f"{e.relative_percent:.2f}% of the value; {r.method.upper()}, {_noise_text(r.noise)}"
    )


def _render_map(console: Console, r: Any) -> None:
    from rich.table import Table

    unit = "mm^2" if r.template == "area" else "mm"
    table = Table(
        title=f"predicted error of a {r.size_mm:g} mm {r.template} ({r.model}, {r.source})",
        title_justify="left",
    )
    for column in (
        "z mm",
        "points",
        f"median std {unit}",
        f"max std {unit}",
        f"median bias {unit}",
    ):
        table.add_column(column, justify="right")
    for d in r.per_depth:
        table.add_row(
            f"{d['z_mm']:g}",
            str(d["n"]),
            f"{d['std_median']:.5f}",
            f"{d['std_max']:.5f}",
            f"{d['bias_median']:+.5f}",
        )
    _print_table(console, table)
    console.print(
        f"{_noise_text(r.noise)}, calibration covariance "
        f"{'' if r.calibration else 'not '}included; {r.method.upper()}"
    )
    for label, path in (("plot", r.plot), ("data", r.csv)):
        if path:
            console.print(f"{label}: {path}")


def _render_board_prediction(console: Console, r: Any) -> None:
    from rich.table import Table

    table = Table(
        title=f"predicted vs actual board-test errors ({r.model}, {r.method.upper()}, sigma "
        f"{_sigma_text(r.noise.sigma)} from {r.noise.source}, rho images "
        f"{r.noise.rho_images:g}, rho points {r.noise.rho_points:g})",
        title_justify="left",
    )
    for column in (
        "board",
        "kind",
        "zone z mm",
        "n",
        "actual mean",
        "predicted mean",
        "actual std",
        "predicted std",
        "actual/predicted",
        "in 2-sigma band",
    ):
        table.add_column(column, justify="left" if column in ("board", "kind") else "right")
    for z in r.zones:
        ratio = z["std_ratio"]
        colour = "green" if ratio is not None and 0.75 <= ratio <= 1.25 else "yellow"
        table.add_row(
            z["board"].removeprefix("chessboard:"),
            z["kind"],
            f"{z['zone_start']:g}-{z['zone_end']:g}",
            str(z["n"]),
            f"{z['actual_mean']:+.5f}",
            f"{z['predicted_mean']:+.5f}",
            f"{z['actual_std']:.5f}",
            f"{z['predicted_std']:.5f}",
            "-" if ratio is None else f"[{colour}]{ratio:.2f}[/{colour}]",
            f"{100 * z['within_band']:.0f}%",
        )
    _print_table(console, table)
    console.print(f"errors inside their predicted 2-sigma band: {100 * r.within_band:.1f}%")
    if r.plot:
        console.print(f"plot: {r.plot}")


# ----- verify and compare -------------------------------------------------------------------


@command("verify")
def verify(
    session: Annotated[Path, typer.Argument(help="Session file (.h5).", show_default=False)],
    images: Annotated[
        list[Path],
        typer.Argument(
            help="Image files (or directories of them) of the board, whole in both halves.",
            show_default=False,
        ),
    ],
    board: BoardOption,
    model: Annotated[str, typer.Option("--model", help="Calibrated model.")] = "raytrace",
    json_output: JsonOption = False,
) -> None:
    """Check a stored calibration with a few images of a known board (the session is not
    changed).

    Exit 0: pass. Exit 1: recalibrate (a common length bias, or errors larger than
    predicted, each tested at the 0.5 % level). Exit 2: bad input.
    """
    from endomeasure.errors import GoalNotMetError
    from endomeasure.pipeline.verify import verify_calibration

    report = verify_calibration(session, images, board, model)
    error = (
        "" if report.passed else _one_line("recalibrate: " + "; ".join(report.statistics.reasons))
    )
    if json_output:
        _print_json(_with_error(report.to_dict(), error, 1))
    else:
        _render_verify(_stderr_console(), report)
    if not report.passed:
        raise GoalNotMetError(error)
    sys.stderr.write(f"pass: the {report.model} calibration agrees with {len(report.images)} "
                     f"image(s) of {report.board}\n")  # fmt: skip


def _render_verify(console: Console, r: Any) -> None:
    from rich.table import Table

    s = r.statistics
    table = Table(
        title=f"verify {r.model} with {len(r.images)} image(s) of {r.board} (sigma "
        f"{_sigma_text(r.noise.sigma)} from {r.noise.source})",
        title_justify="left",
    )
    for column in ("kind", "n", "true", "mean error", "mean %", "predicted std", "RMS z",
                   "in 2-sigma band"):  # fmt: skip
        table.add_column(column, justify="left" if column == "kind" else "right")
    for k in s.per_kind:
        table.add_row(
            k["kind"], str(k["n"]), f"{k['true']:g}", f"{k['mean_error']:+.5f}",
            f"{k['relative_mean_percent']:+.3f}", f"{k['predicted_std_rms']:.5f}",
            f"{k['rms_z']:.2f}", f"{100 * k['within_band']:.0f}%",
        )  # fmt: skip
    console.print(table)
    b, d = s.bias, s.dispersion
    console.print(
        f"length bias {100 * b.mean_relative:+.3f} % +-{100 * b.predicted_std:.3f} % "
        f"(z {b.z:+.2f}, p {b.p:.2g}); RMS z {d.rms_z:.2f} (limit {d.rms_z_limit:.2f}, "
        f"p {d.p:.2g}); {100 * s.within_band:.1f}% inside the 2-sigma band; "
        f"each test at p < {b.alpha:g}"
    )


@command("compare")
def compare(
    a: Annotated[Path, typer.Argument(help="Session A (.h5).", show_default=False)],
    b: Annotated[Path, typer.Argument(help="Session B (.h5; may be A).", show_default=False)],
    model: Annotated[str, typer.Option("--model", help="Calibrated model of A.")] = "raytrace",
    model_b: Annotated[
        str | None, typer.Option("--model-b", help="Calibrated model of B (default: --model).")
    ] = None,
    depths: Annotated[
        str | None,
        typer.Option(
            "--depths",
            help="START:STOP:STEP or z1,z2,... in mm (default: 3 planes inside the depths "
            "both calibrations saw).",
        ),
    ] = None,
    grid: Annotated[str, typer.Option("--grid", help="NU,NV grid over A's left half.")] = "16,12",
    plot: Annotated[
        Path | None, typer.Option("--plot", help="PNG of the disagreement maps.")
    ] = None,
    json_output: JsonOption = False,
) -> None:
    """Where and by how much two calibrations disagree (pixels, and a 1 mm length
    against their combined +-).

    Exit 0: agree. Exit 1: disagree (at some depth the RMS of the normalised length
    difference exceeds its limit at the 1 % level). Exit 2: bad input.
    """
    from endomeasure.errors import GoalNotMetError
    from endomeasure.pipeline.compare import compare_calibrations

    report = compare_calibrations(
        a, b, model, model_b, depths=None if depths is None else parse_depths(depths),
        grid=parse_grid(grid), plot=plot,
    )  # fmt: skip
    error = "" if report.agree else _one_line("disagree: " + "; ".join(report.reasons))
    if json_output:
        _print_json(_with_error(report.to_dict(), error, 1))
    else:
        _render_compare(_stderr_console(), report)
    if not report.agree:
        raise GoalNotMetError(error)
    sys.stderr.write(f"agree: {report.model_b} of {b} agrees with {report.model_a} of {a} "
                     "within their combined +-\n")  # fmt: skip


def _render_compare(console: Console, r: Any) -> None:
    from rich.table import Table

    table = Table(
        title=f"{r.model_b} ({r.b}) against {r.model_a} ({r.a}), "
        f"{r.comparison.size_mm:g} mm x-segment",
        title_justify="left",
    )
    for column in ("z mm", "points", "left RMS/max px", "right RMS/max px", "length diff RMS mm",
                   "combined +- mm", "RMS z", "max |z|", "outside 2 sigma"):  # fmt: skip
        table.add_column(column, justify="right")
    for d in r.per_depth:
        colour = "green" if d["agree"] else "red"
        table.add_row(
            f"{d['z_mm']:g}", str(d["n"]), f"{d['left_rms_px']:.3f}/{d['left_max_px']:.3f}",
            f"{d['right_rms_px']:.3f}/{d['right_max_px']:.3f}",
            f"{d['length_diff_rms_mm']:.5f}", f"{d['sigma_rms_mm']:.5f}",
            f"[{colour}]{d['rms_z']:.2f}[/{colour}]", f"{d['max_abs_z']:.2f}",
            f"{100 * d['outside_band']:.0f}%",
        )  # fmt: skip
    console.print(table)
    console.print(f"RMS z limit {r.rms_z_limit:.2f} (level {r.alpha:g} over the depths)")
    if r.plot:
        console.print(f"plot: {r.plot}")


@command("sweep")
def sweep(
    spec: Annotated[Path, typer.Argument(help="Sweep spec (JSON).", show_default=False)],
    output: Annotated[
        Path, typer.Option("-o", "--output", help="Results file (HDF5), resumed if it exists.")
    ] = Path("sweep.h5"),
    scheduler: Annotated[
        str | None, typer.Option("--scheduler", help="A running Dask scheduler, tcp://host:port.")
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option("--workers", help="Local worker processes (default: one per core; 0 serial)."),
    ] = None,
    serial: Annotated[bool, typer.Option("--serial", help="Same as --workers 0.")] = False,
    max_designs: Annotated[
        int | None, typer.Option("--max-designs", help="Evaluate at most this many now.")
    ] = None,
    plot: Annotated[
        Path | None, typer.Option("--plot", help="Figure of the results (.png, .pdf, .svg).")
    ] = None,
    export: Annotated[
        int | None, typer.Option("--export", help="Write this design's preset and model file.")
    ] = None,
    export_dir: Annotated[
        Path | None, typer.Option("--export-dir", help="Folder of --export (default: -o's).")
    ] = None,
    top: Annotated[int, typer.Option("--top", help="Designs shown in the ranked table.")] = 10,
    json_output: JsonOption = False,
) -> None:
    """Sweep probe designs through simulated calibrations and error maps (docs/sweep.md).

    Every design of SPEC the results file lacks is evaluated (its tolerance draws, the
    calibration protocol, the figures of merit) on a Dask cluster, or serially; results
    are written as they arrive, so a rerun computes only the missing designs. Prints the
    designs ranked by the worst 95 % error and the Pareto front against the cost.
    """
    from endomeasure.pipeline.sweep import run_sweep

    console = _stderr_console()
    with _progress(console, "designs", enabled=not json_output) as on_progress:
        report = run_sweep(
            spec,
            output,
            scheduler=scheduler,
            workers=0 if serial else workers,
            max_designs=max_designs,
            on_progress=on_progress,
            plot=plot,
            export=export,
            export_dir=export_dir,
        )
    if json_output:
        _print_json(report.to_dict())
        return
    _render_sweep(console, report, top)


def _render_sweep(console: Console, r: Any, top: int) -> None:
    from rich.table import Table

    table = Table(
        title=f"{len(r.results)}/{r.n_designs} designs of {r.spec} ({r.output}): "
        f"{len(r.computed)} computed now ({r.mode}, {r.seconds:.1f} s), {r.skipped} from before",
        title_justify="left",
    )
    front = {p.index for p in r.pareto}
    for column in (
        "rank",
        "design",
        *r.axis_names,
        "worst 95 % error",
        "calibrated",
        r.cost_name,
        "Pareto",
    ):
        table.add_column(column, justify="right")
    for rank, d in enumerate(r.ranked[: max(top, 0)], 1):
        colour = "green" if d.merit <= r.target_pct and d.success == 1.0 else "red"
        table.add_row(
            str(rank),
            str(d.index),
            *(f"{v:.4g}" for v in d.values),
            f"[{colour}]{d.merit:.3g} %[/{colour}]",
            f"{d.success:.0%}",
            f"{d.cost:.4g}",
            "*" if d.index in front else "",
        )
    _print_table(console, table)
    meets = [d for d in r.ranked if d.merit <= r.target_pct and d.success == 1.0]
    console.print(
        f"{len(meets)} of {len(r.results)} designs meet {r.target_pct:g} %; Pareto "
        f"front ({r.cost_name}): {', '.join(str(p.index) for p in r.pareto) or 'empty'}"
    )
    if r.missing:
        console.print(f"{r.missing} designs not evaluated yet: run the same command again")
    for path in ([r.plot] if r.plot else []) + r.exported:
        console.print(f"wrote {path}")
