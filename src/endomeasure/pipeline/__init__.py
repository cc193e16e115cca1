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

__all__ = ["calibrated_model", "search_depths", "SEARCH_DEPTH_MARGINS"]


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


SEARCH_DEPTH_MARGINS = (1.25, 2.0)
"""The automatic search covers the depths where the calibration saw the board, from
the nearest / the first to the farthest x the second: where the user calibrated is
where the probe works, and a match beyond the searched depths is not found at all (or
another feature on the curve is). The near end sets most of the curve's length in
pixels (the disparity goes as 1 / depth), and a longer curve holds more look-alikes, so
the margin is smaller there: at half the nearest depth a mark of the default preset's
scene found a neighbouring mark as a second candidate, and on the 39 random designs'
scenes (``bench/operator_designs.py``) more distances were refused as ambiguous than
with 1.25. Without a stored depth range: the search's own default."""


def search_depths(cm) -> tuple[float, float]:
    """The depths (mm) the automatic search spans for the calibrated model ``cm``
    (:data:`SEARCH_DEPTH_MARGINS`)."""
    from endomeasure.measure.epipolar import DEPTH_RANGE_MM

    if cm.depth_range_mm is None:
        return DEPTH_RANGE_MM
    (near, far), (near_margin, far_margin) = cm.depth_range_mm, SEARCH_DEPTH_MARGINS
    return (near / near_margin, far * far_margin)
