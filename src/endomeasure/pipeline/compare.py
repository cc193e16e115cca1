"""``endomeasure compare``: where and by how much two calibrations disagree.

Load two calibrated models (two sessions, or two models of one session; both opened
read-only) -> compare them over a grid of the working volume
(:func:`endomeasure.measure.compare.compare_models`: pixel disagreement in both halves,
and the length difference of a 1 mm segment against the two calibrations' combined +-)
-> the per-depth summary, the verdict and, optionally, the maps as a figure. Nothing is
stored.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError

__all__ = ["CompareReport", "compare_calibrations"]

DEFAULT_PLANES = 3
"""Depth planes over the depths both calibrations saw, when ``--depths`` is not given."""
FALLBACK_DEPTHS_MM = (20.0, 30.0, 40.0)
"""Depths when a calibration stores no depth range, mm."""


@dataclasses.dataclass(frozen=True)
class CompareReport:
    """Two calibrations compared: their names, the summary per depth and the verdict."""

    a: str
    b: str
    model_a: str
    model_b: str
    depths: list[float]
    grid: tuple[int, int]
    per_depth: list[dict[str, Any]]
    rms_z_limit: float
    alpha: float
    plot: str | None
    comparison: Any = dataclasses.field(repr=False)  # Comparison

    @property
    def agree(self) -> bool:
        return bool(self.per_depth) and all(r["agree"] for r in self.per_depth)

    @property
    def verdict(self) -> str:
        return "agree" if self.agree else "disagree"

    @property
    def reasons(self) -> list[str]:
        """The depths where they disagree, one sentence each (empty when they agree)."""
        return [
            f"at z = {r['z_mm']:g} mm a {self.comparison.size_mm:g} mm length differs by "
            f"{r['length_diff_rms_mm']:.4f} mm RMS, {r['rms_z']:.2f} times the combined +- "
            f"(limit {self.rms_z_limit:.2f}); {100 * r['outside_band']:.0f}% of the field "
            "outside 2 sigma"
            for r in self.per_depth
            if not r["agree"]
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "a": {"session": self.a, "model": self.model_a},
            "b": {"session": self.b, "model": self.model_b},
            "verdict": self.verdict,
            "reasons": self.reasons,
            "alpha": self.alpha,
            "rms_z_limit": self.rms_z_limit,
            "size_mm": self.comparison.size_mm,
            "depths": self.depths,
            "grid": list(self.grid),
            "per_depth": self.per_depth,
            "plot": self.plot,
        }


def _default_depths(cms) -> list[float]:
    ranges = [cm.depth_range_mm for cm in cms]
    if any(r is None for r in ranges):
        return list(FALLBACK_DEPTHS_MM)
    near, far = max(r[0] for r in ranges), min(r[1] for r in ranges)
    if not near < far:
        raise BadInputError(
            "the two calibrations saw the board at depths that do not overlap "
            f"({ranges[0][0]:.1f}-{ranges[0][1]:.1f} and {ranges[1][0]:.1f}-{ranges[1][1]:.1f} mm)",
            hint="give --depths where both were calibrated",
        )
    return [float(d) for d in np.linspace(near, far, DEFAULT_PLANES + 2)[1:-1].round(1)]


def _load(session, model: str):
    from endomeasure.io.session import open_session
    from endomeasure.pipeline import calibrated_model

    with open_session(session) as reader:
        return calibrated_model(reader, model, session)


def compare_calibrations(
    a: str | Path,
    b: str | Path,
    model_a: str = "raytrace",
    model_b: str | None = None,
    *,
    depths: Sequence[float] | None = None,
    grid: tuple[int, int] = (16, 12),
    plot: str | Path | None = None,
) -> CompareReport:
    """Compare calibration ``model_a`` of session ``a`` with ``model_b`` (default: the same
    name) of session ``b`` (which may be ``a``).

    ``depths``: planes, mm (default: :data:`DEFAULT_PLANES` inside the depths both
    calibrations saw); ``grid``: pixels per row and column over A's left half; ``plot``:
    PNG of the disagreement maps.
    """
    from endomeasure import defaults
    from endomeasure.io.outputs import PLOT_SUFFIXES, checked_output
    from endomeasure.measure.compare import compare_models

    model_b = model_a if model_b is None else model_b
    if Path(a).resolve() == Path(b).resolve() and model_a == model_b:
        raise BadInputError(
            f"A and B are the same calibration ({model_a!r} of {a})",
            hint="give another session, or --model-b another model of this one",
        )
    n_u, n_v = grid
    if n_u < 2 or n_v < 2 or n_u * n_v > defaults.MAX_MAP_POINTS:
        raise BadInputError(f"the grid needs 2x2 to {defaults.MAX_MAP_POINTS} points, got "
                            f"{n_u}x{n_v}")  # fmt: skip
    if depths is not None and len(depths) > defaults.MAX_MAP_DEPTHS:
        raise BadInputError(f"{len(depths)} depth planes is more than {defaults.MAX_MAP_DEPTHS}",
                            hint="give fewer --depths")  # fmt: skip
    if plot is not None:
        plot = checked_output(plot, "plot", inputs=[a, b], suffixes=PLOT_SUFFIXES)
    cm_a, cm_b = _load(a, model_a), _load(b, model_b)
    z = _default_depths((cm_a, cm_b)) if depths is None else [float(d) for d in depths]
    c = compare_models(cm_a.model, cm_b.model, z, (n_u, n_v), cov_a=cm_a.param_cov,
                       cov_b=cm_b.param_cov)  # fmt: skip
    written = None
    if plot is not None:
        from endomeasure.measure.plots import plot_comparison

        labels = (f"A ({model_a}, {Path(a).name})", f"B ({model_b}, {Path(b).name})")
        written = str(plot_comparison(c, plot, labels))
    return CompareReport(
        str(a), str(b), model_a, model_b, [float(v) for v in c.depths], (n_u, n_v),
        c.per_depth(), c.rms_z_limit, c.alpha, written, c,
    )  # fmt: skip
