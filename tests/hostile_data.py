"""Hostile files for the tests and the fault scripts (a test helper, not a test): PNGs
that declare huge sizes in their header, sessions crafted with h5py by someone who knows
the format (their checksum matches). Used by ``tests/test_hostile.py`` and
``bench/fault_limits.py``."""

from __future__ import annotations

import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import h5py

from endomeasure.io.integrity import seal_file


def png_header_only(path: Path, width: int, height: int, iccp: bool = False) -> None:
    """A grey PNG of ``width`` x ``height``: whole for small sizes, otherwise with a stub
    of data, as the size must be refused from the header before a decoder would
    allocate the pixels. ``iccp`` adds a colour profile too short for libpng, which
    then warns on the process's stderr."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    rows = height if width * height <= 1 << 20 else 1
    idat = zlib.compress((b"\x00" + b"\x80" * width) * rows)
    profile = chunk(b"iCCP", b"bogus\x00\x00" + zlib.compress(b"short")) if iccp else b""
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + profile + chunk(b"IDAT", idat)
        + chunk(b"IEND", b"")
    )  # fmt: skip


def crafted(source: Path, target: Path, edit) -> Path:
    shutil.copyfile(source, target)
    with h5py.File(target, "r+") as h5:
        edit(h5)
    seal_file(target)  # crafted by someone who knows the format: its checksum matches
    return target


def replace_image(h5, name: str, shape, dtype) -> None:
    attrs = dict(h5["images"][name].attrs)
    del h5["images"][name]
    dset = h5["images"].create_dataset(
        name, shape=shape, dtype=dtype, chunks=(64, 64) + shape[2:], compression="gzip"
    )
    for key, value in attrs.items():
        dset.attrs[key] = value


_PEAK_RSS = """
import resource, subprocess, sys
done = subprocess.run([sys.executable, "-m", "endomeasure", *sys.argv[1:]], capture_output=True,
                      text=True)
sys.stdout.write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) + "\\n")
sys.stderr.write(done.stderr)
sys.exit(done.returncode)
"""


def run_measured(*args: str) -> tuple[subprocess.CompletedProcess, float]:
    """Run the command line in a fresh process; its result and its peak memory, MB (a
    wrapper process has it as its only child, so no other test's child counts)."""
    result = subprocess.run(
        [sys.executable, "-c", _PEAK_RSS, *args], capture_output=True, text=True, timeout=60
    )
    return result, int(result.stdout.split()[-1]) / 1024  # ru_maxrss is in kB on Linux
