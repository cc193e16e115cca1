"""Ctrl-C and SIGTERM: one clean path out of any command, and workers that die with it.

A command process takes over SIGINT and SIGTERM from its first line (:func:`install`).
While it starts, parses its options, and once its outcome is decided, a signal is only
remembered; while the command works (:func:`arm` .. :func:`disarm`) the first signal
raises :class:`Interrupted` in the main thread (a ``KeyboardInterrupt``, so no ``except
Exception`` swallows it). Only the first signal raises: later ones are ignored, so that
the clean-up the first one started (temp files removed, worker processes ended) runs to
its end and the user sees one line. Every signal is remembered (:func:`received`): an
interrupt that a library turned into an ordinary error, or swallowed, is still reported
as the interrupt it was; one that Python itself had to drop (raised in a destructor or
a weakref callback, where it would print "Exception ignored") is raised again a moment
later, and so is one that comes while h5py is in control (see :data:`_UNINTERRUPTIBLE`).

:func:`deferred` holds both signals back around a step that must not be cut (the
rename that replaces a session); :func:`worker_initializer` makes a pool worker ignore
both (its parent reports) and die when its parent dies, even by SIGKILL.

Standard library only; nothing here prints or exits the process.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

__all__ = [
    "HANDLED",
    "Interrupted",
    "arm",
    "blocked",
    "deferred",
    "disarm",
    "handling",
    "install",
    "received",
    "settle",
    "worker_initializer",
]

HANDLED = (signal.SIGINT, signal.SIGTERM)
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
_PARENT_POLL_S = 0.5
"""How often a worker without PR_SET_PDEATHSIG checks that its parent still lives."""


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM received by a command; exit code ``128 + signum`` (130, 143)."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = int(signum)
        super().__init__(self.signal_name)

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_RERAISE_AFTER_S = 0.002
"""Delay before an interrupt that was swallowed or held back is raised again (after the
code that swallowed it, or held it back, has returned)."""

_UNINTERRUPTIBLE = ("h5py",)
"""Packages an interrupt is never raised inside; it is raised a moment after they return.
h5py runs Python code inside HDF5's C calls (type conversion, iteration callbacks): an
exception raised there leaves HDF5 in the middle of a call, and h5py prints to stdout
on the way out ("Failed to find converter ..."), which a pipeline reading our stdout
would take as output."""


class _State:
    received: int | None = None  # the first signal, once one came
    deferring = 0  # depth of deferred() blocks
    pending = False  # a signal came inside deferred(): raise when it ends
    reraise = False  # the last raise was swallowed (a destructor, a callback): raise again
    in_hook = False  # the main thread is inside the unraisable hook: do not signal it yet


_STATE = _State()


def _raise_first(signum: int, frame: object) -> None:
    if _STATE.received is not None and not _STATE.reraise:
        return  # the first one is being handled; let its clean-up finish
    if _STATE.received is None:
        _STATE.received = signum
    _STATE.reraise = False
    if _STATE.deferring:
        _STATE.pending = True
        return
    if _inside_uninterruptible(frame):
        _raise_again_soon()
        return
    raise Interrupted(_STATE.received)


def _inside_uninterruptible(frame) -> bool:
    """Whether a frame of one of the :data:`_UNINTERRUPTIBLE` packages is on the stack."""
    while frame is not None:
        module = frame.f_globals.get("__name__") or ""
        if module.partition(".")[0] in _UNINTERRUPTIBLE:
            return True
        frame = frame.f_back
    return False


def _raise_again_soon() -> None:
    timer = threading.Timer(_RERAISE_AFTER_S, _trip_again)
    timer.daemon = True
    timer.start()


def _unraisable(hook_args) -> None:
    """``sys.unraisablehook``: an interrupt raised where Python cannot propagate it (a
    ``__del__``, a weakref callback, the garbage collector) is raised again a moment
    later, in the code that runs then, instead of being printed and lost."""
    if isinstance(hook_args.exc_value, KeyboardInterrupt) and _STATE.received is not None:
        # the flag is set by the timer, not here, and only once this hook has returned:
        # starting a thread waits on a lock, and a raise inside this hook would be
        # dropped (and printed) in its turn
        _STATE.in_hook = True
        _raise_again_soon()
        _STATE.in_hook = False  # no call follows before the return: no handler runs here
        return
    _PREVIOUS_UNRAISABLEHOOK(hook_args)


_PREVIOUS_UNRAISABLEHOOK = sys.unraisablehook


def _trip_again() -> None:
    while _STATE.in_hook:
        time.sleep(_RERAISE_AFTER_S)
    if _STATE.received is not None:
        _STATE.reraise = True
        os.kill(os.getpid(), _STATE.received)  # its handler runs in the main thread


def _remember(signum: int, frame: object) -> None:
    if _STATE.received is None:
        _STATE.received = signum


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _can_block() -> bool:
    return hasattr(signal, "pthread_sigmask") and _in_main_thread()


def install() -> None:
    """Take over SIGINT and SIGTERM in this process (main thread only), at first only
    remembering them: :func:`arm` makes them raise. A signal the process was started
    with ignored (``nohup``, a background job) stays ignored."""
    if not _in_main_thread():
        return
    for signum in HANDLED:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _remember)
    sys.unraisablehook = _unraisable
    _reset()


def _reset() -> None:
    _STATE.received, _STATE.deferring, _STATE.pending, _STATE.reraise = None, 0, False, False


def _set_mode(handler) -> None:
    if not _in_main_thread():
        return
    for signum in HANDLED:
        if signal.getsignal(signum) in (_raise_first, _remember):
            signal.signal(signum, handler)


def arm() -> None:
    """From now on the first signal raises :class:`Interrupted`; one remembered before
    (while the process started, or parsed its options) raises now."""
    _set_mode(_raise_first)
    came = received()
    if came is not None:
        raise came


def disarm() -> None:
    """From now on a signal is only remembered: the command's outcome is decided (its
    line written, or its work done), and the process ends with that outcome."""
    _set_mode(_remember)


def settle() -> None:
    """The process ends now, with its outcome decided: both signals are ignored from
    here on. (Python's own shutdown sets handlers written in Python back to the
    default, so a signal in its last milliseconds would kill the process without its
    line or its exit code; an ignored signal it leaves ignored.)"""
    if not _in_main_thread():
        return
    for signum in HANDLED:
        if signal.getsignal(signum) in (_raise_first, _remember):
            signal.signal(signum, signal.SIG_IGN)


def received() -> Interrupted | None:
    """The interrupt this process received (whether or not it reached the caller), or None."""
    return None if _STATE.received is None else Interrupted(_STATE.received)


def _installed() -> bool:
    return any(signal.getsignal(s) in (_raise_first, _remember) for s in HANDLED)


@contextlib.contextmanager
def handling() -> Iterator[None]:
    """:func:`install` for a block, and the handlers from before restored after it (a
    command run inside another program, e.g. a test, leaves no trace). In a process that
    installed them for good (the command's own) this changes nothing."""
    if not _in_main_thread() or _installed():
        yield
        return
    saved = {signum: signal.getsignal(signum) for signum in HANDLED}
    saved_hook = sys.unraisablehook
    install()
    try:
        yield
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)
        sys.unraisablehook = saved_hook
        _reset()


