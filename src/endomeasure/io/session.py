"""The session file: one HDF5 file holding everything about one probe and its images.

This is the only module (with its ``io`` siblings) that imports h5py. Everything it
returns is plain Python or NumPy; h5py objects never leave it. The on-disk layout is
specified in ``docs/session-format.md``.

Reading
-------
``open_session(path)`` returns a :class:`Session`, a read-only snapshot; use it as a
context manager::

    with open_session("probe.h5") as s:
        meta = s.metadata()                 # SessionMetadata(image_size, split, ...)
        for info in s.images_info("calib"):  # ImageInfo(name, shape, sha256, ...)
            pixels = s.image(info.name)      # ndarray (H, W) or (H, W, C), uint8/uint16
        boards = s.boards()                  # {name: Board(name, spec, attrs)}
        dets = s.detections(board="cb1", half="left")   # [Detection, ...]
        model = s.model("raytrace")          # ModelRecord(params, param_names, config, ...)
        recs = s.records("measurement")      # [Record(kind, name, attrs, arrays, units)]

The snapshot stays consistent while it is open even if another command edits the
session meanwhile, because writers never modify a session file in place: they replace it
atomically with a new file, and an open file keeps reading the old one.

Writing
-------
``edit_session(path, create=False)`` is a context manager yielding a
:class:`SessionWriter` (which can also read, like :class:`Session`, and sees its own
edits)::

    with edit_session("probe.h5", create=True) as w:
        w.set_metadata(image_size=(1280, 720), split=640)
        w.write_images([ImageRecord(name, pixels, original_path, sha256, "calib"), ...])
        w.write_board("cb1", "chessboard:9x6:1.0", {"cols": 9, "rows": 6, "square_mm": 1.0})
        w.write_detections([Detection(image, "cb1", Half.LEFT, ids, pixels, quality, "")])
        w.write_model(ModelRecord("raytrace", "raytrace", params, names, config,
                                  arrays={"covariance": cov}, attrs={"rms": 0.12},
                                  units={"rms": "px"}))
        w.write_record(Record("measurement", "m001", attrs={...}, arrays={...}))

All edits of one ``with`` block form one transaction. The session's lock (an exclusive
``flock`` on ``<session>.lock``) is held for the whole block, the current file is read
and its checksum checked (:mod:`endomeasure.io.integrity`), the edits go to a copy in
memory, and on success the copy gets its new manifest and checksum and is written to a
temporary file beside the session, fsynced and renamed over it (then the directory is
fsynced). If the block raises, the disk is full, or the process dies, the session file
is untouched. Keep the block short:
compute first (from a snapshot), then open the edit to store the results; a second
command that edits meanwhile is serialised by the lock and its work is kept, because each
edit starts from the file as it is when the lock is granted.

Errors
------
A missing file, a file that is not HDF5, a truncated or damaged file (its checksum fails:
the message names the damaged items), or an HDF5 file that is not a session raise
:class:`~endomeasure.errors.SessionError`; a session written by an unknown major format
version raises
:class:`~endomeasure.errors.SessionVersionError` naming both versions. Asking for an item
the session does not hold raises :class:`~endomeasure.errors.BadInputError` listing what
is there.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import math
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from endomeasure import __version__, interrupts
from endomeasure.conventions import Half
from endomeasure.defaults import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, MAX_STORED_ELEMENTS
from endomeasure.errors import (
    BadInputError,
    EndomeasureError,
    SessionError,
    SessionVersionError,
)
from endomeasure.io._lock import DEFAULT_LOCK_TIMEOUT_S, SessionLock
from endomeasure.io.image_header import checked_image_size
from endomeasure.io.integrity import (
    CONTAINERS,
    USERBLOCK_SIZE,
    DamageReport,
    FileCheck,
    check_file,
    check_image,
    damage_report,
    item_paths,
    seal_image,
    write_manifest,
)
from endomeasure.io.outputs import (
    SESSION_TMP_SUFFIX,
    checked_session_target,
    file_kind,
    is_regular_file,
)

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "IMAGE_SETS",
    "Board",
    "Detection",
    "ImageInfo",
    "ImageRecord",
    "ModelRecord",
    "Record",
    "Session",
    "SessionMetadata",
    "SessionWriter",
    "edit_session",
    "open_session",
]

FORMAT_NAME = "session"
"""Value of the root attribute ``endomeasure_format``."""
FORMAT_VERSION = "1.1"
"""The version this code writes; it reads every ``1.x``. 1.1 added the checksums
(:mod:`endomeasure.io.integrity`); a 1.0 file is read unchecked and upgraded by its
first edit."""
_READ_MAJOR = 1
_WRITE_VERSION = tuple(int(n) for n in FORMAT_VERSION.split("."))
_NODE_VERSION = "1.0"
IMAGE_SETS = ("calib", "test", "scene")
"""Image sets: calibration images, test images of a known board, scenes to measure."""

_TMP_SUFFIX = SESSION_TMP_SUFFIX
_NAME_RE = re.compile(r"^[^/\x00]+$")
_RESERVED_ATTRS = frozenset({"type", "version", "json_attrs"})
_UNITS_PREFIX = "units:"
_IMAGE_COMPRESSION_LEVEL = 4
"""gzip level for images: near the best ratio on camera images at a fraction of level 9's time."""


# --------------------------------------------------------------------------- records


@dataclass(frozen=True)
class SessionMetadata:
    """Session-wide facts.

    Attributes
    ----------
    format_version : str
        ``major.minor`` of the file.
    created_by : str
        The program that created the file.
    image_size : (width, height) or None, px
    split : int or None, px
        First column of the right half.
    attrs : dict
        Any further metadata (for example how the split was found).
    """

    format_version: str
    created_by: str
    image_size: tuple[int, int] | None = None
    split: int | None = None
    attrs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ImageRecord:
    """An image to embed, or one read back with its pixels.

    Attributes
    ----------
    name : str
        Unique key within the session (usually the file's stem).
    pixels : ndarray, shape (H, W) or (H, W, C), uint8 or uint16, DN
        Grey or colour (channel order given by ``channel_order``).
    original_path : str
        Where the image came from (as given by the user).
    sha256 : str
        SHA-256 (hex) of the original file's bytes.
    image_set : str
        One of :data:`IMAGE_SETS`.
    channel_order : str
        ``"gray"``, ``"BGR"`` or ``"BGRA"``; inferred from the shape when empty.
    frame : int or None
        Frame number (from 0) in the video ``original_path`` for a frame taken from a
        video (``sha256`` is then the video file's); None for an image file.
    """

    name: str
    pixels: np.ndarray
    original_path: str
    sha256: str
    image_set: str
    channel_order: str = ""
    frame: int | None = None


