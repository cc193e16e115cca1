"""``endomeasure measure``: measurements from correspondences, and the board test.

Two jobs (SPEC section 7):

- :func:`measure_points` — an operator's measurement: the left and right pixels of each
  point, a kind (length, point-line, depth, area, polyline) and a calibrated model;
  triangulate (maximum likelihood), compute the value, predict its uncertainty
  (:func:`endomeasure.measure.predict.predict_measurement_error`, scaled UT, with the
  calibration covariance and the image noise of the calibration residuals), flag it
  when its accuracy index exceeds a threshold, and store it as a ``measurement`` record;
- :func:`board_test` — the paper's Section 3 (its Fig. 4) for every test image of a
  known board (:func:`endomeasure.measure.board_runs.run_board_test`), stored as one
  ``board_test`` record per model.

Each is load -> core -> store -> report; the records are defined in
:mod:`endomeasure.io.records`.

The accuracy index
------------------
An operator needs one number that says whether a measurement can be trusted, as
commercial videoscopes show an accuracy index. Ours is the predicted 95 % error bound
relative to the value (:func:`endomeasure.measure.predict.accuracy_index`), from the
unscented transform of image noise and calibration uncertainty. Above ``warn_percent``
the report carries a warning. For a depth near zero the index is large by construction:
a dent of 0.05 mm measured with +-0.1 mm is not a measurement of that dent.

Operator points (one half only)
-------------------------------
``right=None`` (or ``left=None``) means "find the matches automatically": every given
point is searched in the other half along its epipolar curve
(:func:`endomeasure.measure.correspondence.find_matches`, patch size ``patch``). A point
the search refuses (untextured, ambiguous, not seen by the other half, low score) stops
the measurement: :class:`MatchRefusedError` (exit 1) names the point and the reason,
carries every point's :class:`~endomeasure.measure.correspondence.Match` for the report,
and nothing is stored. ``plot`` draws both halves with the points, their matches (or
refused candidates) and the searched epipolar curves, refused or not.

The uncertainty input of a matched point is not the calibration-residual sigma of a
detected corner. The clicked pixel *defines* the point (standard deviation 0); its match
is uncertain by the search's predicted precision ``precision_px`` (from the patch's
texture and the image noise, with the search's systematic misfit added in quadrature),
applied to both coordinates of the matched pixel. ``sigma`` (``--sigma``) overrides this
with one value for every coordinate of both halves.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from endomeasure import defaults
from endomeasure.conventions import Half, Status, in_half
from endomeasure.errors import BadInputError, GoalNotMetError

if TYPE_CHECKING:
    from endomeasure.measure.board_runs import ModelBoardTest

__all__ = [
    "BoardTestReport",
    "MeasureReport",
    "MatchRefusedError",
    "MeasuredPoint",
    "board_test",
    "measure_points",
]

METHOD = "ut"
"""How ``measure`` propagates the uncertainty (``predict-error`` offers the others)."""


# ----- inputs ---------------------------------------------------------------------------------


def _check_pixels(pixels: np.ndarray, half: Half, model, label: str) -> None:
    width, height = model.config.image_size
    split = model.config.split
    inside = in_half(pixels, half, split, (width, height))
    for i in np.flatnonzero(~inside):
        u, v = pixels[i]
        if not (-0.5 <= u < width - 0.5 and -0.5 <= v < height - 0.5):
            where = f"outside the {width}x{height} image"
        else:
            where = f"not in the {half.label} half (the split is column {split})"
        cols = f"0..{split - 1}" if half is Half.LEFT else f"{split}..{width - 1}"
        raise BadInputError(
            f"{label} point {i + 1} ({u:g},{v:g}) is {where}",
            hint=f"give --{half.label} pixels inside the {half.label} half (columns {cols})",
        )


class MatchRefusedError(GoalNotMetError):
    """The automatic search refused at least one operator point (exit 1).

    Attributes
    ----------
    matches : list of Match
        Every point's search result, refused or not, in the order given.
    plot : str or None
        The picture written before the refusal (``plot=``), if any.
    """

    def __init__(self, what: str, matches: list, *, hint: str | None = None, plot=None):
        super().__init__(what, hint=hint)
        self.matches = matches
        self.plot = plot


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


def _match_other_half(
    model, image: np.ndarray, query: np.ndarray, half: Half, patch: int, depths
) -> list:
    """Matches in the other half of operator points given in ``half``, searched over
    ``depths`` (mm)."""
    from endomeasure.measure.correspondence import MatchSettings, find_matches

    settings = MatchSettings(patch=patch, depth_range_mm=tuple(map(float, depths)))
    return find_matches(model, image, query, half, settings)


def _refusal(matches: list, half: Half, plot) -> MatchRefusedError:
    refused = [(i, m) for i, m in enumerate(matches) if not m.ok]
    reasons = "; ".join(f"point {i + 1}: {m.status.value}: {m.message}" for i, m in refused)
    other = "right" if half is Half.LEFT else "left"
    return MatchRefusedError(
        f"{len(refused)} of {len(matches)} points not matched in the {other} half, nothing "
        f"measured ({reasons})",
        matches,
        hint=f"move the point onto texture both halves see, or give its match with --{other} U,V",
        plot=plot,
    )


# ----- an operator's measurement --------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MeasuredPoint:
    """One triangulated point of a measurement."""

    left: tuple[float, float]
    right: tuple[float, float]
    xyz: tuple[float, float, float]
    gap_mm: float
    rms_px: float
    match: Any = None
    """The automatic search's :class:`~endomeasure.measure.correspondence.Match` when
    this point's other-half pixel was found by it, else None."""

    def to_dict(self) -> dict[str, Any]:
        out = {
            "left_px": list(self.left),
            "right_px": list(self.right),
            "xyz_mm": list(self.xyz),
            "ray_gap_mm": self.gap_mm,
            "reprojection_rms_px": self.rms_px,
        }
        if self.match is not None:
            out["match"] = self.match.to_dict()
        return out