@contextlib.contextmanager
def blocked() -> Iterator[None]:
    """SIGINT and SIGTERM held back in this thread for the block; one that came meanwhile
    is delivered (and raises) when the block ends. Processes forked inside the block start
    with both blocked, until :func:`worker_initializer` sets them up."""
    if not _can_block():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, HANDLED)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)  # runs the handlers of pending ones


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back for a step that must not be cut short (replacing a
    session): an interrupt that came before, also one a library swallowed, is raised
    instead of starting the step; one that comes during it raises right after it.

    The signal is held back in its handler, not by a signal mask: the handler runs in
    the main thread whichever thread the kernel chose (OpenCV's or the pool's threads do
    not block signals).
    """
    came = received()
    if came is not None:
        raise came
    _STATE.deferring += 1
    try:
        yield
    finally:
        _STATE.deferring -= 1
        if not _STATE.deferring and _STATE.pending:
            _STATE.pending = False
            raise Interrupted(_STATE.received)


def worker_initializer(parent_pid: int) -> None:
    """Set up a pool worker: SIGINT ignored (the parent reports the interrupt and ends
    the pool), SIGTERM back to its default (ending the worker at once), and the worker
    killed when its parent dies (``PR_SET_PDEATHSIG`` on Linux; elsewhere a thread that
    watches the parent's pid).

    Parameters
    ----------
    parent_pid : int
        The pid of the process that started the pool.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    sys.unraisablehook = _PREVIOUS_UNRAISABLEHOOK
    _reset()
    if hasattr(signal, "pthread_sigmask"):  # the parent forked it with both blocked
        signal.pthread_sigmask(signal.SIG_UNBLOCK, HANDLED)
    if not _die_with_parent():
        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before the watch was set up
        os.kill(os.getpid(), signal.SIGKILL)


def _die_with_parent() -> bool:
    """Ask Linux to SIGKILL this process when its parent ends; False where unavailable."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(_PARENT_POLL_S)
    os.kill(os.getpid(), signal.SIGKILL)