@dataclass(frozen=True)
class ImageInfo:
    """An embedded image's description, without its pixels."""

    name: str
    original_path: str
    sha256: str
    image_set: str
    shape: tuple[int, ...]
    dtype: str
    channel_order: str
    frame: int | None = None
    """Frame number in the video ``original_path``; None for an image file."""


@dataclass(frozen=True)
class Board:
    """A calibration target: its spec string and the parsed values (``cols``, ``square_mm``...)."""

    name: str
    spec: str
    attrs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Detection:
    """The corners of one board found in one half of one image.

    Attributes
    ----------
    image, board : str
        Names of the image and board in the session.
    half : Half
    ids : ndarray, shape (N,), int32
        Corner ids (``row * cols + col``).
    pixels : ndarray, shape (N, 2), float64, px
        Full-image pixel coordinates of the corners.
    quality : float
        Detector-defined sharpness/quality figure (NaN when not computed).
    failure : str
        Why the half failed; empty when the detection succeeded.
    attrs : dict
        Further detector output.
    covariance : ndarray, shape (N, 2, 2), float64, px^2, or None
        Each corner's formal covariance from the image noise (NaN where unknown); None
        when the detector gave none.
    """

    image: str
    board: str
    half: Half
    ids: np.ndarray
    pixels: np.ndarray
    quality: float = math.nan
    failure: str = ""
    attrs: dict[str, Any] = field(default_factory=dict)
    covariance: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return not self.failure


@dataclass(frozen=True)
class ModelRecord:
    """A camera model (usually a calibration result) stored by name.

    Attributes
    ----------
    name : str
        Key in the session (for example ``"pinhole"`` or ``"raytrace-free-n"``).
    registry_name : str
        The model registry's name of the model type.
    params : ndarray, shape (P,), float64
    param_names : tuple of str, length P
    config : dict
        Fixed configuration, JSON-serialisable.
    arrays : dict of str to ndarray
        Further named arrays: covariance, residuals, per-image RMS, ...
    attrs : dict
        Further scalars and strings (``rms``, solver status, ...).
    units : dict of str to str
        Unit of any entry of ``arrays`` or ``attrs`` (``{"rms": "px"}``).
    """

    name: str
    registry_name: str
    params: np.ndarray
    param_names: tuple[str, ...]
    config: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Record:
    """A generic named result (a measurement, a prediction, simulator truth ...).

    Attributes
    ----------
    kind : str
        The collection it belongs to (``"measurement"``, ``"prediction"``, ...).
    name : str
        Key within the kind.
    attrs : dict
        Scalars, strings, lists; anything else JSON-serialisable is stored as JSON.
    arrays : dict of str to ndarray
        Numeric or string arrays.
    units : dict of str to str
        Unit of any entry of ``arrays`` or ``attrs``.
    """

    kind: str
    name: str
    attrs: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)


# --------------------------------------------------------------------------- helpers


def _parse_version(text: Any, where: str, path: str) -> tuple[int, int]:
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    match = re.fullmatch(r"(\d+)\.(\d+)", str(text).strip())
    if match is None:
        raise SessionError(
            f"malformed format version {text!r} on {where}",
            path=path,
            hint="the file was not written by endomeasure or is damaged",
        )
    return int(match.group(1)), int(match.group(2))


def _check_major(version: str, where: str, path: str) -> None:
    major, _ = _parse_version(version, where, path)
    if major != _READ_MAJOR:
        newer = major > _READ_MAJOR
        raise SessionVersionError(
            f"{where} has session format version {version}, "
            f"this endomeasure {__version__} reads version {_READ_MAJOR}.x",
            path=path,
            hint=(
                "open it with a newer endomeasure"
                if newer
                else "convert it with the endomeasure release that wrote it"
            ),
        )


def _check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not _NAME_RE.match(name) or name in (".", ".."):
        raise BadInputError(
            f"invalid {what} name {name!r}",
            hint="use a non-empty name without '/'",
        )
    return name


