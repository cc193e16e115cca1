"""One design of a sweep, evaluated: a pure function of the spec and the design's index.

For each tolerance draw of the design (:meth:`SweepSpec.drawn_preset`): the truth optics
of the drawn preset (the simulator's own tracer), the calibration protocol's board poses
(:func:`~endomeasure.simulate.scenes.plan_set`), the board corners projected through the
truth with Gaussian detector noise (no rendering), the calibration of the spec's model
by the project's own start and solver (seeded with the nominal design when the spec
says ``start: design``, as a lab that knows its adapter's drawings would), and the
predicted 95 % error of each template at each depth.

The 95 % error of one template placement is ``|m - t| + Z95 sigma``: ``m`` the length
the calibrated model measures from the template's noise-free truth pixels (so the
model's own systematic error over the field counts), ``t`` its true length, ``sigma``
the predicted standard deviation from the image noise and the calibration covariance
(:func:`~endomeasure.measure.predict.predict_measurement_error`). A design's figure is
the ``field_quantile`` of that error over the placements of a depth plane seen by both
halves (:func:`~endomeasure.measure.predict.volume_grid`), relative to ``t``, in %.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from endomeasure.conventions import Half, Status, in_half
from endomeasure.errors import BadInputError, EndomeasureError
from endomeasure.study.spec import SweepSpec, get_path

__all__ = ["STATUS_NAMES", "DesignResult", "evaluate_design", "design_cost"]

STATUS_NAMES = ("ok", "warning", "failed", "infeasible")
"""Per draw: the calibration's verdict, or ``infeasible`` (drawn optics not physical,
or no pose of the protocol shows a board in both halves)."""
OK, WARNING, FAILED, INFEASIBLE = range(4)


@dataclasses.dataclass(frozen=True, eq=False)
class DesignResult:
    """A design's evaluation; arrays over D draws, T templates, Z depths, S sigmas.

    ``seconds`` and ``cpu_seconds`` are the evaluation's wall time and the CPU time of
    the thread that ran it (the only fields that are not a function of the spec and the
    index; ``cpu_seconds / seconds`` below 1 is time spent waiting for a core).
    """

    index: int
    seed: int
    values: np.ndarray  # (A,) the axes' values
    cost: float
    status: np.ndarray  # (D,) int8, STATUS_NAMES
    reasons: tuple[str, ...]  # (D,) why a draw is not ok ("" when ok)
    rms_px: np.ndarray  # (D,) calibration RMS residual, NaN where not calibrated
    e95_pct: np.ndarray  # (D, T, Z) field quantile of the 95 % error, % of the true value
    n_points: np.ndarray  # (D, T, Z) template placements seen by both halves
    sigmas: np.ndarray  # (D, S) calibrated parameter standard deviations
    seconds: float = 0.0
    cpu_seconds: float = float("nan")

    FIELDS = ("values", "status", "rms_px", "e95_pct", "n_points", "sigmas")

    @property
    def success(self) -> float:
        """Fraction of the draws whose calibration was ok or a warning."""
        return float(np.mean(self.status <= WARNING))

    @property
    def merit(self) -> float:
        """The worst 95 % error (%) over templates, depths and calibrated draws (NaN when
        none calibrated)."""
        good = self.status <= WARNING
        if not good.any():
            return float("nan")
        return float(np.max(self.e95_pct[good]))

    def same_as(self, other: DesignResult) -> bool:
        """Equal in everything but the wall time (NaN equal to NaN)."""
        same_cost = self.cost == other.cost or (np.isnan(self.cost) and np.isnan(other.cost))
        same_ids = (self.index, self.seed, self.reasons) == (other.index, other.seed, other.reasons)
        return (
            same_ids
            and same_cost
            and all(
                np.array_equal(getattr(self, f), getattr(other, f), equal_nan=True)
                for f in self.FIELDS
            )
        )


def design_cost(spec: SweepSpec, data: dict[str, Any], values: tuple[float, ...]) -> float:
    """The spec's cost of a nominal design preset (an axis, a path or a derived cost)."""
    if spec.cost in spec.axis_names:
        return float(values[spec.axis_names.index(spec.cost)])
    if spec.cost == "prism_thickness_mm":
        return float(data["prism"]["apex_mm"][2]) - float(data["prism"]["rear_face"]["d_mm"])
    if spec.cost == "prism_length_mm":
        return float(data["prism"]["apex_mm"][2])
    return float(get_path(data, spec.cost))


def _corners(optics, shots, noise_px: float, rng: np.random.Generator):
    """Board corners of each shot projected by the truth optics with Gaussian noise: the
    :class:`ViewDetections` and the boards (those inside their half after the noise)."""
    from endomeasure.solvers.calibrate import ViewDetections

    size, split = optics.config.image_size, optics.config.split
    views, boards = [], {}
    for shot in shots:
        board = shot.target
        boards.setdefault(board.name, board.corners_board)
        ids, pixels = [], []
        for half in Half:
            proj = optics.project(board.corners_camera, half)
            ok = np.flatnonzero(proj.status == Status.OK)
            q = proj.pixels[ok] + noise_px * rng.standard_normal((ok.size, 2))
            keep = in_half(q, half, split, size)
            ids.append(ok[keep])
            pixels.append(q[keep])
        views.append(ViewDetections(shot.name, board.name, tuple(ids), tuple(pixels)))
    return views, boards


