"""The commands' pipelines: one module per command, which import none of each other;
what two of them share lives here.

The calibrated model a measurement or a prediction uses.

:func:`~endomeasure.io.records.load_calibrated_model` reads what ``calibrate`` stored;
this adds what the uncertainty needs beyond it and measures from it: the model misfit
the calibration's residuals show beyond noise (:mod:`endomeasure.solvers.misfit`), so
that sessions of any version carry it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

__all__ = ["calibrated_model"]


def calibrated_model(reader, name: str, session: str | Path, *, allow_failed: bool = False):
    """The model ``name`` of an open session as a
    :class:`~endomeasure.io.records.CalibratedModel` with its ``misfit`` (None where the
    record holds no residuals or too few neighbouring corners)."""
    from endomeasure.io.records import calibrated_from_record, inlier_residuals, stored_model_record
    from endomeasure.solvers.misfit import fit_misfit

    record = stored_model_record(reader, name, session)
    cm = calibrated_from_record(record, session, allow_failed=allow_failed)
    residuals = inlier_residuals(record)
    return dataclasses.replace(cm, misfit=None if residuals is None else fit_misfit(*residuals))
