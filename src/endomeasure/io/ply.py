"""Point clouds as PLY files (binary little endian), written without a dependency.

Layout (one ``vertex`` element per valid point, ``docs/session-format.md``, "surface")::

    ply
    format binary_little_endian 1.0
    comment endomeasure surface: mm, model frame of MODEL
    element vertex N
    property float x          mm, model frame
    property float y
    property float z
    property float sigma      1-sigma of the point along its ray, mm
    property uchar grey       the left image's grey value (8-bit; 16-bit images >> 8)
    property ushort u         the left pixel, column
    property ushort v         the left pixel, row
    end_header

Readers that know only x, y, z (MeshLab, CloudCompare, Open3D) skip the rest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from endomeasure.io.outputs import atomic_write

__all__ = ["write_ply", "read_ply"]

_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("sigma", "<f4"), ("grey", "u1"),
     ("u", "<u2"), ("v", "<u2")]
)  # fmt: skip


def write_ply(
    path: str | Path, points: np.ndarray, sigma: np.ndarray, grey: np.ndarray,
    pixels: np.ndarray, comment: str = "",
) -> int:  # fmt: skip
    """Write points (N, 3) mm with their sigma (N,) mm, grey (N,) and pixel (N, 2) to a
    binary little-endian PLY; returns N. Written to a temporary file, then renamed."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    data = np.empty(points.shape[0], dtype=_DTYPE)
    for k, name in enumerate("xyz"):
        data[name] = points[:, k]
    data["sigma"] = np.asarray(sigma).reshape(-1)
    grey = np.asarray(grey).reshape(-1)
    data["grey"] = np.clip(grey / 256.0 if grey.max(initial=0) > 255 else grey, 0, 255)
    data["u"], data["v"] = np.asarray(pixels).reshape(-1, 2).T
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {line}" for line in comment.splitlines() if line]
    header += [f"element vertex {data.size}"]
    ply_types = {"<f4": "float", "u1": "uchar", "<u2": "ushort"}
    header += [f"property {ply_types[_DTYPE[n].str.replace('|', '')]} {n}" for n in _DTYPE.names]
    header += ["end_header"]
    blob = ("\n".join(header) + "\n").encode("ascii") + data.tobytes()
    atomic_write(path, lambda tmp: tmp.write_bytes(blob))
    return int(data.size)


def read_ply(path: str | Path) -> np.ndarray:
    """Read a PLY written by :func:`write_ply` (a structured array)."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(raw[end:], dtype=_DTYPE)