@dataclasses.dataclass(frozen=True)
class MeasureReport:
    """What ``measure`` found for one measurement (plain data).

    ``error``: the value with its predicted bias, std and budget, in ``unit``;
    ``noise``: the image noise the prediction assumed.
    """

    session: str
    record: str
    model: str
    image: str
    kind: str
    unit: str
    points: list[MeasuredPoint]
    error: Any  # PredictedError
    warn_percent: float
    noise: Any  # ImageNoise
    method: str
    plot: str | None = None

    @property
    def matched(self) -> bool:
        """True when the other half's pixels were found by the automatic search."""
        return any(p.match is not None for p in self.points)

    @property
    def warning(self) -> bool:
        """True when the accuracy index exceeds the threshold (or is undefined)."""
        return not (self.error.relative_percent <= self.warn_percent)

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "record": self.record,
            "model": self.model,
            "image": self.image,
            "kind": self.kind,
            "unit": self.unit,
            "points": [p.to_dict() for p in self.points],
            **self.error.to_dict(),
            "warn_percent": self.warn_percent,
            **self.noise.to_dict(correlations=False),
            "method": self.method,
            "plot": self.plot,
            "warning": self.warning,
            "matched": self.matched,
        }


class _Request(NamedTuple):
    """A checked measurement request: the query half's points and what to do with them."""

    spec: Any  # KindSpec
    query_half: Half
    search: bool  # True: find the other half's pixels automatically
    given: dict  # Half -> (n, 2) px or None


