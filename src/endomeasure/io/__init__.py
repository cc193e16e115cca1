"""Storage: the session file (HDF5) and image files.

This package is the only place that imports h5py. The session API is documented in
:mod:`endomeasure.io.session`; the layout on disk in ``docs/session-format.md``.
Importing ``endomeasure.io`` imports h5py, so import it inside command code, not at the
top of modules that ``endomeasure --help`` loads.
"""

from endomeasure.io.images import find_image_files, read_image_file, sha256_of_file
from endomeasure.io.session import (
    FORMAT_VERSION,
    IMAGE_SETS,
    Board,
    Detection,
    ImageInfo,
    ImageRecord,
    ModelRecord,
    Record,
    Session,
    SessionMetadata,
    SessionWriter,
    edit_session,
    open_session,
)

__all__ = [
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
    "find_image_files",
    "open_session",
    "read_image_file",
    "sha256_of_file",
]
