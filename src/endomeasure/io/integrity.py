"""Checksums of a session: every stored byte is checked before anything is read.

Two layers, both written when an edit commits (``docs/session-format.md``, "Integrity"):

- The **file checksum**: the first :data:`USERBLOCK_SIZE` bytes of the file are an HDF5
  user block (HDF5 ignores them) holding the SHA-256 of every byte after it. A reader
  hashes the file before opening it, so any change to the file, wherever it falls
  (pixels, attributes, HDF5's own structures), is found before a value is used. Hashing
  runs at disk speed (about 15 ms for a 12 MB session).
- The **manifest**: the dataset ``/manifest`` lists every stored item (the metadata, one
  image, one board, one detection, one model, one record) with the SHA-256 of its path,
  attributes and data. It says *what* is damaged when the file checksum fails, and lets
  :func:`endomeasure.io.session.salvage_session` keep the intact items.

A file written before format 1.1 has neither (its HDF5 signature is at byte 0): it is
read unchecked and gains both at its first edit. h5py-level code; nothing here prints.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import h5py
import numpy as np

from endomeasure.defaults import MAX_STORED_ELEMENTS

__all__ = [
    "CONTAINERS",
    "MANIFEST",
    "USERBLOCK_SIZE",
    "DamageReport",
    "FileCheck",
    "check_file",
    "check_image",
    "damage_report",
    "item_digest",
    "item_paths",
    "seal_file",
    "seal_image",
    "write_manifest",
]

USERBLOCK_SIZE = 512
"""Bytes before the HDF5 superblock (HDF5's smallest user block)."""
MANIFEST = "manifest"
"""Root dataset of (item path, item digest) rows."""
_MAGIC = b"endomeasure session checksum\nsha256 "
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_CHUNK = 1 << 20
CONTAINERS = {
    "metadata": (),
    "images": ("images",),
    "boards": ("boards",),
    "detections": ("detections", "board_detections", "image_detections"),
    "models": ("models",),
    "records": ("records", "record_kind"),
}
"""The groups above the items, by top-level group: their ``type`` from the top down.
``detections/<board>/<image>/<half>`` is one item (below three containers),
``images/<name>`` another, ``metadata`` one itself. A top-level group unknown to this
version (a newer minor addition) is one item as a whole."""


# --------------------------------------------------------------------------- file checksum


def _header(digest: bytes) -> bytes:
    text = _MAGIC + digest.hex().encode("ascii") + b"\n"
    return text + b"\0" * (USERBLOCK_SIZE - len(text))


@dataclass(frozen=True)
class FileCheck:
    """The outcome of checking a session file's bytes.

    Attributes
    ----------
    status : str
        ``"ok"`` (checksum matches), ``"unchecked"`` (a file from before format 1.1,
        without a checksum) or ``"damaged"``.
    detail : str
        Why it is damaged ("" otherwise).
    """

    status: str
    detail: str = ""

    @property
    def damaged(self) -> bool:
        return self.status == "damaged"


def _check_stream(stream: BinaryIO) -> FileCheck:
    head = stream.read(USERBLOCK_SIZE + len(_HDF5_SIGNATURE))
    if head.startswith(_HDF5_SIGNATURE):
        return FileCheck("unchecked")
    if len(head) < USERBLOCK_SIZE + len(_HDF5_SIGNATURE):
        return FileCheck("damaged", f"only {len(head)} bytes")
    if head[USERBLOCK_SIZE:] != _HDF5_SIGNATURE:
        return FileCheck("damaged", "no HDF5 signature after the checksum block")
    if not head.startswith(_MAGIC):
        return FileCheck("damaged", "the checksum block is damaged")
    hasher = hashlib.sha256(head[USERBLOCK_SIZE:])
    while chunk := stream.read(_CHUNK):
        hasher.update(chunk)
    if head[:USERBLOCK_SIZE] != _header(hasher.digest()):
        return FileCheck("damaged", "the file's checksum does not match its contents")
    return FileCheck("ok")


def check_file(path: str | os.PathLike) -> FileCheck:
    """Check the file checksum of the session file at ``path``."""
    with open(path, "rb") as stream:
        return _check_stream(stream)


def check_image(image: bytes) -> FileCheck:
    """Check the file checksum of a session's bytes in memory."""
    import io

    return _check_stream(io.BytesIO(image))


def seal_image(image: bytearray) -> None:
    """Write the file checksum into the user block of a session's bytes, in place."""
    if image[USERBLOCK_SIZE : USERBLOCK_SIZE + len(_HDF5_SIGNATURE)] != _HDF5_SIGNATURE:
        raise ValueError("the image has no user block of the expected size")  # a caller's bug
    image[:USERBLOCK_SIZE] = _header(hashlib.sha256(memoryview(image)[USERBLOCK_SIZE:]).digest())


# --------------------------------------------------------------------------- item digests


def _feed(hasher: Any, tag: bytes, payload: bytes) -> None:
    hasher.update(tag + len(payload).to_bytes(8, "little") + payload)


def _feed_value(hasher: Any, value: Any) -> None:
    """Hash a value as h5py returns it (attribute or dataset contents), unambiguously."""
    if isinstance(value, str):
        _feed(hasher, b"s", value.encode("utf-8", errors="surrogatepass"))
    elif isinstance(value, bytes):
        _feed(hasher, b"b", value)
    else:
        arr = np.asarray(value)
        shape = repr(arr.shape).encode("ascii")
        if arr.dtype.kind == "O":
            _feed(hasher, b"o", shape)
            for element in arr.ravel():
                _feed_value(hasher, element)
        else:
            _feed(hasher, b"a", arr.dtype.str.encode("ascii") + shape)
            _feed(hasher, b"d", np.ascontiguousarray(arr).tobytes())


def _feed_node(hasher: Any, node: Any) -> None:
    for key in sorted(node.attrs.keys()):
        _feed(hasher, b"k", key.encode("utf-8"))
        _feed_value(hasher, node.attrs[key])
    if isinstance(node, h5py.Dataset):
        _feed(hasher, b"t", node.dtype.str.encode("ascii") + repr(node.shape).encode("ascii"))
        if node.size <= MAX_STORED_ELEMENTS:  # larger: never read, refused by its size
            _feed_value(hasher, node[()])
        return
    for key in sorted(node.keys()):
        _feed(hasher, b"n", key.encode("utf-8"))
        _feed_node(hasher, node[key])


def item_digest(h5: h5py.File, path: str) -> str:
    """The SHA-256 (hex) of an item: its path, and all attributes and data below it."""
    hasher = hashlib.sha256()
    _feed(hasher, b"p", path.encode("utf-8"))
    _feed_node(hasher, h5[path])
    return hasher.hexdigest()


def item_paths(h5: h5py.File) -> Iterator[str]:
    """The paths of the items a session holds (keys only: no attribute or data is read)."""
    for top in sorted(h5.keys()):
        if top == MANIFEST:
            continue
        depth = len(CONTAINERS.get(top, ()))
        yield from _paths_below(h5, top, depth)


def _paths_below(h5: h5py.File, path: str, depth: int) -> Iterator[str]:
    if depth == 0:
        yield path
        return
    node = h5[path]
    if not isinstance(node, h5py.Group):
        yield path  # where a group should be: an item of its own, so a digest covers it
        return
    for key in sorted(node.keys()):
        yield from _paths_below(h5, f"{path}/{key}", depth - 1)


def read_manifest(h5: h5py.File) -> dict[str, str]:
    """The stored manifest (path -> digest); empty when there is none."""
    if MANIFEST not in h5:
        return {}
    rows = h5[MANIFEST].asstr()[()]
    return {str(path): str(digest) for path, digest in np.asarray(rows).reshape(-1, 2)}


def write_manifest(h5: h5py.File, changed: Iterable[str]) -> None:
    """Bring the manifest up to date: digests of the items ``changed`` in this edit and
    of any item it does not list yet; entries of removed items dropped."""
    old = read_manifest(h5)
    changed = set(changed)
    rows = []
    for path in item_paths(h5):
        digest = old.get(path)
        if digest is None or path in changed:
            digest = item_digest(h5, path)
        rows.append((path, digest))
    if MANIFEST in h5:
        del h5[MANIFEST]
    data = np.array(rows, dtype=object).reshape(-1, 2)
    h5.create_dataset(MANIFEST, data=data.astype(h5py.string_dtype()), dtype=h5py.string_dtype())


# --------------------------------------------------------------------------- damage


@dataclass
class DamageReport:
    """Which items of a session whose file checksum failed are intact.

    Attributes
    ----------
    intact : list of str
        Item paths whose digest matches the manifest.
    damaged : dict
        Item path -> why (digest differs, unreadable, missing, not in the manifest).
    readable : bool
        False when HDF5 cannot open the file or its manifest at all: nothing can be
        said per item.
    detail : str
        Why it is unreadable ("" otherwise).
    """

    intact: list[str] = field(default_factory=list)
    damaged: dict[str, str] = field(default_factory=dict)
    readable: bool = True
    detail: str = ""


def damage_report(h5: h5py.File) -> DamageReport:
    """Check every item of an open session file against its manifest."""
    report = DamageReport()
    try:
        manifest = read_manifest(h5)
        present = list(item_paths(h5))
    except Exception as exc:  # noqa: BLE001 - any failure of a damaged file is the answer
        return DamageReport(readable=False, detail=_short(exc))
    if not manifest:
        return DamageReport(readable=False, detail="the manifest is missing")
    for path in sorted(set(present) | set(manifest)):
        if path not in manifest:
            report.damaged[path] = "not in the manifest"
            continue
        if path not in present:
            report.damaged[path] = "missing"
            continue
        try:
            same = item_digest(h5, path) == manifest[path]
        except Exception as exc:  # noqa: BLE001
            report.damaged[path] = f"unreadable ({_short(exc)})"
            continue
        if same:
            report.intact.append(path)
        else:
            report.damaged[path] = "differs from what was written"
    return report


def _short(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:120] or type(exc).__name__


def seal_file(path: str | os.PathLike) -> None:
    """Renew the manifest and the file checksum of a session edited with h5py directly.

    endomeasure itself never needs this (its edits seal what they write); it exists for
    crafting sessions in tests and for tools that rewrite a session knowingly. The file
    must already have the checksum's user block (format 1.1).
    """
    with h5py.File(path, "r+") as h5:
        write_manifest(h5, item_paths(h5))
    with open(path, "r+b") as stream:
        image = bytearray(stream.read())
        seal_image(image)
        stream.seek(0)
        stream.write(image[:USERBLOCK_SIZE])
