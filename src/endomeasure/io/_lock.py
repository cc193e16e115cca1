"""An OS-level lock on a session, held through a sidecar file.

The lock is ``fcntl.flock`` on ``<session>.lock``: exclusive for edits, shared for
reads. The kernel releases a flock when its holder's file descriptor closes, which also
happens when the process is killed, so a crash can never leave a session locked. The
sidecar file itself may stay on disk; it carries no information.
"""

from __future__ import annotations

import errno
import fcntl
import os
import time
from pathlib import Path

from endomeasure.errors import SessionError

LOCK_SUFFIX = ".lock"
DEFAULT_LOCK_TIMEOUT_S = 120.0
"""Edits hold the lock only while they write (seconds), so two minutes means a stuck peer."""
_POLL_INTERVAL_S = 0.02


def lock_path_for(session_path: Path) -> Path:
    """The sidecar lock file of a session: ``<session>.lock`` in the same directory."""
    return session_path.with_name(session_path.name + LOCK_SUFFIX)


class SessionLock:
    """A shared or exclusive flock on a session's sidecar lock file.

    Parameters
    ----------
    session_path : Path
    exclusive : bool
        Exclusive for edits, shared for reads.
    timeout : float or None, s
        How long to wait for the lock; ``None`` waits forever.
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

    def acquire(self) -> None:
        mode = fcntl.LOCK_EX if self.exclusive else fcntl.LOCK_SH
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                if not self.required and exc.errno in (errno.EACCES, errno.EROFS, errno.EPERM):
                    return
                raise SessionError(
                    f"cannot create the session lock file ({exc.strerror})",
                    path=str(self.path),
                    hint="check that the session's directory exists and is writable",
                ) from exc
            try:
                while True:
                    try:
                        fcntl.flock(fd, mode | fcntl.LOCK_NB)
                        break
                    except BlockingIOError:
                        if deadline is not None and time.monotonic() >= deadline:
                            raise SessionError(
                                "the session is locked by another endomeasure command",
                                path=str(self.session_path),
                                hint="wait for that command to finish, then retry",
                            ) from None
                        time.sleep(_POLL_INTERVAL_S)
                # Someone may have deleted the lock file while we waited; a lock on the
                # unlinked inode would not exclude a process that opens the new file.
                try:
                    same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
                except FileNotFoundError:
                    same = False
            except BaseException:
                os.close(fd)
                raise
            if same:
                self._fd = fd
                return
            os.close(fd)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> SessionLock:
        self.acquire()
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()
