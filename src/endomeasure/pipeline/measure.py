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

The measurement plane
---------------------
``plane`` (``--plane`` x3): three left-half points, matched (or given with
``plane_right``) and triangulated, span a plane; the measured ``left`` points (a depth's
4th only, :func:`~endomeasure.measure.kinds.projected_points`) are not matched but
placed where their left ray meets it (:func:`~endomeasure.measure.kinds.ray_plane`).
The +- is the same unscented transform with the plane's points as inputs too
(``plane=True`` of :func:`~endomeasure.measure.predict.predict_measurement_error`); a
placed point's left pixel follows the rule above (exact when clicked), its right pixel
is no input.
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
from endomeasure.pipeline import search_depths

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
    projected: bool = False
    """Placed where its left ray meets the measurement plane (``--plane``), not
    triangulated: no right pixel, ray gap or reprojection error (NaN)."""

    def to_dict(self) -> dict[str, Any]:
        out = {
            "left_px": list(self.left),
            "right_px": None if self.projected else list(self.right),
            "xyz_mm": list(self.xyz),
            "ray_gap_mm": None if self.projected else self.gap_mm,
            "reprojection_rms_px": None if self.projected else self.rms_px,
            "projected": self.projected,
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
    plane: list[MeasuredPoint] | None = None
    """The three triangulated points of the measurement plane (``--plane``), else None."""

    @property
    def matches(self) -> list:
        """The automatic search's matches, in the order searched (the plane's points
        first); empty without a search."""
        points = (self.plane or []) + self.points
        return [p.match for p in points if p.match is not None]

    @property
    def matched(self) -> bool:
        """True when the other half's pixels were found by the automatic search."""
        return bool(self.matches)

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
            "modifier": None if self.plane is None else "plane",
            "plane": None if self.plane is None else [p.to_dict() for p in self.plane],
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
    if spec.dense:  # measured on the dense surface: pipeline.profile.measure_profile
        raise BadInputError(
            f"{kind} is measured on the dense surface, not from triangulated points",
            hint=f"use `endomeasure measure SESSION --image NAME --kind {kind} --left U,V ...`",
        )
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


def _predicted(
    cm, kind: str, value: float, ql, qr, sigma, matches, query_half: Half, projected: int = 0
):
    """The predicted error of a measurement and the image noise it assumed; with
    ``projected``, ``ql``/``qr`` are a measurement plane's points, the kind's
    triangulated points and its last ``projected`` points, placed on the plane."""
    from endomeasure.measure.predict import ImageNoise, PredictedError, image_noise
    from endomeasure.measure.predict import predict_measurement_error as predict

    n = ql.shape[0] - projected
    if sigma is None and matches is not None:
        # the clicked pixel defines the point; its match carries the search's precision
        pixel_std = np.zeros((n, 2))
        pixel_std[:, 1 if query_half is Half.LEFT else 0] = [m.precision_px for m in matches]
        noise = ImageNoise.per_point(pixel_std, f"match precision, {query_half.label} pixels exact")
    else:
        noise = image_noise(sigma, cm.sigma_px, f"model {cm.name!r}", misfit=cm.misfit)
    if projected:
        noise = _with_projected(noise, n, projected, clicked=sigma is None and matches is not None)
    pred = predict(cm.model, kind, ql, qr, noise=noise, param_cov=cm.param_cov,
                   misfit=cm.misfit, method=METHOD, plane=bool(projected))  # fmt: skip
    error = PredictedError.of(pred)
    return dataclasses.replace(error, value=value), noise


def _with_projected(noise, n: int, projected: int, *, clicked: bool):
    """``noise`` of ``n`` triangulated points, extended (per point, ``u_L, v_L, u_R,
    v_R``) to ``projected`` points placed on a measurement plane: their left pixel at
    the noise of the others' (exact when clicked), their unused right pixel at none."""
    from endomeasure.measure.predict import ImageNoise
    from endomeasure.solvers.uncertainty import pixel_sigmas

    if noise.pixel_std is not None:
        std = np.asarray(noise.pixel_std, dtype=np.float64)
        std = np.repeat(std, 2, axis=-1) if std.shape[-1] == 2 else std
    else:
        std = np.tile(np.tile(pixel_sigmas(noise.sigma), 2), (n, 1))
    extra = np.zeros((projected, 4))
    if not clicked:
        extra[:, :2] = pixel_sigmas(noise.sigma)
    return ImageNoise.per_point(np.vstack([std, extra]), noise.source)


# ----- the measurement plane (``--plane``) ------------------------------------------------------


class _PlaneRequest(NamedTuple):
    """A checked ``--plane`` measurement: the points to triangulate (the plane's three,
    then the kind's that are not projected) and the left pixels placed on the plane."""

    triangulated: _Request
    projected: np.ndarray  # (k, 2) px


def _checked_plane_request(kind, left, right, plane, plane_right, warn_percent, plot):
    from endomeasure.measure.kinds import PLANE_POINTS, check_count, kind_spec, projected_points

    kind_spec(kind)
    if len(plane) != PLANE_POINTS:
        raise BadInputError(
            f"--plane needs exactly {PLANE_POINTS} points, got {len(plane)}",
            hint="give --plane U,V three times (left-half pixels of three points on the plane)",
        )
    if plane_right is not None and len(plane_right) != PLANE_POINTS:
        raise BadInputError(
            f"{PLANE_POINTS} --plane points but {len(plane_right)} --plane-right points",
            hint="give one --plane-right U,V for every --plane U,V, or none to find them",
        )
    if left is None:
        raise BadInputError(
            "--plane places left-half points on the plane: give them with --left U,V",
            hint="give the measured points with --left",
        )
    check_count(kind, len(left), "--left points")
    on_plane = projected_points(kind, len(left))
    n_tri = int(np.sum(~on_plane))
    if right is not None and n_tri == 0:
        raise BadInputError(
            f"--right has no effect with --plane: every {kind} point is placed on the plane "
            "along its left ray, not matched",
            hint="leave out --right",
        )
    if right is not None and len(right) != n_tri:
        raise BadInputError(
            f"{kind} with --plane triangulates its first {n_tri} points, but {len(right)} "
            "--right points were given",
            hint=f"give --right for the first {n_tri} points only, or none to find them",
        )
    if n_tri and (right is None) != (plane_right is None):
        raise BadInputError(
            "give the right pixels of both the plane points and the triangulated points "
            "(--plane-right and --right), or of neither (to find them all)",
        )
    left = np.asarray(left, dtype=np.float64).reshape(-1, 2)
    plane = np.asarray(plane, dtype=np.float64).reshape(-1, 2)
    tri_left = np.vstack([plane, left[~on_plane]])
    tri_right = None
    if plane_right is not None:
        extra = [] if right is None else list(right)
        tri_right = np.asarray(list(plane_right) + extra, dtype=np.float64).reshape(-1, 2)
    request = _checked_request(kind, tri_left, tri_right, warn_percent, plot)
    return _PlaneRequest(request, left[on_plane])


def _point_names(kind: str, n_tri: int) -> list[str]:
    """How the points of a plane measurement's search are named: the plane's, then
    the kind's."""
    return [f"plane point {i + 1}" for i in range(3)] + [f"point {i + 1}" for i in range(n_tri - 3)]


def _plane_pairs(cm, request: _PlaneRequest, image_pixels, patch: int, plot, kind: str):
    """:func:`_pixel_pairs` of the points a plane measurement triangulates; a refusal
    names them as the plane's points or the kind's."""
    try:
        return _pixel_pairs(cm, request.triangulated, image_pixels, patch, plot)
    except MatchRefusedError as exc:
        names = _point_names(kind, len(exc.matches))
        refused = [(i, m) for i, m in enumerate(exc.matches) if not m.ok]
        reasons = "; ".join(f"{names[i]}: {m.status.value}: {m.message}" for i, m in refused)
        raise MatchRefusedError(
            f"{len(refused)} of {len(exc.matches)} points not matched in the right half, "
            f"nothing measured ({reasons})",
            exc.matches,
            hint="move the point onto texture both halves see, or give its match with "
            "--plane-right U,V (--right U,V for a depth's first three points)",
            plot=exc.plot,
        ) from None


def _on_plane(model, plane_xyz: np.ndarray, pixels: np.ndarray, first: int) -> np.ndarray:
    """Where the left rays of ``pixels`` (k, 2) meet the plane through ``plane_xyz``
    (3, 3); ``first`` is the number of the first of them in the measurement."""
    from endomeasure.measure.kinds import plane_of, ray_plane

    normal, distance = plane_of(plane_xyz)
    rays = model.rays(pixels, Half.LEFT)
    for i in np.flatnonzero(rays.status != Status.OK):
        why = Status(int(rays.status[i])).name.lower().replace("_", " ")
        raise BadInputError(f"point {first + i}: its left pixel has no ray ({why})",
                            hint="pick a point inside the left half's field of view")  # fmt: skip
    return ray_plane(rays.origins, rays.directions, normal, distance, first)


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
    plane: Sequence[tuple[float, float]] | None = None,
    plane_right: Sequence[tuple[float, float]] | None = None,
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
    plane, plane_right : sequence of three (u, v), px, optional
        A measurement plane (the module docstring): its three points in the left half,
        and their right pixels (None: found automatically). The ``left`` points of a
        length, point-line, polyline or area, the 4th of a depth, are then placed where
        their left ray meets the plane; ``right`` gives only a depth's first three.

    Returns
    -------
    MeasureReport

    Raises
    ------
    MatchRefusedError
        The search refused a point (nothing is stored).
    """
    from endomeasure.io.session import open_session
    from endomeasure.measure.kinds import measure
    from endomeasure.pipeline import calibrated_model

    plane_request = None
    if plane is None and plane_right is not None:
        raise BadInputError("--plane-right needs its --plane points", hint="give --plane U,V x3")
    if plane is not None:
        plane_request = _checked_plane_request(kind, left, right, plane, plane_right,
                                               warn_percent, plot)  # fmt: skip
        request = plane_request.triangulated
    else:
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
    if plane_request is not None:
        where = (str(session), model_name, image, float(warn_percent))
        report = _plane_report(cm, where, kind, plane_request, image_pixels, patch, plot, sigma)
        return _stored(report, session, store)
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
    return _stored(report, session, store)


def _stored(report: MeasureReport, session, store: bool) -> MeasureReport:
    """``report`` stored as the session's next measurement record (when ``store``)."""
    from endomeasure.io import records
    from endomeasure.io.session import edit_session

    if store:
        with edit_session(session) as writer:
            name = records.next_measurement_name(writer.record_names(records.MEASUREMENT_RECORD))
            report = dataclasses.replace(report, record=name)
            writer.write_record(records.measurement_record(name, report))
    return report


def _plane_report(cm, where, kind: str, request: _PlaneRequest, image_pixels, patch: int,
                  plot, sigma) -> MeasureReport:  # fmt: skip
    """A ``--plane`` measurement; ``where``: (session, model name, image, warn percent)."""
    from endomeasure.measure.kinds import PLANE_POINTS, measure

    session, model_name, image, warn_percent = where
    model = cm.model
    ql, qr, matches, written = _plane_pairs(cm, request, image_pixels, patch, plot, kind)
    n_tri = ql.shape[0]
    _check_pixels(request.projected, Half.LEFT, model, "left")
    tri = _triangulated(model, model_name, ql, qr)
    first = n_tri - PLANE_POINTS + 1  # the number of the first projected point
    xyz = _on_plane(model, tri.points[:PLANE_POINTS], request.projected, first)
    points = np.vstack([tri.points[PLANE_POINTS:], xyz])
    value = measure(kind, points)
    k = xyz.shape[0]
    all_left = np.vstack([ql, request.projected])
    all_right = np.vstack([qr, np.full((k, 2), np.nan)])
    error, noise = _predicted(cm, kind, value, all_left, all_right, sigma, matches,
                              request.triangulated.query_half, projected=k)  # fmt: skip

    def point(i: int) -> MeasuredPoint:
        if i < n_tri:
            return MeasuredPoint(
                tuple(map(float, ql[i])), tuple(map(float, qr[i])),
                tuple(map(float, tri.points[i])), float(tri.gap[i]), float(tri.rms[i]),
                None if matches is None else matches[i],
            )  # fmt: skip
        j = i - n_tri
        left = tuple(map(float, request.projected[j]))
        return MeasuredPoint(left, (math.nan, math.nan), tuple(map(float, xyz[j])),
                             math.nan, math.nan, projected=True)  # fmt: skip

    measured = [point(i) for i in range(n_tri + k)]
    return MeasureReport(session, "", model_name, image, kind, request.triangulated.spec.unit,
                         measured[PLANE_POINTS:], error, warn_percent, noise, METHOD, written,
                         plane=measured[:PLANE_POINTS])  # fmt: skip


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
