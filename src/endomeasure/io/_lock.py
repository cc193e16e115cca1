"""An OS-level lock on a session, held through a sidecar file.

The lock is ``fcntl.flock`` on ``<session>.lock``: exclusive for edits, shared for
reads. The kernel releases a flock when its holder's file descriptor closes, which also
happens when the process is killed, so a crash can never leave a session locked. The
sidecar file may stay on disk. While an exclusive holder works, the file holds one JSON
line saying who it is (pid, host, since when), so that a command waiting for the lock
can name it; the holder empties the file before it lets go. Shared (read) holders write
nothing.

How long to wait, and whom to tell that a command is waiting, is the caller's choice:
the command line sets it once per command with :func:`lock_waiting` (its ``--wait``
option and a callback that prints), and every lock taken inside obeys it. This module
never prints.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import fcntl
import json
import os
import socket
import stat
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from endomeasure.defaults import LOCK_WAIT_S
from endomeasure.errors import SessionError, SessionLockedError

LOCK_SUFFIX = ".lock"
DEFAULT_LOCK_TIMEOUT_S = LOCK_WAIT_S
"""Edits hold the lock only while they write (seconds), so two minutes means a stuck peer."""
WAIT_NOTICE_AFTER_S = 1.0
"""A lock still not granted after this long is announced (once): shorter waits are normal."""
_POLL_INTERVAL_S = 0.02
_HOLDER_INFO_MAX_BYTES = 4096


@dataclass(frozen=True)
class LockWaiting:
    """How the locks taken inside :func:`lock_waiting` wait for another command.

    Attributes
    ----------
    timeout_s : float or None, s
        Longest wait for a lock; 0 tries once; None waits for ever.
    on_wait : callable(str), optional
        Told once, with a one-line message naming the holder, when a lock is still not
        granted after ``notice_after_s``.
    notice_after_s : float, s
    """

    timeout_s: float | None = DEFAULT_LOCK_TIMEOUT_S
    on_wait: Callable[[str], None] | None = None
    notice_after_s: float = WAIT_NOTICE_AFTER_S


_WAITING: contextvars.ContextVar[LockWaiting | None] = contextvars.ContextVar(
    "endomeasure_lock_waiting", default=None
)


@contextlib.contextmanager
def lock_waiting(policy: LockWaiting) -> Iterator[None]:
    """Every :class:`SessionLock` taken in this block waits as ``policy`` says (its
    timeout replaces the one the lock was given)."""
    token = _WAITING.set(policy)
    try:
        yield
    finally:
        _WAITING.reset(token)


def lock_path_for(session_path: Path) -> Path:
    """The sidecar lock file of a session: ``<session>.lock`` in the same directory."""
    return session_path.with_name(session_path.name + LOCK_SUFFIX)


@dataclass(frozen=True)
class LockHolder:
    """Who holds an exclusive lock, as it wrote itself into the lock file."""

    pid: int
    host: str
    since: float  # s since the epoch

    def describe(self) -> str:
        """``PID 123 since 12:46:03`` (with the date when not today, the host when not this one)."""
        moment = time.localtime(self.since)
        today = time.localtime()
        fmt = "%H:%M:%S" if moment[:3] == today[:3] else "%Y-%m-%d %H:%M:%S"
        where = "" if self.host == socket.gethostname() else f" on {self.host}"
        return f"PID {self.pid}{where} since {time.strftime(fmt, moment)}"


def read_holder(lock_file: Path) -> LockHolder | None:
    """The holder a lock file names, or None (empty, unreadable, or a process of this
    host that no longer exists: a holder killed before it could empty the file)."""
    try:
        with open(lock_file, "rb") as stream:
            data = json.loads(stream.read(_HOLDER_INFO_MAX_BYTES).decode("utf-8"))
        holder = LockHolder(int(data["pid"]), str(data["host"]), float(data["since"]))
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError):
        return None
    if holder.host == socket.gethostname():
        try:
            os.kill(holder.pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:  # alive, another user's
            pass
    return holder


def _owner_text(st: os.stat_result) -> str:
    try:
        import pwd

        owner = pwd.getpwuid(st.st_uid).pw_name
    except (ImportError, KeyError):
        owner = f"uid {st.st_uid}"
    return f"owner {owner}, mode {stat.S_IMODE(st.st_mode):04o}"


class SessionLock:
    """A shared or exclusive flock on a session's sidecar lock file.

    Parameters
    ----------
    session_path : Path
    exclusive : bool
        Exclusive for edits, shared for reads.
    timeout : float or None, s
        How long to wait for the lock (0: try once); ``None`` waits forever. Inside
        :func:`lock_waiting` that block's timeout is used instead.
    required : bool
        If False (reads), a lock file that cannot be created (read-only directory) is
        not an error: the read goes ahead unlocked, which is safe because writers only
        ever replace the session file atomically.
    """

    def __init__(
        self,
        session_path: Path,
        *,
        exclusive: bool,
        timeout: float | None = DEFAULT_LOCK_TIMEOUT_S,
        required: bool = True,
    ):
        self.session_path = Path(session_path)
        self.path = lock_path_for(self.session_path)
        self.exclusive = exclusive
        self.timeout = timeout
        self.required = required
        self._fd: int | None = None
        self._wrote_holder = False

    def _open(self) -> tuple[int | None, bool]:
        """The lock file's descriptor (None: go ahead unlocked) and whether it is writable.

        A lock file another user made and this one may not write is opened for reading
        (a flock needs no write access), so it still serialises the commands.
        """
        try:
            return os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666), True
        except OSError as exc:
            denied = exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS)
            if denied and os.path.isfile(self.path):
                try:
                    return os.open(self.path, os.O_RDONLY), False
                except OSError:
                    pass
                if not self.required:
                    return None, False
                raise SessionError(
                    f"cannot open the session's lock file ({exc.strerror}; "
                    f"{_owner_text(os.stat(self.path))})",
                    path=str(self.path),
                    hint="let your user read and write it, or delete it while no endomeasure "
                    "command uses the session",
                ) from None
            if not self.required and denied:
                return None, False
            raise SessionError(
                f"cannot create the session lock file ({exc.strerror})",
                path=str(self.path),
                hint="check that the session's directory exists and is writable",
            ) from None

    def acquire(self) -> None:
        policy = _WAITING.get()
        timeout = self.timeout if policy is None else policy.timeout_s
        mode = fcntl.LOCK_EX if self.exclusive else fcntl.LOCK_SH
        start = time.monotonic()
        deadline = None if timeout is None else start + max(float(timeout), 0.0)
        noticed = policy is None or policy.on_wait is None
        while True:
            fd, writable = self._open()
            if fd is None:
                return
            try:
                while True:
                    try:
                        fcntl.flock(fd, mode | fcntl.LOCK_NB)
                        break
                    except BlockingIOError:
                        now = time.monotonic()
                        if deadline is not None and now >= deadline:
                            raise self._timed_out(timeout) from None
                        if not noticed and now - start >= policy.notice_after_s:
                            noticed = True
                            policy.on_wait(self._waiting_message(timeout))
                        time.sleep(_POLL_INTERVAL_S)
                    except OSError as exc:  # EBADF: an exclusive lock on a read-only file (NFS)
                        raise self._not_writable(exc) from None
                # Someone may have deleted the lock file while we waited; a lock on the
                # unlinked inode would not exclude a process that opens the new file.
                try:
                    same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
                except FileNotFoundError:
                    same = False
                if same and self.exclusive and writable:
                    self._write_holder(fd)
            except BaseException:
                os.close(fd)
                raise
            if same:
                self._fd = fd
                return
            os.close(fd)

    def _write_holder(self, fd: int) -> None:
        info = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.time()}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(info) + "\n").encode("utf-8"), 0)
            self._wrote_holder = True
        except OSError:  # a full disk: the lock holds all the same, unnamed
            pass

    def _holder_text(self) -> str:
        holder = read_holder(self.path)
        return "another endomeasure command" if holder is None else holder.describe()

    def _waiting_message(self, timeout: float | None) -> str:
        bound = "until it is released" if timeout is None else f"up to {timeout:g} s"
        return (
            f"waiting for the lock on {self.session_path.name} held by {self._holder_text()} "
            f"({bound}; --wait SECONDS sets how long)"
        )

    def _timed_out(self, timeout: float | None) -> SessionLockedError:
        holder = read_holder(self.path)
        who = "" if holder is None else f" ({holder.describe()})"
        waited = "" if not timeout else f"; waited {timeout:g} s"
        return SessionLockedError(
            f"the session is locked by another endomeasure command{who}{waited}",
            path=str(self.session_path),
            hint="retry when that command has finished, or wait longer with --wait SECONDS",
        )

    def _not_writable(self, exc: OSError) -> SessionError:
        try:
            owner = "; " + _owner_text(os.stat(self.path))
        except OSError:
            owner = ""
        return SessionError(
            f"cannot lock the session: its lock file is not writable for you "
            f"({exc.strerror}{owner})",
            path=str(self.path),
            hint="let your user write it, or delete it while no endomeasure command uses "
            "the session",
        )

    def release(self) -> None:
        if self._fd is not None:
            if self._wrote_holder:
                with contextlib.suppress(OSError):
                    os.ftruncate(self._fd, 0)  # still held: no one reads a stale holder
                self._wrote_holder = False
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> SessionLock:
        self.acquire()
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()