def _errors(spec: SweepSpec, optics, result) -> tuple[np.ndarray, np.ndarray]:
    """The (T, Z) field quantiles of the 95 % error (%) and the placements counted."""
    from endomeasure.measure.kinds import evaluate
    from endomeasure.measure.predict import (
        TEMPLATES,
        Z95,
        ImageNoise,
        predict_measurement_error,
        template_points,
        volume_grid,
    )

    model, cov = result.uncertainty_model, np.asarray(result.measurement_covariance)
    size, split = optics.config.image_size, optics.config.split
    e95 = np.full((len(spec.templates), len(spec.depths_mm)), np.nan)
    count = np.zeros(e95.shape, dtype=np.int64)
    for j, z in enumerate(spec.depths_mm):
        centres = volume_grid(model, np.array([z]), *spec.grid)
        for i, t in enumerate(spec.templates):
            kind = TEMPLATES[t.template][0]
            pts = template_points(t.template, centres, t.size_mm)
            true = float(
                evaluate(kind, template_points(t.template, np.zeros((1, 3)), t.size_mm))[0]
            )
            q, seen = [], np.ones(pts.shape[0], dtype=bool)
            for half in Half:
                proj = optics.project(pts.reshape(-1, 3), half)
                pix = proj.pixels.reshape(*pts.shape[:2], 2)
                ok = (proj.status == Status.OK).reshape(pts.shape[:2])
                seen &= np.all(ok & in_half(pix, half, split, size), axis=1)
                q.append(pix)
            if not seen.any():
                continue
            pred = predict_measurement_error(
                model,
                kind,
                q[0][seen],
                q[1][seen],
                noise=ImageNoise(spec.noise_px),
                param_cov=cov,
            )
            err = (np.abs(pred.value - true) + Z95 * pred.std) / abs(true) * 100.0
            err = err[np.isfinite(err)]
            if err.size:
                e95[i, j] = float(np.quantile(err, spec.field_quantile))
                count[i, j] = err.size
    return e95, count


def _draw(spec: SweepSpec, index: int, draw: int, seed_model) -> tuple:
    """(status, reason, rms, e95 (T, Z), n (T, Z), sigmas (S,)) of one tolerance draw."""
    from endomeasure.simulate.design import DesignError, check_optics
    from endomeasure.simulate.preset import Preset
    from endomeasure.simulate.scenes import plan_set
    from endomeasure.solvers.calibrate import CalibrationOptions, calibrate

    shape = (len(spec.templates), len(spec.depths_mm))
    nothing = (np.full(shape, np.nan), np.zeros(shape, np.int64), np.full(len(spec.sigmas), np.nan))
    draw_seed = int(np.random.SeedSequence([spec.design_seed(index), draw]).generate_state(1)[0])
    try:
        preset = Preset.from_dict(spec.drawn_preset(index, draw))
        optics = preset.truth_optics
        check_optics(optics)
        shots = plan_set(preset, "calib", draw_seed)
    except (BadInputError, DesignError, ValueError) as exc:
        reason = exc.what if isinstance(exc, BadInputError) else str(exc)
        return (INFEASIBLE, reason, np.nan, *nothing)
    rng = np.random.default_rng([draw_seed, 0x6E6F6973])
    views, boards = _corners(optics, shots, spec.noise_px, rng)
    options = CalibrationOptions(seed=None if seed_model is None else seed_model.to_dict())
    try:
        result = calibrate(
            spec.model, views, boards, optics.config.image_size, optics.config.split, options
        )
    except EndomeasureError as exc:
        return (FAILED, exc.what, np.nan, *nothing)
    level = result.verdict.level if result.verdict is not None else "ok"
    status = {"ok": OK, "warning": WARNING}.get(level, FAILED)
    reason = "" if status == OK else "; ".join(result.verdict.reasons)
    named = result.named_std()
    sigmas = np.array([named.get(s, np.nan) for s in spec.sigmas], dtype=np.float64)
    e95, count = _errors(spec, optics, result)
    return (status, reason, float(result.rms), e95, count, sigmas)


def evaluate_design(spec: SweepSpec, index: int) -> DesignResult:
    """Evaluate design ``index`` of the spec over its tolerance draws (see the module
    docstring); deterministic for the spec and the index, in any process."""
    from endomeasure.simulate.preset import Preset

    if not 0 <= int(index) < spec.n_designs:
        raise BadInputError(f"design index {index} is outside 0-{spec.n_designs - 1}")
    t0, cpu0 = time.perf_counter(), time.thread_time()
    values = spec.design_values(index)
    nominal = spec.design_preset(index)
    seed_model = Preset.from_dict(nominal).truth_model if spec.start == "design" else None
    draws = [_draw(spec, index, d, seed_model) for d in range(spec.draws)]
    status, reasons, rms, e95, count, sigmas = zip(*draws, strict=True)
    return DesignResult(
        index=int(index),
        seed=spec.design_seed(index),
        values=np.array(values),
        cost=design_cost(spec, nominal, values),
        status=np.array(status, dtype=np.int8),
        reasons=tuple(reasons),
        rms_px=np.array(rms),
        e95_pct=np.stack(e95),
        n_points=np.stack(count),
        sigmas=np.stack(sigmas).reshape(spec.draws, len(spec.sigmas)),
        seconds=time.perf_counter() - t0,
        cpu_seconds=time.thread_time() - cpu0,
    )