def _checked_request(kind, left, right, warn_percent, plot) -> _Request:
    from endomeasure.measure.kinds import kind_spec

    spec = kind_spec(kind)
    if not (math.isfinite(warn_percent) and warn_percent > 0):
        raise BadInputError(
            f"the warning threshold must be a positive percentage, not {warn_percent}"
        )
    if left is None and right is None:
        raise BadInputError("a measurement needs its points: --left U,V and/or --right U,V")
    search = left is None or right is None
    if plot is not None and not search:
        raise BadInputError(
            "--plot draws the automatic search; it has nothing to draw when both "
            "--left and --right points are given",
            hint="leave out the --right (or --left) points, or use --board-test --plot",
        )
    given = {
        Half.LEFT: None if left is None else np.asarray(left, dtype=np.float64).reshape(-1, 2),
        Half.RIGHT: None if right is None else np.asarray(right, dtype=np.float64).reshape(-1, 2),
    }
    query_half = Half.RIGHT if left is None else Half.LEFT  # with both given: the left
    return _Request(spec, query_half, search, given)


def _checked_plot(plot, session, store: bool):
    """The plot file to write (or None) and, when results are stored, the session's
    target: both refused before any work (:mod:`endomeasure.io.outputs`)."""
    from endomeasure.io.outputs import PLOT_SUFFIXES, checked_output, checked_session_target

    if store:
        checked_session_target(session, create=False)
    if plot is None:
        return None
    return checked_output(plot, "plot", inputs=[session], suffixes=PLOT_SUFFIXES)


def _check_count(request: _Request, kind: str) -> int:
    from endomeasure.measure.kinds import check_count

    n = request.given[request.query_half].shape[0]
    check_count(kind, n, "--left/--right pairs")
    return n


def _pixel_pairs(cm, request: _Request, image_pixels, patch: int, plot):
    """Left and right pixels (n, 2) of every point, the search's matches (or None) and
    the written plot (or None), with the calibrated model ``cm``."""
    model = cm.model
    query_half, given = request.query_half, request.given
    n = given[query_half].shape[0]
    _check_pixels(given[query_half], query_half, model, query_half.label)
    matches = written = None
    if request.search:
        matches = _match_other_half(
            model, image_pixels, given[query_half], query_half, patch, search_depths(cm)
        )
        if plot is not None:
            from endomeasure.measure.plots import plot_matches

            written = str(plot_matches(image_pixels, matches, plot, model.config.split))
        if not all(m.ok for m in matches):
            raise _refusal(matches, query_half, written)
        ql = np.array([m.left for m in matches])
        qr = np.array([m.right for m in matches])
    else:
        ql, qr = given[Half.LEFT], given[Half.RIGHT]
        if qr.shape[0] != n:
            raise BadInputError(
                f"{n} --left points but {qr.shape[0]} --right points",
                hint="give one --right U,V for every --left U,V, in the same order",
            )
    _check_pixels(qr, Half.RIGHT, model, "right")
    _check_pixels(ql, Half.LEFT, model, "left")
    return ql, qr, matches, written


def _triangulated(model, model_name: str, ql, qr):
    from endomeasure.solvers.triangulate import triangulate

    tri = triangulate(model, ql, qr, "ml")
    for i in np.flatnonzero(tri.status != Status.OK):
        raise BadInputError(
            f"point {i + 1} cannot be triangulated with the {model_name} model "
            f"({Status(int(tri.status[i])).name.lower().replace('_', ' ')})",
            hint="check that the left and right pixels show the same point",
        )
    return tri


def _predicted(cm, kind: str, value: float, ql, qr, sigma, matches, query_half: Half):
    """The predicted error of a measurement and the image noise it assumed."""
    from endomeasure.measure.predict import ImageNoise, PredictedError, image_noise
    from endomeasure.measure.predict import predict_measurement_error as predict

    if sigma is None and matches is not None:
        # the clicked pixel defines the point; its match carries the search's precision
        pixel_std = np.zeros((ql.shape[0], 2))
        pixel_std[:, 1 if query_half is Half.LEFT else 0] = [m.precision_px for m in matches]
        noise = ImageNoise.per_point(pixel_std, f"match precision, {query_half.label} pixels exact")
    else:
        noise = image_noise(sigma, cm.sigma_px, f"model {cm.name!r}", misfit=cm.misfit)
    pred = predict(cm.model, kind, ql, qr, noise=noise, param_cov=cm.param_cov,
                   misfit=cm.misfit, method=METHOD)  # fmt: skip
    error = PredictedError.of(pred)
    return dataclasses.replace(error, value=value), noise


