"""Random bit flips in a calibrated session: is every change found on the next read?

    .venv/bin/python bench/fault_bitflips.py SESSION [--trials 200] [--seed 0]
                                             [--cli 20] [--work DIR] [--no-write]

SESSION is a calibrated session (e.g. ``out/accuracy/accuracy.h5`` or ``make demo``'s
``out/demo/demo.h5``); a copy is sealed first (a format 1.0 file gains its checksums).
Each trial flips one random bit of a fresh copy: half of the trials anywhere in the
file, half outside the images' compressed chunks (HDF5's structures, attributes and the
small datasets, where a flip is most likely to change a value silently). The truth of
whether the flip changed stored data comes from code the session reader does not share:
h5py walks every object of the flipped file and of the pristine one and compares names,
attributes, types, shapes and data bytes (a file HDF5 cannot walk counts as changed).
Found means ``open_session`` refused the file; for the first ``--cli`` trials the real
command ``endomeasure info`` is run too and must exit 2 with one line.

Trials go to ``WORK/bitflips.jsonl`` as they finish. Writes the "bitflips" section of
docs/robustness.md unless ``--no-write``; exits 3 when a changed file was accepted.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import Report, Target, script_parser  # noqa: E402

ROBUSTNESS = ROOT / "docs" / "robustness.md"
SECTION = "bitflips"
TARGET = Target("changed sessions accepted on the next read", "==", 0, "", "issue 18")


def raw_dump(path: Path) -> str | None:
    """A digest of everything h5py reads from the file (None: HDF5 cannot walk it)."""
    import h5py

    hasher = hashlib.md5()

    def feed(name, obj):
        hasher.update(name.encode())
        for key in sorted(obj.attrs):
            hasher.update(key.encode() + repr(obj.attrs[key]).encode())
        if isinstance(obj, h5py.Dataset):
            hasher.update(f"{obj.dtype}{obj.shape}".encode())
            data = obj[()]
            hasher.update(
                repr(data.tolist()).encode() if data.dtype.kind == "O" else data.tobytes()
            )

    try:
        with h5py.File(path, "r") as h5:
            feed("/", h5)
            h5.visititems(feed)
    except Exception:  # noqa: BLE001 - any failure to walk the file is a change
        return None
    return hasher.hexdigest()


def image_chunks(path: Path) -> list[tuple[int, int]]:
    """(offset, size) of the images' compressed chunks in the file."""
    import h5py

    spans = []
    with h5py.File(path, "r") as h5:
        for name in h5.get("images", {}):
            dset = h5["images"][name]
            for index in range(dset.id.get_num_chunks()):
                info = dset.id.get_chunk_info(index)
                spans.append((int(info.byte_offset), int(info.size)))
    return sorted(spans)


def outside(spans, size: int) -> np.ndarray:
    """Byte positions of the file not in any of ``spans``."""
    mask = np.ones(size, bool)
    for offset, length in spans:
        mask[offset : offset + length] = False
    return np.flatnonzero(mask)


def refused(path: Path) -> str | None:
    """The reader's refusal of ``path`` (None: it opened and read everything)."""
    from endomeasure.errors import SessionError
    from endomeasure.io.session import open_session

    try:
        with open_session(path) as s:
            for name in s.image_names():
                s.image(name)
            s.detections()
            for name in s.model_names():
                s.model(name)
            for kind in s.record_kinds():
                s.records(kind)
    except SessionError as exc:
        return exc.what
    return None


def cli_info(path: Path) -> dict:
    done = subprocess.run(
        [sys.executable, "-m", "endomeasure", "info", str(path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = done.stderr.strip().splitlines()
    return {
        "exit": done.returncode,
        "one_line": len(lines) == 1 and lines[0].startswith("error: "),
        "traceback": "Traceback" in done.stderr,
    }


def main(argv=None) -> int:
    parser = script_parser(__doc__, seed=0, work=True)
    parser.add_argument("session", type=Path)
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--cli", type=int, default=20, help="trials also run through `info`")
    args = parser.parse_args(argv)
    if args.quick:
        args.trials, args.cli = 20, 4
    report = Report("bench/fault_bitflips.py", args, ROBUSTNESS)
    from endomeasure.io.session import edit_session

    work = args.work or Path(tempfile.mkdtemp(prefix="bitflips-"))
    work.mkdir(parents=True, exist_ok=True)
    pristine = work / "pristine.h5"
    shutil.copyfile(args.session, pristine)
    with edit_session(pristine):
        pass  # seals the copy: a format 1.0 file gains its checksum and manifest
    truth = raw_dump(pristine)
    data = pristine.read_bytes()
    structure = outside(image_chunks(pristine), len(data))
    rng = np.random.default_rng(args.seed)
    trial_path = work / "trial.h5"
    out = (work / "bitflips.jsonl").open("w")
    rows = []
    for trial in range(args.trials):
        region = "anywhere" if trial % 2 == 0 else "outside image chunks"
        position = int(rng.integers(len(data)) if trial % 2 == 0 else rng.choice(structure))
        bit = int(rng.integers(8))
        flipped = bytearray(data)
        flipped[position] ^= 1 << bit
        trial_path.write_bytes(flipped)
        row = {"trial": trial, "region": region, "position": position, "bit": bit}
        row["changed"] = raw_dump(trial_path) != truth
        row["refusal"] = refused(trial_path)
        if trial < args.cli:
            row["cli"] = cli_info(trial_path)
        out.write(json.dumps(row) + "\n")
        out.flush()
        rows.append(row)
    out.close()

    def count(rows, changed, found):
        return sum(r["changed"] == changed and (r["refusal"] is not None) == found for r in rows)

    accepted_changed = count(rows, True, False)
    check = report.check(TARGET, accepted_changed)
    cli_rows = [r["cli"] for r in rows if "cli" in r]
    cli_ok = sum(c["exit"] == 2 and c["one_line"] and not c["traceback"] for c in cli_rows)
    named = sum(r["refusal"] is not None and "stored items differ" in r["refusal"] for r in rows)
    table = [
        "| flips | changed, found | changed, accepted | unchanged, found | unchanged, accepted |"
        "\n|---|---:|---:|---:|---:|"
    ]
    for region in ("anywhere", "outside image chunks"):
        sub = [r for r in rows if r["region"] == region]
        table.append(
            f"| {region} ({len(sub)}) | {count(sub, True, True)} | {count(sub, True, False)} "
            f"| {count(sub, False, True)} | {count(sub, False, False)} |"
        )
    command = (
        f"python bench/fault_bitflips.py {args.session} --trials {args.trials} --seed {args.seed}"
    )
    body = f"""Command: `{command}`
(a calibrated session of {len(data) / 1e6:.1f} MB, {len(structure) / 1e3:.0f} kB of it outside
the images' compressed chunks).

{chr(10).join(table)}

"Changed" is judged by an independent h5py walk of every object (names, attributes,
types, shapes, data); "found" means `open_session` refused the file before a value was
used. A flip that changes nothing HDF5 reads (padding, free space, the checksum block)
is still found: the file is not what endomeasure wrote. {named} of the refusals named the
damaged items. `endomeasure info` on the first {len(cli_rows)} flipped files: {cli_ok} exited 2
with one line and no traceback.

Changed sessions accepted: **{accepted_changed}** (target 0, issue 18) - {check}.
"""
    return report.finish({SECTION: body})


if __name__ == "__main__":
    raise SystemExit(main())
