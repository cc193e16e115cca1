"""``endomeasure info``: what a session holds, as a plain report object."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from typing import Any

from endomeasure.conventions import Half
from endomeasure.io.records import stored_verdict
from endomeasure.io.session import IMAGE_SETS, open_session, salvage_session

__all__ = ["RepairReport", "SessionSummary", "repair_session", "summarise_session"]


@dataclass(frozen=True)
class SessionSummary:
    """A summary of one session.

    Attributes
    ----------
    path, format_version, created_by : str
    checksum : str
        ``ok`` (the file checksum matched) or ``unchecked`` (a format 1.0 file, which
        has none until its next edit).
    image_size : [width, height] or None, px
    split : int or None, px
        First column of the right half.
    images : dict of str to int
        Number of embedded images per set (``calib``, ``test``, ``scene``).
    boards : list of dict
        ``name``, ``spec``.
    detections : list of dict
        Per board and half: ``images`` (detections stored), ``found`` (succeeded),
        ``failed``, ``corners`` (total over the successful ones).
    models : list of dict
        ``name``, ``registry_name``, ``n_params``, ``verdict`` (``unjudged`` for models
        stored without one) with ``verdict_reasons`` and, when stored, ``rms`` with
        ``rms_units``.
    records : dict of str to int
        Number of records per kind.
    """

    path: str
    format_version: str
    created_by: str
    checksum: str
    image_size: list[int] | None
    split: int | None
    images: dict[str, int]
    boards: list[dict[str, Any]] = field(default_factory=list)
    detections: list[dict[str, Any]] = field(default_factory=list)
    models: list[dict[str, Any]] = field(default_factory=list)
    records: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict."""
        return asdict(self)


def summarise_session(path: str | os.PathLike) -> SessionSummary:
    """Summarise what a session holds.

    Raises
    ------
    SessionError, SessionVersionError
        The file cannot be read as a session of a known version.
    """
    with open_session(path) as session:
        meta = session.metadata()
        counts = dict.fromkeys(IMAGE_SETS, 0)
        for info in session.images_info():
            counts[info.image_set] = counts.get(info.image_set, 0) + 1
        boards = [{"name": b.name, "spec": b.spec} for b in session.boards().values()]

        per_board_half: dict[tuple[str, int], dict[str, Any]] = {}
        for det in session.detections():
            key = (det.board, int(det.half))
            entry = per_board_half.setdefault(
                key,
                {
                    "board": det.board,
                    "half": Half(det.half).label,
                    "images": 0,
                    "found": 0,
                    "failed": 0,
                    "corners": 0,
                },
            )
            entry["images"] += 1
            if det.ok:
                entry["found"] += 1
                entry["corners"] += int(det.ids.shape[0])
            else:
                entry["failed"] += 1
        detections = [per_board_half[key] for key in sorted(per_board_half)]

        models = []
        for name in session.model_names():
            model = session.model(name)
            entry = {
                "name": name,
                "registry_name": model.registry_name,
                "n_params": int(model.params.shape[0]),
            }
            if "rms" in model.attrs:
                entry["rms"] = float(model.attrs["rms"])
                entry["rms_units"] = model.units.get("rms", "px")
            entry["verdict"], entry["verdict_reasons"] = stored_verdict(model)
            models.append(entry)

        records = {kind: len(session.record_names(kind)) for kind in session.record_kinds()}
        return SessionSummary(
            path=str(path),
            format_version=meta.format_version,
            created_by=meta.created_by,
            checksum=session.checksum,
            image_size=None if meta.image_size is None else list(meta.image_size),
            split=meta.split,
            images=counts,
            boards=boards,
            detections=detections,
            models=models,
            records=records,
        )


@dataclass(frozen=True)
class RepairReport:
    """What ``endomeasure repair`` kept of a session.

    Attributes
    ----------
    source, out : str
    checksum : str
        The source's file check: ``ok``, ``unchecked`` (format 1.0) or ``damaged``.
    kept : list of str
        Items copied into ``out`` (their digests matched).
    dropped : dict of str to str
        Items left out, with why.
    """

    source: str
    out: str
    checksum: str
    kept: list[str]
    dropped: dict[str, str]

    @property
    def complete(self) -> bool:
        return not self.dropped

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "complete": self.complete}


def repair_session(source: str | os.PathLike, out: str | os.PathLike) -> RepairReport:
    """Copy the intact items of a (damaged) session into the new session file ``out``."""
    report, checksum = salvage_session(source, out)
    return RepairReport(
        source=str(source),
        out=str(out),
        checksum=checksum,
        kept=list(report.intact),
        dropped=dict(report.damaged),
    )
