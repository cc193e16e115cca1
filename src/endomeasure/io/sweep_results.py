"""The results file of ``endomeasure sweep``: one HDF5 group per evaluated design.

Layout: root attributes ``format`` (``endomeasure-sweep-results``), ``version``,
``spec`` (the spec's JSON), ``spec_digest`` (of the spec and its base preset),
``n_designs``, ``axes`` (JSON list); a group ``designs/NNNNNN`` per design with the
attributes ``index``, ``seed``, ``cost``, ``seconds``, ``cpu_seconds`` (the evaluation's
wall and CPU time; files written before ``cpu_seconds`` lack it), ``reasons`` (JSON
list) and the datasets of :attr:`DesignResult.FIELDS`, and last the attribute
``complete``. The file
is opened for one design at a time and closed after it (so an interrupted sweep leaves
every finished design readable); a group without ``complete`` is from a write that was
cut short and is removed when the sweep resumes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.io.outputs import atomic_write

__all__ = ["RESULTS_FORMAT", "RESULTS_VERSION", "SweepResultsFile"]

RESULTS_FORMAT = "endomeasure-sweep-results"
RESULTS_VERSION = 1


class SweepResultsFile:
    """A results file bound to one spec (its digest): :meth:`finished`, :meth:`append`,
    :meth:`read_all`."""

    def __init__(
        self, path: str | Path, spec_json: str, digest: str, n_designs: int, axes: tuple[str, ...]
    ):
        self.path = Path(path)
        self.digest = digest
        if self.path.exists():
            self._check_and_clean()
        else:
            attrs = {"format": RESULTS_FORMAT, "version": RESULTS_VERSION, "spec": spec_json,
                     "spec_digest": digest, "n_designs": int(n_designs),
                     "axes": json.dumps(list(axes))}  # fmt: skip

            def create(tmp: Path) -> None:
                with h5py.File(tmp, "w") as f:
                    f.attrs.update(attrs)
                    f.create_group("designs")

            atomic_write(self.path, create)

    def _check_and_clean(self) -> None:
        try:
            with h5py.File(self.path, "a") as f:
                if f.attrs.get("format") != RESULTS_FORMAT:
                    raise BadInputError(
                        "the output is not a sweep results file",
                        path=str(self.path),
                        hint="give another -o",
                    )
                if f.attrs.get("spec_digest") != self.digest:
                    raise BadInputError(
                        "the output holds the results of another sweep spec",
                        path=str(self.path),
                        hint="give another -o, or the spec it was made of",
                    )
                for name in [n for n, g in f["designs"].items() if not g.attrs.get("complete")]:
                    del f["designs"][name]
        except OSError as exc:
            raise BadInputError(
                f"cannot open the sweep results ({exc})", path=str(self.path)
            ) from None

    def finished(self) -> set[int]:
        """Indices of the designs stored completely."""
        with h5py.File(self.path, "r") as f:
            return {int(g.attrs["index"]) for g in f["designs"].values() if g.attrs.get("complete")}

    def append(self, result) -> None:
        """Store one :class:`~endomeasure.study.evaluate.DesignResult` (replacing a
        partial group of the same design)."""
        with h5py.File(self.path, "a") as f:
            name = f"{int(result.index):06d}"
            if name in f["designs"]:
                del f["designs"][name]
            g = f["designs"].create_group(name)
            g.attrs.update(
                {
                    "index": int(result.index),
                    "seed": int(result.seed),
                    "cost": float(result.cost),
                    "seconds": float(result.seconds),
                    "cpu_seconds": float(result.cpu_seconds),
                    "reasons": json.dumps(list(result.reasons)),
                }
            )
            for field in result.FIELDS:
                g.create_dataset(field, data=np.asarray(getattr(result, field)))
            f.flush()
            g.attrs["complete"] = 1

    def read_all(self) -> list[dict[str, Any]]:
        """Every complete design as the keywords of ``DesignResult``, by index."""
        out = []
        with h5py.File(self.path, "r") as f:
            for g in f["designs"].values():
                if not g.attrs.get("complete"):
                    continue
                row = {field: np.array(data) for field, data in g.items()}  # as append wrote
                row.update(
                    index=int(g.attrs["index"]),
                    seed=int(g.attrs["seed"]),
                    cost=float(g.attrs["cost"]),
                    seconds=float(g.attrs["seconds"]),
                    cpu_seconds=float(g.attrs.get("cpu_seconds", np.nan)),
                    reasons=tuple(json.loads(g.attrs["reasons"])),
                )
                out.append(row)
        return sorted(out, key=lambda r: r["index"])
