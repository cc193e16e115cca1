"""Checking the files a command will write before it computes anything.

Every file a command writes besides its session (an exported model, a plot, a CSV, a
folder of plots, a simulated image set) goes through :func:`checked_output` or
:func:`checked_output_dir` at the start of the command, so that a path that would
destroy something the user did not ask to replace is refused in one line before any
work, and never after seconds of computing or after a model was already stored:

- the session itself or another input of the command (compared by inode, so a symlink
  or a hard link to it is caught too);
- an existing file that is not a regular file (a directory, a device such as
  ``/dev/full``, a FIFO, a socket), which a rename would replace;
- a folder that does not exist or where no file can be created (read-only, ``/proc``).

Session files themselves are checked by :func:`checked_session_target` when a command
is about to create or edit one. Standard library only.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from collections.abc import Iterable
from pathlib import Path

from endomeasure.errors import BadInputError, SessionError

__all__ = [
    "PLOT_SUFFIXES",
    "SESSION_TMP_SUFFIX",
    "atomic_write",
    "checked_output",
    "checked_output_dir",
    "checked_outputs",
    "checked_session_target",
    "file_kind",
    "is_regular_file",
]

PLOT_SUFFIXES = (".png", ".pdf", ".svg")
"""Picture formats the plots are written in (matplotlib picks the format by the suffix)."""


def file_kind(mode: int) -> str:
    """A name for the type of file of an ``st_mode``: 'directory', 'FIFO', ..."""
    for test, name in (
        (stat.S_ISDIR, "directory"),
        (stat.S_ISFIFO, "FIFO (named pipe)"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISREG, "regular file"),
    ):
        if test(mode):
            return name
    return "special file"


def is_regular_file(path: str | os.PathLike) -> bool:
    """True for an existing regular file (after symlinks); never opens the file, so a FIFO
    cannot block."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def _stat_or_none(path, error: type[BadInputError], what: str, shown) -> os.stat_result | None:
    """``os.stat`` of ``path``, None if it does not exist; any other failure is one
    ``error`` naming ``what`` and ``shown``."""
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise error(f"cannot use the {what} ({exc.strerror or exc})", path=str(shown)) from None


def _same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _probe_folder(
    folder: Path, path: Path, what: str, prefix: str = ".endomeasure-probe-", suffix: str = ""
) -> None:
    """Refuse a folder where no file can be created, by creating (and removing) one.

    ``os.access`` is not enough: it says yes to root everywhere, also in ``/proc``.
    """
    try:
        fd, name = tempfile.mkstemp(dir=folder, prefix=prefix, suffix=suffix)
    except OSError as exc:
        raise BadInputError(
            f"cannot write the {what} there: no file can be created in its folder "
            f"({exc.strerror or exc})",
            path=str(path),
            hint="choose a writable folder",
        ) from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)


def checked_output(
    path: str | os.PathLike,
    what: str,
    *,
    inputs: Iterable[str | os.PathLike | None] = (),
    suffixes: Iterable[str] | None = None,
) -> Path:
    """The file to write for an output ``path``, or a :class:`BadInputError`.

    Parameters
    ----------
    path : path-like
        The output file as given.
    what : str
        What it is, for the message ("plot", "CSV file", "exported model").
    inputs : iterable of path-like or None
        Files the command reads (the session, a model file): the output must not be
        one of them.
    suffixes : iterable of str, optional
        Accepted suffixes (lower case, with the dot), for outputs whose format the
        suffix chooses.

    Returns
    -------
    Path
        ``path`` itself, or the target of ``path`` when it is a symlink to a regular
        file, so that writing replaces the target and keeps the link.
    """
    path = Path(path)
    if not str(path) or str(path) in (".", ".."):
        raise BadInputError(f"the {what} needs a file name", path=str(path))
    for source in inputs:
        if source is not None and _same_file(path, source):
            raise BadInputError(
                f"the {what} would overwrite the command's input {os.fspath(source)!r}",
                path=str(path),
                hint="choose another output file name",
            )
    if suffixes is not None:
        allowed = tuple(suffixes)
        if path.suffix.lower() not in allowed:
            raise BadInputError(
                f"the {what} must be a {' / '.join(s.lstrip('.').upper() for s in allowed)} "
                f"file, not {path.suffix or 'a name without a suffix'}",
                path=str(path),
                hint=f"give a name ending in {' or '.join(allowed)}",
            )
    st = _stat_or_none(path, BadInputError, f"{what} path", path)
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise BadInputError(
            f"the {what} exists and is a {file_kind(st.st_mode)}, not a regular file",
            path=str(path),
            hint="give the name of a file to write",
        )
    target = Path(os.path.realpath(path)) if path.is_symlink() else path
    folder = target.parent
    if not folder.is_dir():
        raise BadInputError(
            f"the folder of the {what} does not exist",
            path=str(path),
            hint=f"create {str(folder)!r} first",
        )
    _probe_folder(folder, path, what)
    return target