def _attr_to_python(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "OSU":
            return [v.decode("utf-8") if isinstance(v, bytes) else str(v) for v in value.ravel()]
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _is_plain_attr(value: Any) -> bool:
    if isinstance(value, str):
        return "\x00" not in value  # HDF5 strings cannot hold NUL; JSON escapes it
    if isinstance(value, int) and not isinstance(value, bool):
        return -(2**63) <= value < 2**63  # larger integers go through JSON
    if isinstance(value, (bool, float, np.generic)):
        return True
    if isinstance(value, (list, tuple, np.ndarray)):
        arr = np.asarray(value)
        return arr.ndim == 1 and arr.size > 0 and arr.dtype.kind in "biuf"
    return False


def _write_attrs(node: Any, attrs: Mapping[str, Any], units: Mapping[str, str]) -> None:
    json_names = set(_attr_to_python(node.attrs.get("json_attrs", np.array([], dtype=object))))
    json_names -= set(attrs)
    for key, value in attrs.items():
        if key in _RESERVED_ATTRS or key.startswith(_UNITS_PREFIX):
            raise BadInputError(f"attribute name {key!r} is reserved by the session format")
        if _is_plain_attr(value):
            node.attrs[key] = np.asarray(value) if isinstance(value, (list, tuple)) else value
        else:
            try:
                node.attrs[key] = json.dumps(value, allow_nan=True)
            except TypeError as exc:
                raise BadInputError(
                    f"attribute {key!r} cannot be stored: {exc}",
                    hint="use numbers, strings, lists or dicts of them",
                ) from exc
            json_names.add(key)
    if json_names:
        node.attrs["json_attrs"] = np.array(sorted(json_names), dtype=h5py.string_dtype())
    elif "json_attrs" in node.attrs:
        del node.attrs["json_attrs"]
    for key, unit in units.items():
        if key in attrs:
            node.attrs[_UNITS_PREFIX + key] = str(unit)


def _read_attrs(node: Any, skip: Iterable[str] = ()) -> tuple[dict[str, Any], dict[str, str]]:
    skip = set(skip) | _RESERVED_ATTRS
    raw = {key: node.attrs[key] for key in node.attrs.keys()}
    json_names = set(_attr_to_python(raw.get("json_attrs", np.array([], dtype=object))))
    attrs: dict[str, Any] = {}
    units: dict[str, str] = {}
    for key, value in raw.items():
        if key.startswith(_UNITS_PREFIX):
            units[key[len(_UNITS_PREFIX) :]] = _attr_to_python(value)
        elif key not in skip:
            value = _attr_to_python(value)
            attrs[key] = json.loads(value) if key in json_names else value
    return attrs, units


def _stamp(node: Any, type_name: str) -> None:
    node.attrs["type"] = type_name
    node.attrs["version"] = _NODE_VERSION


def _write_array(group: Any, name: str, value: Any, unit: str | None = None) -> None:
    _check_name(name, "array")
    if name in group:
        del group[name]
    arr = np.asarray(value)
    if arr.dtype.kind in "US" or (
        arr.dtype.kind == "O" and all(isinstance(v, str) for v in arr.ravel())
    ):
        dset = group.create_dataset(
            name,
            data=np.array([str(v) for v in arr.ravel()], dtype=h5py.string_dtype()).reshape(
                arr.shape
            ),
        )
    elif arr.dtype.kind in "biuf":
        dset = group.create_dataset(name, data=arr)
    else:
        raise BadInputError(
            f"array {name!r} of dtype {arr.dtype} cannot be stored",
            hint="store numeric or string arrays",
        )
    if unit:
        dset.attrs["units"] = str(unit)


def _read(dset: Any) -> Any:
    """All of a dataset, after checking its declared size: a crafted shape is refused
    (as damage) before h5py allocates it."""
    if dset.size > MAX_STORED_ELEMENTS:
        raise ValueError(
            f"the dataset {dset.name} declares {dset.size:.3g} elements, more than the "
            f"{MAX_STORED_ELEMENTS:.3g} any session holds"
        )
    return dset[()]


def _read_array(dset: Any) -> np.ndarray:
    if dset.size > MAX_STORED_ELEMENTS:
        _read(dset)  # raises
    if h5py.check_string_dtype(dset.dtype) is not None:
        data = dset.asstr()[()]
        return np.array(data, dtype=str) if isinstance(data, np.ndarray) else np.array(data)
    return np.asarray(_read(dset))


def _read_arrays(
    group: Any, skip: Iterable[str] = ()
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    arrays, units = {}, {}
    skip = set(skip)
    for key in group.keys():
        obj = group[key]
        if key in skip or not isinstance(obj, h5py.Dataset):
            continue
        arrays[key] = _read_array(obj)
        if "units" in obj.attrs:
            units[key] = _attr_to_python(obj.attrs["units"])
    return arrays, units


def _not_found(what: str, name: str, available: Iterable[str], path: str) -> BadInputError:
    names = sorted(available)
    listed = ", ".join(names[:10]) + (" ..." if len(names) > 10 else "")
    return BadInputError(
        f"the session holds no {what} named {name!r}",
        path=path,
        hint=f"available: {listed}" if names else f"the session holds no {what}s yet",
    )


def _damaged(path: str, exc: BaseException) -> SessionError:
    detail = " ".join(str(exc).split())[:160]
    return SessionError(
        f"the session file is truncated or damaged ({detail})",
        path=path,
        hint="restore it from a backup; endomeasure never leaves partial writes behind",
    )


def _translating_errors(method):
    """Turn low-level read failures (a damaged file) into a one-line SessionError."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        if self._h5 is None:
            raise RuntimeError(f"{method.__name__}() on a closed session")  # a caller's bug
        try:
            return method(self, *args, **kwargs)
        except EndomeasureError:
            raise
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise _damaged(str(self.path), exc) from exc

    return wrapper


def _check_session_path(path: Path) -> None:
    """Refuse a path that is not an existing regular HDF5 file, before opening it."""
    spath = str(path)
    if not path.exists():
        raise SessionError(
            "the session file does not exist",
            path=spath,
            hint="check the path; commands that write a session create it",
        )
    if path.is_dir():
        raise SessionError("a session must be a file, not a directory", path=spath)
    st_mode = os.stat(path).st_mode
    if not stat.S_ISREG(st_mode):  # never open a FIFO or a device: it could block or never end
        raise SessionError(
            f"the session path is a {file_kind(st_mode)}, not a session file",
            path=spath,
            hint="give an endomeasure session file (.h5)",
        )
    try:
        is_hdf5 = h5py.is_hdf5(spath)
    except OSError as exc:
        raise SessionError(f"cannot read the session file ({exc})", path=spath) from exc
    if not is_hdf5:
        raise SessionError(
            "not a session: the file is not HDF5",
            path=spath,
            hint="give an endomeasure session file (.h5)",
        )


def _opened(source: Path | io.BytesIO, mode: str, path: Path) -> h5py.File:
    """h5py's handle on a session file or its bytes, its root attributes checked."""
    try:
        h5 = h5py.File(source, mode)
    except OSError as exc:
        raise _damaged(str(path), exc) from exc
    try:
        _check_root(h5, str(path))
    except BaseException:
        h5.close()
        raise
    return h5


def _refuse_damaged(path: Path, check: FileCheck, image: bytes | None = None) -> None:
    """Raise a SessionError naming what is damaged when the file checksum failed."""
    if not check.damaged:
        return
    source = io.BytesIO(image) if image is not None else path
    try:
        h5 = h5py.File(source, "r")
    except Exception as exc:  # noqa: BLE001 - HDF5 cannot open it: that is the answer
        report = DamageReport(readable=False, detail=" ".join(str(exc).split())[:120])
    else:
        with h5:
            # a file of another major version may keep its checksum differently: say so
            version = h5.attrs.get("format_version")
            try:
                major = _parse_version(version, "", "")[0]
            except SessionError:
                major = _READ_MAJOR  # unreadable: the damage report says what is wrong
            if major != _READ_MAJOR:
                _check_major(version, "the file", str(path))
            report = damage_report(h5)
    repair = f"`endomeasure repair {path.name} -o NEW.h5`"
    if not report.readable:
        raise SessionError(
            f"the session file is truncated or damaged ({check.detail}; {report.detail})",
            path=str(path),
            hint=f"restore it from a backup; {repair} keeps what can be read",
        )
    total = len(report.intact) + len(report.damaged)
    if not report.damaged:
        raise SessionError(
            f"the session file is damaged outside its stored items ({check.detail}); "
            f"all {total} items are intact",
            path=str(path),
            hint=f"{repair} copies them into a new session file",
        )
    names = ", ".join(list(report.damaged)[:3]) + (" ..." if len(report.damaged) > 3 else "")
    raise SessionError(
        f"the session file is damaged: {len(report.damaged)} of {total} stored items differ "
        f"from what was written ({names})",
        path=str(path),
        hint=f"{repair} keeps the {len(report.intact)} intact ones, or restore it from a backup",
    )


def _check_root(h5: h5py.File, path: str) -> None:
    try:
        fmt = _attr_to_python(h5.attrs.get("endomeasure_format"))
        version = _attr_to_python(h5.attrs.get("format_version"))
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        raise _damaged(path, exc) from exc
    if fmt != FORMAT_NAME:
        raise SessionError(
            "an HDF5 file but not an endomeasure session (no endomeasure_format='session')",
            path=path,
            hint="give a file written by endomeasure",
        )
    if version is None:
        raise SessionError("the session has no format_version attribute", path=path)
    _check_major(version, "the file", path)


# --------------------------------------------------------------------------- reader


class Session:
    """A read-only view of a session file. Create it with :func:`open_session`."""

    def __init__(self, path: Path, h5: h5py.File, *, checksum: str = "unchecked"):
        self.path = Path(path)
        self._h5 = h5
        self.checksum = checksum
        """``"ok"``: the file checksum matched when it was opened; ``"unchecked"``: a
        format 1.0 file, which has none (:class:`~endomeasure.io.integrity.FileCheck`)."""

    # context management
    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # internal navigation
    def _node(self, location: str, type_name: str) -> Any | None:
        """The node at ``location`` if present, after checking its type and version."""
        if location not in self._h5:
            return None
        node = self._h5[location]
        if not self._check_node(node, type_name):
            raise SessionError(
                f"group {node.name} should have type {type_name!r}",
                path=str(self.path),
                hint="the file was not written by endomeasure or is damaged",
            )
        return node

    def _check_node(self, node: Any, type_name: str) -> bool:
        """Check a node's type/version; False for an unknown type (a newer minor addition)."""
        node_type = _attr_to_python(node.attrs.get("type"))
        version = _attr_to_python(node.attrs.get("version"))
        if node_type is None or version is None:
            raise SessionError(
                f"group {node.name} has no type/version attributes",
                path=str(self.path),
                hint="the file was not written by endomeasure or is damaged",
            )
        _check_major(version, f"group {node.name}", str(self.path))
        return node_type == type_name

    def _children(self, location: str, container_type: str, child_type: str) -> dict[str, Any]:
        node = self._node(location, container_type)
        if node is None:
            return {}
        out = {}
        for key in sorted(node.keys()):
            child = node[key]
            if self._check_node(child, child_type):
                out[key] = child
        return out

    # metadata
    @property
    @_translating_errors
    def format_version(self) -> str:
        return _attr_to_python(self._h5.attrs["format_version"])

    @_translating_errors
    def metadata(self) -> SessionMetadata:
        """Session-wide facts: format version, creator, image size, split."""
        root = self._h5
        node = self._node("metadata", "metadata")
        attrs: dict[str, Any] = {}
        if node is not None:
            attrs, _ = _read_attrs(node)
        size = attrs.pop("image_size", None)
        split = attrs.pop("split", None)
        size = None if size is None else (int(size[0]), int(size[1]))
        split = None if split is None else int(split)
        if size is not None:
            self._check_declared(size, "its image size")
            if split is not None and not 0 < split < size[0]:
                raise SessionError(
                    f"the session declares the split column {split} outside its "
                    f"{size[0]} px wide images",
                    path=str(self.path),
                    hint="the metadata is damaged or crafted; restore the session from a backup",
                )
        created_by = _attr_to_python(root.attrs.get("created_by", ""))
        if isinstance(created_by, bytes):
            created_by = created_by.decode("utf-8", errors="replace")
        return SessionMetadata(
            format_version=_attr_to_python(root.attrs["format_version"]),
            created_by=str(created_by),
            image_size=size,
            split=split,
            attrs=attrs,
        )

    def _check_declared(self, size: tuple[int, int], what: str) -> None:
        """A SessionError for a declared image size beyond the limits (before any read)."""
        try:
            checked_image_size(size, str(self.path))
        except BadInputError as exc:
            raise SessionError(
                f"the session declares {what} {size[0]}x{size[1]} px, beyond the limit of "
                f"{MAX_IMAGE_SIDE} px a side and {MAX_IMAGE_PIXELS / 1e6:g} MP",
                path=str(self.path),
                hint="the session is damaged or crafted; restore it from a backup",
            ) from exc

    # images
    def _image_nodes(self) -> dict[str, Any]:
        return self._children("images", "images", "image")

    @_translating_errors
    def image_names(self, image_set: str | None = None) -> list[str]:
        """Names of the embedded images, sorted, optionally of one set only."""
        return [info.name for info in self.images_info(image_set)]

    @_translating_errors
    def images_info(self, image_set: str | None = None) -> list[ImageInfo]:
        """Descriptions (no pixels) of the embedded images, sorted by name."""
        out = []
        for name, dset in self._image_nodes().items():
            info = self._image_info(name, dset)
            if image_set is None or info.image_set == image_set:
                out.append(info)
        return out

    def _image_info(self, name: str, dset: Any) -> ImageInfo:
        attrs, _ = _read_attrs(dset)
        return ImageInfo(
            name=name,
            original_path=attrs.get("original_path", ""),
            sha256=attrs.get("sha256", ""),
            image_set=attrs.get("set", ""),
            shape=tuple(int(n) for n in dset.shape),
            dtype=str(dset.dtype),
            channel_order=attrs.get("channel_order", ""),
            frame=None if attrs.get("frame") is None else int(attrs["frame"]),
        )

    @_translating_errors
    def image_info(self, name: str) -> ImageInfo:
        """The description of one image, whose declared shape and type must be those of
        an image of this session (checked from the metadata, no pixel read)."""
        nodes = self._image_nodes()
        if name not in nodes:
            raise _not_found("image", name, nodes, str(self.path))
        dset = nodes[name]
        self._check_image_shape(name, dset.shape, dset.dtype)
        return self._image_info(name, dset)

    @_translating_errors
    def image(self, name: str) -> np.ndarray:
        """The pixels of an embedded image, shape (H, W) or (H, W, C), uint8 or uint16."""
        nodes = self._image_nodes()
        if name not in nodes:
            raise _not_found("image", name, nodes, str(self.path))
        dset = nodes[name]
        self._check_image_shape(name, dset.shape, dset.dtype)  # before reading a pixel
        return np.asarray(dset[()])

    def _check_image_shape(self, name: str, shape: tuple[int, ...], dtype: Any) -> None:
        """Refuse an image dataset whose declared shape or type no image of the session
        can have: beyond the limits, other than the session's image size, or not 8/16-bit
        grey or colour pixels."""
        bad = None
        if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] not in (1, 3, 4)):
            bad = f"shape {tuple(shape)}"
        elif np.dtype(dtype) not in (np.uint8, np.uint16):
            bad = f"pixel type {np.dtype(dtype)}"
        if bad is not None:
            raise SessionError(
                f"the stored image {name!r} has the {bad}, which no image has",
                path=str(self.path),
                hint="the session is damaged or crafted; restore it from a backup",
            )
        size = (int(shape[1]), int(shape[0]))
        self._check_declared(size, f"the image {name!r} of")
        declared = self.metadata().image_size
        if declared is not None and size != declared:
            raise SessionError(
                f"the stored image {name!r} is {size[0]}x{size[1]} px but the session "
                f"declares {declared[0]}x{declared[1]} px",
                path=str(self.path),
                hint="the session is damaged or crafted; restore it from a backup",
            )

    @_translating_errors
    def image_record(self, name: str) -> ImageRecord:
        info = self.image_info(name)
        return ImageRecord(
            name=info.name,
            pixels=self.image(name),
            original_path=info.original_path,
            sha256=info.sha256,
            image_set=info.image_set,
            channel_order=info.channel_order,
            frame=info.frame,
        )

    # boards
    @_translating_errors
    def boards(self) -> dict[str, Board]:
        """All boards by name."""
        out = {}
        for name, node in self._children("boards", "boards", "board").items():
            attrs, _ = _read_attrs(node)
            spec = attrs.pop("spec", "")
            out[name] = Board(name=name, spec=spec, attrs=attrs)
        return out

    @_translating_errors
    def board(self, name: str) -> Board:
        boards = self.boards()
        if name not in boards:
            raise _not_found("board", name, boards, str(self.path))
        return boards[name]

    # detections
    @_translating_errors
    def detections(
        self,
        board: str | None = None,
        image: str | None = None,
        half: Half | str | int | None = None,
    ) -> list[Detection]:
        """Detections, filtered by board, image and half; sorted by board, image, half."""
        try:
            want_half = None if half is None else Half.parse(half)
        except ValueError as exc:
            raise BadInputError(str(exc)) from None
        out = []
        for board_name, board_node in self._children(
            "detections", "detections", "board_detections"
        ).items():
            if board is not None and board_name != board:
                continue
            for image_name in sorted(board_node.keys()):
                if image is not None and image_name != image:
                    continue
                image_node = board_node[image_name]
                if not self._check_node(image_node, "image_detections"):
                    continue
                for half_value in Half:
                    if want_half is not None and half_value is not want_half:
                        continue
                    if half_value.label not in image_node:
                        continue
                    node = image_node[half_value.label]
                    if not self._check_node(node, "detection"):
                        continue
                    attrs, _ = _read_attrs(node)
                    pixels = np.asarray(_read(node["pixels"]), dtype=np.float64).reshape(-1, 2)
                    covariance = None
                    if "covariance" in node:
                        covariance = np.asarray(_read(node["covariance"]), dtype=np.float64)
                        if covariance.shape != (len(pixels), 2, 2):
                            raise _damaged(
                                str(self.path),
                                ValueError(
                                    f"detection {image_name}/{board_name}/{half_value.label}: "
                                    f"covariance shape {covariance.shape} for {len(pixels)} corners"
                                ),
                            )
                    out.append(
                        Detection(
                            image=image_name,
                            board=board_name,
                            half=half_value,
                            ids=np.asarray(_read(node["ids"]), dtype=np.int32),
                            pixels=pixels,
                            quality=float(attrs.pop("quality", math.nan)),
                            failure=str(attrs.pop("failure", "")),
                            attrs=attrs,
                            covariance=covariance,
                        )
                    )
        return out

    # models
    @_translating_errors
    def model_names(self) -> list[str]:
        return list(self._children("models", "models", "model"))

    @_translating_errors
    def model(self, name: str) -> ModelRecord:
        nodes = self._children("models", "models", "model")
        if name not in nodes:
            raise _not_found("model", name, nodes, str(self.path))
        node = nodes[name]
        attrs, attr_units = _read_attrs(node)
        arrays, array_units = _read_arrays(node, skip=("params", "param_names"))
        registry_name = attrs.pop("registry_name", "")
        config = attrs.pop("config", {})
        return ModelRecord(
            name=name,
            registry_name=registry_name,
            params=np.asarray(_read(node["params"]), dtype=np.float64),
            param_names=tuple(str(s) for s in _read_array(node["param_names"])),
            config=config,
            arrays=arrays,
            attrs=attrs,
            units={**attr_units, **array_units},
        )

    # records
    @_translating_errors
    def record_kinds(self) -> list[str]:
        return list(self._children("records", "records", "record_kind"))

    @_translating_errors
    def record_names(self, kind: str) -> list[str]:
        kinds = self._children("records", "records", "record_kind")
        if kind not in kinds:
            return []
        return [
            key
            for key in sorted(kinds[kind].keys())
            if self._check_node(kinds[kind][key], "record")
        ]

    @_translating_errors
    def record(self, kind: str, name: str) -> Record:
        names = self.record_names(kind)
        if name not in names:
            raise _not_found(f"{kind} record", name, names, str(self.path))
        node = self._h5["records"][kind][name]
        attrs, attr_units = _read_attrs(node, skip=("kind",))
        arrays, array_units = _read_arrays(node)
        return Record(
            kind=kind, name=name, attrs=attrs, arrays=arrays, units={**attr_units, **array_units}
        )

    @_translating_errors
    def records(self, kind: str) -> list[Record]:
        """All records of one kind, sorted by name."""
        return [self.record(kind, name) for name in self.record_names(kind)]


