"""The domain error family.

Every error the user can cause or meet is an :class:`EndomeasureError`. It carries what
went wrong, which file it concerns and what to do about it; the command line turns it
into one line and an exit code (0 success, 1 ran but failed its goal, 2 bad usage or
bad input). Core code raises these; it never prints and never exits.
"""

from __future__ import annotations


class EndomeasureError(Exception):
    """Base of all endomeasure errors.

    Parameters
    ----------
    what : str
        What is wrong, as one sentence without a trailing full stop.
    path : str, optional
        The file (or object) concerned.
    hint : str, optional
        What the user can do about it.
    """

    exit_code = 2

    def __init__(self, what: str, *, path: str | None = None, hint: str | None = None):
        self.what = what
        self.path = None if path is None else str(path)
        self.hint = hint
        super().__init__(self.one_line())

    def one_line(self) -> str:
        """The message as one line: ``what [file]: hint``."""
        text = self.what
        if self.path:
            text += f" [{self.path}]"
        if self.hint:
            text += f"; {self.hint}"
        return text


class BadInputError(EndomeasureError):
    """Input the tool cannot use: a missing or malformed file, argument or value (exit 2)."""

    exit_code = 2


class SessionError(BadInputError):
    """A session file that cannot be read: not HDF5, truncated, or of an unknown kind."""


class SessionVersionError(SessionError):
    """A session written by a newer, incompatible format version."""


class SessionLockedError(SessionError):
    """Another command held the session's lock for longer than this one would wait."""


class GoalNotMetError(EndomeasureError):
    """The command ran on valid input but could not reach its goal (exit 1)."""

    exit_code = 1


class CalibrationError(GoalNotMetError):
    """A calibration that is refused: too little data, degenerate geometry, no convergence."""