def checked_outputs(
    outputs: Iterable[tuple[str | os.PathLike | None, str, Iterable[str] | None]],
    *,
    inputs: Iterable[str | os.PathLike | None] = (),
) -> list[Path | None]:
    """:func:`checked_output` for several outputs ``(path or None, what, suffixes)`` of
    one command, which must also differ from each other; None stays None."""
    inputs = list(inputs)
    checked: list[Path | None] = []
    seen: dict[str, str] = {}
    for path, what, suffixes in outputs:
        if path is None:
            checked.append(None)
            continue
        target = checked_output(path, what, inputs=inputs, suffixes=suffixes)
        key = os.path.realpath(target)
        if key in seen:
            raise BadInputError(
                f"the {what} and the {seen[key]} are the same file",
                path=str(path),
                hint="give each output its own name",
            )
        seen[key] = what
        checked.append(target)
    return checked


def checked_output_dir(path: str | os.PathLike, what: str, *, create_parents: bool = False) -> Path:
    """An output folder (created later if missing), or a :class:`BadInputError`.

    The folder may exist (it must then be a directory where files can be created) or
    not: then its parent must exist (any existing ancestor with ``create_parents``) and
    be writable. Nothing is created here.
    """
    path = Path(path)
    st = _stat_or_none(path, BadInputError, what, path)
    if st is not None:
        if not stat.S_ISDIR(st.st_mode):
            raise BadInputError(
                f"the {what} exists and is a {file_kind(st.st_mode)}, not a folder",
                path=str(path),
                hint="give a folder name",
            )
        _probe_folder(path, path, what)
        return path
    parent = Path(os.path.abspath(path)).parent
    if create_parents:
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
    if not parent.is_dir():
        raise BadInputError(
            f"the folder that would hold the {what} does not exist",
            path=str(path),
            hint=f"create {str(parent)!r} first",
        )
    _probe_folder(parent, path, what)
    return path


SESSION_TMP_SUFFIX = ".endomeasure-tmp"
"""Suffix of a session's temporary files (``.<session name>.*<suffix>``): a writer removes
those a killed edit left, and the folder probe of a session is named the same way."""


def checked_session_target(path: str | os.PathLike, *, create: bool, probe: bool = True) -> Path:
    """The file an edit of the session ``path`` writes, or a :class:`BadInputError`.

    A symlink is resolved, so the edit replaces its target and keeps the link. A session
    with more than one hard link is refused: an edit replaces the file atomically by a
    new one (a crash can then never leave a half-written session), which would split the
    links, leaving the other names on the old content. An existing path must be a
    regular file (a FIFO or a device is refused before anything opens it); a new one
    needs an existing, writable folder (``probe`` creates and removes a file there to
    know; the edit itself, which creates its copy there anyway, does without).
    """
    given = Path(path)
    target = Path(os.path.realpath(given)) if given.is_symlink() else given
    st = _stat_or_none(target, SessionError, "session path", given)
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise SessionError(
            f"the session path is a {file_kind(st.st_mode)}, not a session file",
            path=str(given),
            hint="give an endomeasure session file (.h5)",
        )
    if st is not None and st.st_nlink > 1:
        raise SessionError(
            f"the session file has {st.st_nlink} hard links; an edit replaces the file "
            "and would leave the other names on the old content",
            path=str(given),
            hint="edit a copy of its own (cp SESSION NEW.h5), or remove the other links",
        )
    if st is None and not create:
        raise SessionError(
            "the session file does not exist",
            path=str(given),
            hint="check the path, or start a session with a command that creates one",
        )
    if not target.parent.is_dir():
        raise SessionError(
            "the session's directory does not exist",
            path=str(given),
            hint="create the directory first",
        )
    if probe:
        try:
            _probe_folder(target.parent, given, "session", f".{target.name}.", SESSION_TMP_SUFFIX)
        except BadInputError as exc:
            raise SessionError(exc.what, path=str(given), hint=exc.hint) from None
    return target


def atomic_write(path: str | os.PathLike, write) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it over ``path``.

    The temporary name keeps ``path``'s suffix (``cv2.FileStorage`` picks the format by it);
    a replaced file keeps its mode; the temporary file never stays behind. Returns ``path``.
    """
    path = Path(path)
    tmp = path.with_name(f".tmp{os.getpid()}-{path.name}")
    try:
        write(tmp)
        if path.exists():  # a replaced file keeps its permissions
            shutil.copymode(path, tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