# --------------------------------------------------------------------------- writer


class SessionWriter(Session):
    """A transaction on a session. Create it with :func:`edit_session`.

    It reads like :class:`Session` (and sees its own edits); its ``write_*`` methods
    replace an existing item of the same key.
    """

    def __init__(self, path: Path, h5: h5py.File, *, checksum: str = "unchecked"):
        super().__init__(path, h5, checksum=checksum)
        self._changed: set[str] = set()  # item paths written: their digests are renewed

    def _container(self, location: str, type_name: str) -> Any:
        node = self._node(location, type_name)
        if node is None:
            node = self._h5.require_group(location)
            _stamp(node, type_name)
        return node

    def _fresh_group(self, parent: Any, name: str, type_name: str) -> Any:
        if name in parent:
            del parent[name]
        node = parent.create_group(name)
        _stamp(node, type_name)
        self._changed.add(node.name.lstrip("/"))
        return node

    def set_metadata(
        self,
        *,
        image_size: tuple[int, int] | None = None,
        split: int | None = None,
        **attrs: Any,
    ) -> None:
        """Set session-wide facts; arguments left out keep their stored value.

        Parameters
        ----------
        image_size : (width, height), px
        split : int, px
            First column of the right half.
        **attrs
            Further metadata, for example ``split_method="auto"``.
        """
        node = self._container("metadata", "metadata")
        self._changed.add("metadata")
        values: dict[str, Any] = dict(attrs)
        units: dict[str, str] = {}
        if image_size is not None:
            width, height = (int(n) for n in image_size)
            if width <= 0 or height <= 0:
                raise BadInputError(f"invalid image size {width}x{height}")
            values["image_size"] = [width, height]
            units["image_size"] = "px"
        if split is not None:
            values["split"] = int(split)
            units["split"] = "px"
        _write_attrs(node, values, units)

    def write_images(self, records: Iterable[ImageRecord], *, replace: bool = False) -> list[str]:
        """Embed images (gzip-compressed), all in this transaction.

        An image whose name is already stored with the same SHA-256 is left as it is; a
        different image under a stored name is refused unless ``replace``.

        Returns
        -------
        list of str
            Names of the images written (not those already present).
        """
        container = self._container("images", "images")
        written = []
        for rec in records:
            name = _check_name(rec.name, "image")
            if rec.image_set not in IMAGE_SETS:
                raise BadInputError(
                    f"unknown image set {rec.image_set!r} for image {name!r}",
                    hint=f"use one of {', '.join(IMAGE_SETS)}",
                )
            pixels = np.asarray(rec.pixels)
            if pixels.dtype not in (np.uint8, np.uint16) or pixels.ndim not in (2, 3):
                raise BadInputError(
                    f"image {name!r} must be a 2-D or 3-D uint8/uint16 array, "
                    f"not {pixels.ndim}-D {pixels.dtype}",
                    path=rec.original_path or None,
                )
            order = rec.channel_order or _channel_order(pixels)
            if name in container:
                old_sha = _attr_to_python(container[name].attrs.get("sha256", ""))
                if old_sha == rec.sha256 and not replace:
                    continue
                if not replace:
                    raise BadInputError(
                        f"the session already holds a different image named {name!r}",
                        path=rec.original_path or None,
                        hint="rename the file or remove the old image first",
                    )
                del container[name]
            dset = container.create_dataset(
                name,
                data=pixels,
                chunks=pixels.shape,
                compression="gzip",
                compression_opts=_IMAGE_COMPRESSION_LEVEL,
                shuffle=pixels.dtype.itemsize > 1,
            )
            _stamp(dset, "image")
            self._changed.add(dset.name.lstrip("/"))
            dset.attrs["original_path"] = str(rec.original_path)
            dset.attrs["sha256"] = str(rec.sha256)
            dset.attrs["set"] = rec.image_set
            dset.attrs["channel_order"] = order
            dset.attrs["units"] = "DN"
            if rec.frame is not None:
                dset.attrs["frame"] = int(rec.frame)
            written.append(name)
        return written

    def write_board(
        self,
        name: str,
        spec: str,
        attrs: Mapping[str, Any] | None = None,
        units: Mapping[str, str] | None = None,
    ) -> None:
        """Store a board by name: its spec string and parsed values (``square_mm`` ...)."""
        container = self._container("boards", "boards")
        node = self._fresh_group(container, _check_name(name, "board"), "board")
        _write_attrs(node, {"spec": str(spec), **dict(attrs or {})}, dict(units or {}))

    def write_detections(self, detections: Iterable[Detection]) -> int:
        """Store detections, replacing any earlier one of the same (board, image, half).

        The board must be stored already. Returns how many were written.
        """
        container = self._container("detections", "detections")
        boards = self.boards()
        count = 0
        for det in detections:
            if det.board not in boards:
                raise _not_found("board", det.board, boards, str(self.path))
            half = Half.parse(det.half)
            ids = np.asarray(det.ids)
            pixels = np.asarray(det.pixels, dtype=np.float64)
            if ids.ndim != 1 or pixels.shape != (ids.shape[0], 2):
                raise BadInputError(
                    f"detection {det.image}/{det.board}/{half.label}: ids shape {ids.shape} "
                    f"and pixels shape {pixels.shape} do not match (N,) and (N, 2)"
                )
            board_node = container.get(det.board)
            if board_node is None:
                board_node = container.create_group(det.board)
                _stamp(board_node, "board_detections")
            image_node = board_node.get(_check_name(det.image, "image"))
            if image_node is None:
                image_node = board_node.create_group(det.image)
                _stamp(image_node, "image_detections")
            node = self._fresh_group(image_node, half.label, "detection")
            node.create_dataset("ids", data=ids.astype(np.int32))
            node.create_dataset("pixels", data=pixels).attrs["units"] = "px"
            if det.covariance is not None:
                covariance = np.asarray(det.covariance, dtype=np.float64)
                if covariance.shape != (ids.shape[0], 2, 2):
                    raise BadInputError(
                        f"detection {det.image}/{det.board}/{half.label}: covariance shape "
                        f"{covariance.shape} does not match (N, 2, 2)"
                    )
                node.create_dataset("covariance", data=covariance).attrs["units"] = "px^2"
            extra = dict(det.attrs)
            _write_attrs(
                node, {"quality": float(det.quality), "failure": str(det.failure), **extra}, {}
            )
            count += 1
        return count

    def write_detection(self, detection: Detection) -> None:
        self.write_detections([detection])

    def delete_detections(self, board: str, image: str | None = None) -> None:
        """Remove all detections of a board, or of one image of it."""
        container = self._node("detections", "detections")
        if container is None or board not in container:
            return
        if image is None:
            del container[board]
        elif image in container[board]:
            del container[board][image]

    def write_model(self, model: ModelRecord) -> None:
        """Store a model under ``model.name``, replacing an earlier one of that name."""
        params = np.asarray(model.params, dtype=np.float64)
        names = tuple(str(s) for s in model.param_names)
        if params.ndim != 1 or len(names) != params.shape[0]:
            raise BadInputError(
                f"model {model.name!r}: {params.shape} parameters but {len(names)} names"
            )
        container = self._container("models", "models")
        node = self._fresh_group(container, _check_name(model.name, "model"), "model")
        node.create_dataset("params", data=params)
        node.create_dataset("param_names", data=np.array(names, dtype=h5py.string_dtype()))
        reserved = {"registry_name", "config"} & set(model.attrs)
        if reserved:
            raise BadInputError(f"model attrs may not be named {sorted(reserved)}")
        # config is a dict, so _write_attrs stores it as JSON and lists it in json_attrs
        attrs = {"registry_name": str(model.registry_name), "config": dict(model.config)}
        _write_attrs(node, {**attrs, **model.attrs}, dict(model.units))
        for key, value in model.arrays.items():
            if key in ("params", "param_names"):
                raise BadInputError(f"model array name {key!r} is reserved")
            _write_array(node, key, value, model.units.get(key))

    def delete_model(self, name: str) -> None:
        container = self._node("models", "models")
        if container is not None and name in container:
            del container[name]

    def write_record(self, record: Record) -> None:
        """Store a record under (kind, name), replacing an earlier one."""
        records = self._container("records", "records")
        kind = _check_name(record.kind, "record kind")
        kind_node = records.get(kind)
        if kind_node is None:
            kind_node = records.create_group(kind)
            _stamp(kind_node, "record_kind")
        node = self._fresh_group(kind_node, _check_name(record.name, "record"), "record")
        node.attrs["kind"] = kind
        if "kind" in record.attrs:
            raise BadInputError("record attrs may not be named 'kind'")
        _write_attrs(node, dict(record.attrs), dict(record.units))
        for key, value in record.arrays.items():
            _write_array(node, key, value, record.units.get(key))

    def write_records(self, records: Iterable[Record]) -> None:
        for record in records:
            self.write_record(record)

    def delete_record(self, kind: str, name: str) -> None:
        container = self._node("records", "records")
        if container is not None and kind in container and name in container[kind]:
            del container[kind][name]