def measure_points(
    session: str | Path,
    model_name: str,
    image: str,
    left: Sequence[tuple[float, float]] | None,
    right: Sequence[tuple[float, float]] | None,
    kind: str,
    *,
    warn_percent: float = defaults.WARN_PERCENT,
    sigma: float | tuple[float, float] | None = None,
    store: bool = True,
    patch: int = defaults.PATCH_PX,
    plot: str | Path | None = None,
) -> MeasureReport:
    """Triangulate an operator's points, measure, predict the uncertainty and store it.

    Parameters
    ----------
    session : path
    model_name : str
        A model stored by ``calibrate``.
    image : str
        Name of an image in the session (the points are on it).
    left, right : sequence of (u, v), px, or None
        The same points in each half (full-image pixels); one of them None asks for the
        automatic match of the other's points (see the module docstring).
    kind : str
        One of :data:`endomeasure.measure.kinds.KINDS`.
    warn_percent : float
        Accuracy-index threshold, percent.
    sigma : float or (float, float), optional, px
        Image noise of every coordinate, or of u and v; default: from the calibration
        residuals, or for matched points the search's precision (module docstring).
    store : bool
        Write the measurement record.
    patch : int, px
        Side of the correlation patch of the automatic search (odd, >= 5).
    plot : path, optional
        PNG of both halves with the points, matches and epipolar curves (automatic
        search only; written also when a point is refused).

    Returns
    -------
    MeasureReport

    Raises
    ------
    MatchRefusedError
        The search refused a point (nothing is stored).
    """
    from endomeasure.io import records
    from endomeasure.io.session import edit_session, open_session
    from endomeasure.measure.kinds import measure
    from endomeasure.pipeline import calibrated_model

    request = _checked_request(kind, left, right, warn_percent, plot)
    n = _check_count(request, kind)  # before any image is read
    plot = _checked_plot(plot, session, store)
    with open_session(session) as reader:
        # an unknown image is a BadInputError listing the images, an impossible one (its
        # declared shape) a SessionError: both before the search's imports and any work
        reader.image_info(image)
        if request.search:
            from endomeasure.measure.correspondence import MatchSettings

            MatchSettings(patch=patch)  # the patch size checked before any work
        cm = calibrated_model(reader, model_name, session)
        image_pixels = reader.image(image) if request.search else None
    ql, qr, matches, written = _pixel_pairs(cm, request, image_pixels, patch, plot)
    tri = _triangulated(cm.model, model_name, ql, qr)
    value = measure(kind, tri.points)
    error, noise = _predicted(cm, kind, value, ql, qr, sigma, matches, request.query_half)
    measured = [
        MeasuredPoint(
            tuple(map(float, ql[i])),
            tuple(map(float, qr[i])),
            tuple(map(float, tri.points[i])),
            float(tri.gap[i]),
            float(tri.rms[i]),
            None if matches is None else matches[i],
        )
        for i in range(n)
    ]
    report = MeasureReport(str(session), "", model_name, image, kind, request.spec.unit,
                           measured, error, float(warn_percent), noise, METHOD,
                           written)  # fmt: skip
    if store:
        with edit_session(session) as writer:
            name = records.next_measurement_name(writer.record_names(records.MEASUREMENT_RECORD))
            report = dataclasses.replace(report, record=name)
            writer.write_record(records.measurement_record(name, report))
    return report