def _channel_order(pixels: np.ndarray) -> str:
    if pixels.ndim == 2 or pixels.shape[2] == 1:
        return "gray"
    return {3: "BGR", 4: "BGRA"}.get(pixels.shape[2], f"{pixels.shape[2]}ch")


# --------------------------------------------------------------------------- entry points


def open_session(
    path: str | os.PathLike, *, lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT_S
) -> Session:
    """Open a session for reading, after checking its file checksum; see the module
    docstring.

    Raises
    ------
    SessionError
        Missing, not HDF5, damaged (naming the damaged items), or not a session.
    SessionVersionError
        An unknown major format version.
    """
    path = Path(path)
    if path.is_symlink():  # lock the target, as writers do
        path = Path(os.path.realpath(path))
    if not is_regular_file(path):
        _check_session_path(path)  # raises the reason; no lock file is left beside it
    # The shared lock only covers the check and the open: once open, the file is an
    # immutable snapshot because writers replace it rather than change it.
    with SessionLock(path, exclusive=False, timeout=lock_timeout, required=False):
        _check_session_path(path)
        check = check_file(path)
        _refuse_damaged(path, check)
        h5 = _opened(path, "r", path)
    session = Session(path, h5, checksum=check.status)
    try:
        session.metadata()  # a crafted image size or split is refused before any read
    except BaseException:
        session.close()
        raise
    return session


def _fsync_path(path: Path, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        if directory:
            return  # some platforms cannot open directories; the rename is still atomic
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


def _remove_stale_temps(path: Path) -> None:
    """Delete temp files of edits that were killed; called while holding the exclusive lock."""
    prefix = f".{path.name}."
    for candidate in path.parent.glob(f"{glob_escape(prefix)}*{_TMP_SUFFIX}"):
        with contextlib.suppress(OSError):
            candidate.unlink()


def glob_escape(text: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", text)


_FREE_SPACE_MARGIN = 1 << 20
"""Bytes left free on the disk after a session is written (for the file system's own use)."""


def _read_verified(path: Path) -> tuple[bytes, FileCheck]:
    """The bytes of an existing session file, its checksum checked (damage refused)."""
    _check_session_path(path)
    with open(path, "rb") as stream:
        image = stream.read()
    check = check_image(image)
    _refuse_damaged(path, check, image)
    return image, check


def _new_file(buffer: io.BytesIO) -> h5py.File:
    """A fresh session in ``buffer``, with the user block that will hold its checksum."""
    h5 = h5py.File(buffer, "w", userblock_size=USERBLOCK_SIZE)
    h5.attrs["endomeasure_format"] = FORMAT_NAME
    h5.attrs["format_version"] = FORMAT_VERSION
    h5.attrs["created_by"] = f"endomeasure {__version__}"
    return h5


def _upgraded(image: bytes, buffer: io.BytesIO, path: Path) -> h5py.File:
    """A format 1.0 session (no user block) copied into ``buffer`` with one."""
    h5 = _new_file(buffer)
    with _opened(io.BytesIO(image), "r", path) as old:
        for key, value in old.attrs.items():
            if key != "format_version":
                h5.attrs[key] = value
        for key in old.keys():
            old.copy(old[key], h5, name=key)
    return h5


def _write_file(path: Path, image: bytes | bytearray, mode: int) -> None:
    """Replace ``path`` by ``image`` atomically: a temp file beside it, fsynced, renamed.

    Space is checked first, and a write that fails (disk full, I/O error) removes the
    temp file and leaves the session as it was, with one line saying why.
    """
    with contextlib.suppress(OSError):
        free = shutil.disk_usage(path.parent).free
        if free < len(image) + _FREE_SPACE_MARGIN:
            raise SessionError(
                f"not enough free space to write the session: it needs "
                f"{len(image) / 1e6:.1f} MB and {_FREE_SPACE_MARGIN / 1e6:.0f} MB to spare, "
                f"{free / 1e6:.1f} MB are free",
                path=str(path),
                hint="free some space on that disk and run the command again; "
                "the session is unchanged",
            )
    try:
        fd, tmp_name = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.", suffix=_TMP_SUFFIX
        )
    except OSError as exc:
        raise SessionError(
            f"cannot write beside the session ({exc.strerror or exc})",
            path=str(path),
            hint="the session's folder must be writable",
        ) from None
    tmp = Path(tmp_name)
    try:
        try:
            view = memoryview(image)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise SessionError(
                f"cannot write the session ({exc.strerror or exc})",
                path=str(path),
                hint="free some space or fix the disk and run the command again; "
                "the session is unchanged",
            ) from None
        raise
    _fsync_path(path.parent, directory=True)


@contextlib.contextmanager
def edit_session(
    path: str | os.PathLike,
    *,
    create: bool = False,
    lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT_S,
) -> Iterator[SessionWriter]:
    """Edit a session atomically under its exclusive lock; see the module docstring.

    The session is checked (its file checksum) and edited in memory; on success the
    manifest and checksum are brought up to date and the new bytes replace the file.
    A damaged session is refused, so a writer never builds on damaged data.

    Parameters
    ----------
    path : path-like
    create : bool
        Create the session if it does not exist (its directory must exist).
    lock_timeout : float or None, s
        How long to wait for another command's edit to finish.

    Raises
    ------
    SessionError, SessionVersionError
        As :func:`open_session`; also when the lock is not granted in time, and when the
        new file cannot be written (disk full), the session then unchanged.
    """
    # a symlink is written through (its target replaced, the link kept); a hard-linked
    # session, a FIFO, a device or an unwritable folder are refused before any work
    path = checked_session_target(path, create=create, probe=False)
    with SessionLock(path, exclusive=True, timeout=lock_timeout):
        _remove_stale_temps(path)
        exists = path.exists()
        if not exists and not create:
            raise SessionError(
                "the session file does not exist",
                path=str(path),
                hint="check the path, or start a session with a command that creates one",
            )
        buffer = io.BytesIO()
        if exists:
            image, check = _read_verified(path)
            mode = stat.S_IMODE(os.stat(path).st_mode)
            if check.status == "ok":
                buffer = io.BytesIO(image)
                h5 = _opened(buffer, "r+", path)
            else:
                h5 = _upgraded(image, buffer, path)
            del image
        else:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
            h5 = _new_file(buffer)
        try:
            writer = SessionWriter(path, h5, checksum="ok")
            writer.metadata()  # validate before any work: clear errors
            if _parse_version(writer.format_version, "the file", str(path)) < _WRITE_VERSION:
                h5.attrs["format_version"] = FORMAT_VERSION  # it gains the checksums
            yield writer
            writer._h5 = None
            write_manifest(h5, writer._changed)
            h5.close()
            h5 = None
            image = bytearray(buffer.getbuffer())
            buffer.close()
            seal_image(image)
            with interrupts.deferred():  # Ctrl-C: the old file or the new, no temp file
                _write_file(path, image, mode)
        finally:
            if h5 is not None:
                with contextlib.suppress(Exception):
                    h5.close()


def salvage_session(
    source: str | os.PathLike, target: str | os.PathLike
) -> tuple[DamageReport, str]:
    """Copy the intact items of a session into a new session file ``target``.

    Each item is kept when its digest matches the manifest (all of them when the file
    checksum matches; every readable one of a format 1.0 file, which has no manifest).

    Returns
    -------
    report : DamageReport
        What was kept (``intact``) and what was left out and why (``damaged``).
    checksum : str
        The source's file check: ``"ok"``, ``"unchecked"`` or ``"damaged"``.
    """
    source, target = Path(source), Path(target)
    _check_session_path(source)
    if os.path.lexists(target):
        raise BadInputError(
            "the repaired session must be a new file, and this one exists",
            path=str(target),
            hint="give a new file name with -o",
        )
    with SessionLock(source, exclusive=False, required=False):
        with open(source, "rb") as stream:
            image = stream.read()
    check = check_image(image)
    try:
        old = h5py.File(io.BytesIO(image), "r")
    except OSError as exc:
        raise SessionError(
            "nothing can be salvaged: HDF5 cannot open the file "
            f"({' '.join(str(exc).split())[:120]})",
            path=str(source),
            hint="restore it from a backup",
        ) from None
    with old:
        _check_root(old, str(source))
        if check.status == "damaged":
            report = damage_report(old)
            if not report.readable:
                raise SessionError(
                    f"nothing can be salvaged: {report.detail}",
                    path=str(source),
                    hint="restore it from a backup",
                )
        else:
            report = DamageReport(intact=list(item_paths(old)))
        with edit_session(target, create=True) as writer:
            new = writer._h5
            creator = old.attrs.get("created_by")
            if creator is not None:
                new.attrs["created_by"] = creator
            for item in report.intact:
                parts = item.split("/")
                for depth, type_name in enumerate(CONTAINERS.get(parts[0], ())):
                    location = "/".join(parts[: depth + 1])
                    if location not in new:
                        _stamp(new.create_group(location), type_name)
                old.copy(old[item], new, name=item)
                writer._changed.add(item)
            writer.metadata()  # what was kept must read as a session
    return report, check.status