# ----- the board test ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BoardTestReport:
    session: str
    zone_mm: float
    models: dict[str, ModelBoardTest]
    plot: str | None
    verdicts: dict[str, str] = dataclasses.field(default_factory=dict)
    """Each model's calibration verdict (a failed one is tested for comparison only)."""

    def summary_rows(self) -> list[dict[str, Any]]:
        rows = []
        for m in self.models.values():
            for r, board in zip(m.summary.as_records(), m.summary_board, strict=True):
                r["board"] = str(board)
                r["relative_mean_percent"] = (
                    100.0 * r["mean_error"] / r["true"] if r["true"] else None
                )
                rows.append(r)
        return rows

    def to_dict(self, details: bool = True) -> dict[str, Any]:
        out: dict[str, Any] = {
            "session": self.session,
            "zone_mm": self.zone_mm,
            "summary": self.summary_rows(),
            "plot": self.plot,
            "verdicts": dict(self.verdicts),
        }
        if details:
            models = {}
            for name, m in self.models.items():
                records = m.table.as_records()
                images = []
                for k, image in enumerate(m.images):
                    ids, ql, qr, xyz = m.image_pixels(k)
                    sel = m.corner_image == k
                    images.append(
                        {
                            "image": image,
                            "board": m.board[k],
                            "corners": [
                                {
                                    "id": int(ids[i]),
                                    "left_px": ql[i].tolist(),
                                    "right_px": qr[i].tolist(),
                                    "xyz_mm": xyz[i].tolist(),
                                    "ray_gap_mm": float(m.corner_gap[sel][i]),
                                    "status": int(m.corner_status[sel][i]),
                                }
                                for i in range(ids.size)
                            ],
                            "measurements": [
                                {k2: v for k2, v in r.items() if k2 != "image"}
                                for r in records
                                if r["image"] == k
                            ],
                        }
                    )
                models[name] = {"images": images}
            out["models"] = models
        return out


def _models_to_run(reader, model: str, session) -> list[str]:
    """The stored models a board test runs: one, or for ``'all'`` every stored model, the
    registered ones in registry order first."""
    from endomeasure.models import MODELS

    if model != defaults.ALL_MODELS:
        return [model]
    held = reader.model_names()
    names = [n for n in MODELS if n in held] + [n for n in held if n not in MODELS]
    if not names:
        raise BadInputError(
            "the session holds no calibrated model",
            path=str(session),
            hint=f"run `endomeasure calibrate {session}` first",
        )
    return names


def board_test(
    session: str | Path,
    model: str = defaults.ALL_MODELS,
    zone_mm: float = defaults.ZONE_MM,
    plot: str | Path | None = None,
    store: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
) -> BoardTestReport:
    """The board test of one or all calibrated models (see the module docstring).

    Parameters
    ----------
    session : path
    model : str
        A stored model name or ``'all'``.
    zone_mm : float, mm
        Width of the distance zones.
    plot : path, optional
        PNG of the paper's Fig. 4.
    store : bool
        Write one ``board_test`` record per model.
    on_progress : callable(done, total), optional
        Called after each model.

    Returns
    -------
    BoardTestReport
    """
    from endomeasure.io.records import board_test_record, load_calibrated_model
    from endomeasure.io.session import edit_session, open_session
    from endomeasure.measure.board_runs import board_sets, run_board_test
    from endomeasure.measure.board_test import checked_zone_mm

    zone_mm = checked_zone_mm(zone_mm)
    plot = _checked_plot(plot, session, store)
    with open_session(session) as reader:
        names = _models_to_run(reader, model, session)
        # the board test is the diagnostic that shows a failed calibration's errors
        calibrated = {
            n: load_calibrated_model(reader, n, session, allow_failed=True) for n in names
        }
        models = {n: cm.model for n, cm in calibrated.items()}
        boards = {name: b.attrs for name, b in reader.boards().items()}
        sets = board_sets(boards, reader.detections(), reader.image_names("test"), str(session))
    results = {}
    for i, (name, m) in enumerate(models.items()):
        results[name] = run_board_test(name, m, sets, zone_mm)
        if on_progress is not None:
            on_progress(i + 1, len(models))
    if store:
        with edit_session(session) as writer:
            for bt in results.values():
                writer.write_record(board_test_record(bt, zone_mm))
    written = None
    if plot is not None:
        from endomeasure.measure.plots import plot_board_test

        written = str(plot_board_test(results, zone_mm, plot))
    verdicts = {n: cm.verdict for n, cm in calibrated.items()}
    return BoardTestReport(str(session), float(zone_mm), results, written, verdicts)
