"""``endomeasure measure``: measurements from correspondences, and the board test.

Two jobs (SPEC section 7, issue 7):

- :func:`measure_points` — an operator's measurement: the left and right pixels of each
  point, a kind (length, point-line, depth, area, polyline) and a calibrated model;
  triangulate (maximum likelihood), compute the value, predict its uncertainty
  (:func:`endomeasure.measure.predict.predict_measurement_error`, scaled UT, with the
  calibration covariance the session stores and the image noise estimated from the
  calibration residuals), flag it when the predicted relative error exceeds a
  threshold, and store it in the session as a ``measurement`` record;
- :func:`board_test` — the paper's Section 3 (its Fig. 4): triangulate every corner of
  every test image of a known board, measure x- and y-segments, point-to-plane
  distances and square areas against the board's true geometry, and summarise mean
  error and standard deviation per model, board, kind and distance zone; stored as one
  ``board_test`` record per model.

The accuracy index
------------------
An operator needs one number that says whether a measurement can be trusted, as
commercial videoscopes show an accuracy index. Ours has a meaning: the predicted 95 %
error bound relative to the value, ``(|bias| + 1.96 std) / |value|`` in percent, where
bias and std come from the unscented transform of image noise and calibration
uncertainty. Above ``warn_percent`` (default :data:`DEFAULT_WARN_PERCENT`) the report
carries a warning. For a depth near zero the index is large by construction: a dent of
0.05 mm measured with +-0.1 mm is not a measurement of that dent.

Operator points (one half only)
-------------------------------
``right=None`` (or ``left=None``) means "find the matches automatically" (issue 9): every
given point is searched in the other half along its epipolar curve
(:func:`endomeasure.measure.correspondence.find_matches`, patch size ``patch``). A point
the search refuses (untextured, ambiguous, not seen by the other half, low score) stops
the measurement: :class:`MatchRefusedError` (exit 1) names the point and the reason,
carries every point's :class:`~endomeasure.measure.correspondence.Match` for the report,
and nothing is stored. ``plot`` draws both halves with the points, their matches (or
refused candidates) and the searched epipolar curves, refused or not.

The uncertainty input of a matched point is not the calibration-residual sigma of a
detected corner. The clicked pixel *defines* the point (standard deviation 0); its match
is uncertain by the search's predicted precision ``precision_px`` (the standard deviation
of the relative shift of two noisy patches, from the patch's texture and the image
noise, with the search's systematic misfit added in quadrature), applied to both
coordinates of the matched pixel. ``sigma`` (``--sigma``)
overrides this with one value for every coordinate of both halves.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.conventions import Half, Status, in_half
from endomeasure.errors import BadInputError, GoalNotMetError
from endomeasure.solvers.uncertainty import checked_sigma

__all__ = [
    "DEFAULT_PATCH_PX",
    "DEFAULT_WARN_PERCENT",
    "DEFAULT_ZONE_MM",
    "BoardTestReport",
    "CalibratedModel",
    "MeasureReport",
    "MatchRefusedError",
    "MeasuredPoint",
    "board_test",
    "load_board_test",
    "image_noise",
    "load_calibrated_model",
    "measure_points",
    "parse_pixel",
]

DEFAULT_WARN_PERCENT = 5.0
"""Accuracy-index threshold (percent). The +-5 % that commercial videoscopes quote for
stereo measurements in their working range; the paper's raytrace model reaches better
than 1 % on 1 mm segments at 12-27 mm, so a warning means the measurement is far from
what the probe can do (too far, too short, at the field edge, or a poor match)."""

DEFAULT_PATCH_PX = 15
"""Correlation patch of the automatic search (px): the search's own default, about
0.8 mm at 16 mm, enough texture on the simulator's metal for 0.02-0.03 px precision."""

DEFAULT_ZONE_MM = 5.0
"""Width of the distance zones of the board test (mm): the paper's Fig. 4 uses zones of
a few mm over 12-40 mm; 5 mm gives 4-6 zones per board with >= 4 images each (1 mm
steps), enough for a per-zone standard deviation."""

Z95 = 1.959963984540054
"""Two-sided 95 % quantile of the standard normal distribution."""

MEASUREMENT_RECORD = "measurement"
BOARD_TEST_RECORD = "board_test"
_NAME_RE = re.compile(r"^m(\d+)$")


# ----- inputs ---------------------------------------------------------------------------------


def parse_pixel(text: str) -> tuple[float, float]:
    """``"U,V"`` -> ``(u, v)`` in px; anything else is a :class:`BadInputError`."""
    parts = str(text).replace(" ", "").split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        u, v = float(parts[0]), float(parts[1])
    except ValueError:
        raise BadInputError(
            f"cannot read the pixel {text!r}", hint="give pixels as U,V, e.g. --left 120.5,88"
        ) from None
    if not (math.isfinite(u) and math.isfinite(v)):
        raise BadInputError(f"the pixel {text!r} is not finite")
    return u, v


def parse_sigma(text: str | None) -> float | tuple[float, float] | None:
    """``"PX"`` (every coordinate) or ``"U,V"`` (u and v separately) -> the image noise in
    px; ``None`` stays ``None``; anything else is a :class:`BadInputError`."""
    if text is None:
        return None
    parts = str(text).replace(" ", "").split(",")
    try:
        if len(parts) not in (1, 2):
            raise ValueError
        values = [float(p) for p in parts]
    except ValueError:
        raise BadInputError(
            f"cannot read the image noise {text!r}",
            hint="give --sigma PX for every coordinate or --sigma U,V, e.g. --sigma 0.013,0.016",
        ) from None
    return checked_sigma(values[0] if len(values) == 1 else values)


def image_noise(given, cm, what: str) -> tuple[float | tuple[float, float], str]:
    """The image noise of a prediction and where it comes from: ``given`` (one number, or
    u and v, px) or else the calibrated model ``cm``'s residual sigma; ``what`` names
    the model in the error when it has none."""
    if given is not None:
        return checked_sigma(given), "given"
    if cm is None or cm.sigma_px is None:
        raise BadInputError(
            f"{what} carries no calibration residuals to estimate the image noise",
            hint="give --sigma PX (or U,V)",
        )
    return cm.sigma_px, "calibration residuals"


@dataclasses.dataclass(frozen=True)
class CalibratedModel:
    """A model stored by ``calibrate`` with what the uncertainty needs.

    Attributes
    ----------
    name : str
    model : CameraModel
    param_cov : ndarray, shape (F, F) or None
        Covariance of the free parameters in the model's ``free_mask`` order.
    sigma_px : float or None
        Image noise estimated from the calibration residuals (``sqrt(SSR / dof)``
        per coordinate), px.
    """

    name: str
    model: Any
    param_cov: np.ndarray | None
    sigma_px: float | None


def load_calibrated_model(reader, name: str, session: str | Path) -> CalibratedModel:
    """The model ``name`` of an open session, with covariance and residual sigma.

    A model the session does not hold is a :class:`BadInputError` naming those it holds.
    """
    from endomeasure.pipeline.calibrate import model_from_record

    names = reader.model_names()
    if name not in names:
        held = ", ".join(names) if names else "none"
        raise BadInputError(
            f"the session has no calibrated {name!r} model (it holds: {held})",
            path=str(session),
            hint=f"run `endomeasure calibrate {session} --model {name}` first",
        )
    record = reader.model(name)
    model = model_from_record(record)
    cov = None
    if "covariance" in record.arrays and "free_names" in record.arrays:
        stored = [str(n) for n in record.arrays["free_names"]]
        free = [model.PARAM_NAMES[i] for i in np.flatnonzero(model.free_mask)]
        c = np.asarray(record.arrays["covariance"], dtype=np.float64)
        if sorted(stored) != sorted(free) or c.shape != (len(stored), len(stored)):
            raise BadInputError(
                f"the stored covariance of model {name!r} does not match its free parameters",
                path=str(session),
                hint=f"re-run `endomeasure calibrate {session} --model {name}`",
            )
        order = [stored.index(n) for n in free]
        cov = c[np.ix_(order, order)]
    variance = record.attrs.get("residual_variance")
    sigma = (
        float(np.sqrt(variance))
        if variance is not None and np.isfinite(variance) and variance > 0
        else None
    )
    return CalibratedModel(name, model, cov, sigma)


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


def _match_other_half(model, image: np.ndarray, query: np.ndarray, half: Half, patch: int) -> list:
    """Matches in the other half of operator points given in ``half`` (issue 9)."""
    from endomeasure.measure.correspondence import find_matches

    return find_matches(model, image, query, half, patch=patch)


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
    """What ``measure`` found for one measurement (plain data)."""

    session: str
    record: str
    model: str
    image: str
    kind: str
    unit: str
    points: list[MeasuredPoint]
    value: float
    bias: float
    std: float
    std_image: float
    std_calibration: float
    ci95: float
    relative_percent: float
    warn_percent: float
    sigma_px: float | tuple[float, float]
    sigma_source: str
    method: str
    plot: str | None = None

    @property
    def matched(self) -> bool:
        """True when the other half's pixels were found by the automatic search."""
        return any(p.match is not None for p in self.points)

    @property
    def warning(self) -> bool:
        """True when the predicted relative error exceeds the threshold (or is undefined)."""
        return not (self.relative_percent <= self.warn_percent)

    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["points"] = [p.to_dict() for p in self.points]
        d["warning"] = self.warning
        d["matched"] = self.matched
        return d


def _next_name(names: Sequence[str]) -> str:
    numbers = [int(m.group(1)) for n in names if (m := _NAME_RE.match(n))]
    return f"m{max(numbers, default=0) + 1:03d}"


def accuracy_index(value: float, bias: float, std: float) -> float:
    """The predicted 95 % error bound relative to the value, percent (module docstring)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(100.0 * (abs(bias) + Z95 * std) / abs(value)) if value != 0 else math.inf


def measure_points(
    session: str | Path,
    model_name: str,
    image: str,
    left: Sequence[tuple[float, float]] | None,
    right: Sequence[tuple[float, float]] | None,
    kind: str,
    *,
    warn_percent: float = DEFAULT_WARN_PERCENT,
    sigma: float | tuple[float, float] | None = None,
    store: bool = True,
    patch: int = DEFAULT_PATCH_PX,
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
    from endomeasure.io.session import Record, edit_session, open_session
    from endomeasure.measure.kinds import kind_spec, validate
    from endomeasure.measure.predict import predict_measurement_error
    from endomeasure.solvers.triangulate import triangulate

    spec = kind_spec(kind)
    if not (math.isfinite(warn_percent) and warn_percent > 0):
        raise BadInputError(
            f"the warning threshold must be a positive percentage, not {warn_percent}"
        )
    if left is None and right is None:
        raise BadInputError("a measurement needs its points: --left U,V and/or --right U,V")
    search = left is None or right is None
    query_half = Half.RIGHT if left is None else Half.LEFT  # with both given: the left
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
    with open_session(session) as reader:
        reader.image_info(image)  # an unknown image is a BadInputError listing the images
        cm = load_calibrated_model(reader, model_name, session)
        pixels_of_image = reader.image(image) if search else None
    model = cm.model
    n = given[query_half].shape[0]
    if n < spec.min_points or (spec.max_points is not None and n > spec.max_points):
        need = (
            f"exactly {spec.min_points}"
            if spec.max_points == spec.min_points
            else f"at least {spec.min_points}"
        )
        raise BadInputError(
            f"{kind} needs {need} points, got {n}",
            hint=f"give {need} --left/--right pairs ({spec.description})",
        )
    _check_pixels(given[query_half], query_half, model, query_half.label)
    matches = None
    written = None
    if search:
        matches = _match_other_half(model, pixels_of_image, given[query_half], query_half, patch)
        if plot is not None:
            from endomeasure.measure.plots import plot_matches

            written = str(plot_matches(pixels_of_image, matches, plot, model.config.split))
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

    tri = triangulate(model, ql, qr, "ml")
    for i in np.flatnonzero(tri.status != Status.OK):
        raise BadInputError(
            f"point {i + 1} cannot be triangulated with the {model_name} model "
            f"({Status(int(tri.status[i])).name.lower().replace('_', ' ')})",
            hint="check that the left and right pixels show the same point",
        )
    points = validate(kind, tri.points)
    value = float(spec.function(points))

    pixel_std = None
    if sigma is None and search:
        # the clicked pixel defines the point; its match carries the search's precision
        pixel_std = np.zeros((n, 2))
        pixel_std[:, 1 if query_half is Half.LEFT else 0] = [m.precision_px for m in matches]
        sigma_px = float(pixel_std.max())
        source = f"match precision, {query_half.label} pixels exact"
    else:
        sigma_px, source = image_noise(sigma, cm, f"model {model_name!r}")
    if pixel_std is None:
        pred = predict_measurement_error(
            model, kind, ql, qr, sigma=sigma_px, param_cov=cm.param_cov, method="ut"
        )
    else:
        pred = predict_measurement_error(
            model, kind, ql, qr, pixel_std=pixel_std, param_cov=cm.param_cov
        )
    bias, std = float(pred.bias[0]), float(pred.std[0])
    std_image = float(pred.parts["image"][1][0]) if "image" in pred.parts else math.nan
    std_cal = float(pred.parts["calibration"][1][0]) if "calibration" in pred.parts else math.nan
    relative = accuracy_index(value, bias, std)

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
    name = ""
    if store:
        with edit_session(session) as writer:
            name = _next_name(writer.record_names(MEASUREMENT_RECORD))
            writer.write_record(
                Record(
                    MEASUREMENT_RECORD,
                    name,
                    attrs={
                        "model": model_name,
                        "image": image,
                        "measurement_kind": kind,
                        "value": value,
                        "bias": bias,
                        "std": std,
                        "std_image": std_image,
                        "std_calibration": std_cal,
                        "ci95": Z95 * std,
                        "relative_percent": relative,
                        "warn_percent": float(warn_percent),
                        "warning": not (relative <= warn_percent),
                        "sigma_px": sigma_px,
                        "sigma_source": source,
                        "method": "ut",
                        "created": datetime.datetime.now(datetime.UTC).isoformat(
                            timespec="seconds"
                        ),
                    },
                    arrays={
                        "pixels_left": ql,
                        "pixels_right": qr,
                        "points": tri.points,
                        "ray_gap": tri.gap,
                        "reprojection_rms": tri.rms,
                        **_match_arrays(matches, pixel_std),
                    },
                    units={
                        "value": spec.unit,
                        "bias": spec.unit,
                        "std": spec.unit,
                        "std_image": spec.unit,
                        "std_calibration": spec.unit,
                        "ci95": spec.unit,
                        "relative_percent": "%",
                        "warn_percent": "%",
                        "sigma_px": "px",
                        "pixels_left": "px",
                        "pixels_right": "px",
                        "points": "mm",
                        "ray_gap": "mm",
                        "reprojection_rms": "px",
                        **({} if matches is None else {"pixel_std": "px"}),
                    },
                )
            )
    return MeasureReport(
        session=str(session),
        record=name,
        model=model_name,
        image=image,
        kind=kind,
        unit=spec.unit,
        points=measured,
        value=value,
        bias=bias,
        std=std,
        std_image=std_image,
        std_calibration=std_cal,
        ci95=Z95 * std,
        relative_percent=relative,
        warn_percent=float(warn_percent),
        sigma_px=sigma_px,
        sigma_source=source,
        method="ut",
        plot=written,
    )


def _match_arrays(matches, pixel_std) -> dict[str, np.ndarray]:
    """What the stored record keeps of an automatic search (nothing without one)."""
    if matches is None:
        return {}
    out = {
        "match_query_half": np.array([m.half.label for m in matches], dtype=object),
        "match_score": np.array([m.score for m in matches]),
        "match_precision": np.array([m.precision_px for m in matches]),
    }
    if pixel_std is not None:
        out["pixel_std"] = pixel_std
    return out


# ----- the board test ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BoardSet:
    """The test images of one board: geometry and the detected corners in both halves."""

    board: str
    cols: int
    rows: int
    square_mm: float
    images: list[str]
    ids: list[np.ndarray]
    left: list[np.ndarray]
    right: list[np.ndarray]


def _test_board_sets(reader, session) -> list[BoardSet]:
    """Every test image with a known board detected in both halves (common ids)."""
    test_images = set(reader.image_names("test"))
    if not test_images:
        raise BadInputError(
            "the session holds no test images",
            path=str(session),
            hint="run `endomeasure detect SESSION IMAGES --board SPEC --set test` first",
        )
    sets = []
    for name, board in reader.boards().items():
        a = board.attrs
        if not all(k in a for k in ("cols", "rows", "square_mm")):
            continue
        by_image: dict[str, dict[Half, Any]] = {}
        for det in reader.detections(board=name):
            if det.image in test_images and det.ok:
                by_image.setdefault(det.image, {})[Half.parse(det.half)] = det
        bs = BoardSet(name, int(a["cols"]), int(a["rows"]), float(a["square_mm"]), [], [], [], [])
        for image in sorted(by_image):
            halves = by_image[image]
            if Half.LEFT not in halves or Half.RIGHT not in halves:
                continue
            dl, dr = halves[Half.LEFT], halves[Half.RIGHT]
            ids, il, ir = np.intersect1d(dl.ids, dr.ids, return_indices=True)
            if ids.size == 0:
                continue
            bs.images.append(image)
            bs.ids.append(ids.astype(np.int64))
            bs.left.append(np.asarray(dl.pixels, dtype=np.float64)[il])
            bs.right.append(np.asarray(dr.pixels, dtype=np.float64)[ir])
        if bs.images:
            sets.append(bs)
    if not sets:
        raise BadInputError(
            "no test image has a known board detected in both halves",
            path=str(session),
            hint="run `endomeasure detect SESSION IMAGES --board SPEC --set test` first",
        )
    return sets


@dataclasses.dataclass
class ModelBoardTest:
    """One model's board test: corners, measurement table and the per-zone summary."""

    model: str
    board: list[str]  # per image (index into images)
    images: list[str]
    square_mm: list[float]  # per image
    corner_image: np.ndarray  # (C,) int
    corner_id: np.ndarray  # (C,) int
    corner_left: np.ndarray  # (C, 2) px
    corner_right: np.ndarray  # (C, 2) px
    corner_xyz: np.ndarray  # (C, 3) mm
    corner_gap: np.ndarray  # (C,) mm
    corner_rms: np.ndarray  # (C,) px
    corner_status: np.ndarray  # (C,) uint8
    table: Any  # BoardTestTable, image = index into images
    summary: Any  # ZoneSummary-like, with board per row
    summary_board: np.ndarray  # (K,) str

    def image_pixels(self, index: int):
        """(ids, left, right, xyz) of one image."""
        sel = self.corner_image == index
        return (
            self.corner_id[sel],
            self.corner_left[sel],
            self.corner_right[sel],
            self.corner_xyz[sel],
        )


@dataclasses.dataclass(frozen=True)
class BoardTestReport:
    session: str
    zone_mm: float
    models: dict[str, ModelBoardTest]
    plot: str | None

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


def _zone_summary_by_board(table, model: str, board_of_row: np.ndarray, zone_mm: float):
    from endomeasure.measure.board_test import ZoneSummary, zone_summary

    parts, boards = [], []
    for board in dict.fromkeys(board_of_row.tolist()):
        s = zone_summary({model: table.select(board_of_row == board)}, zone_mm)
        parts.append(s)
        boards.append(np.full(s.model.shape[0], board).astype(str))
    if not parts:
        return zone_summary({model: table}, zone_mm), np.zeros(0, dtype=str)
    return ZoneSummary(*(np.concatenate(c) for c in zip(*parts, strict=True))), np.concatenate(
        boards
    )


def run_board_test(model_name: str, model, sets: list[BoardSet], zone_mm: float) -> ModelBoardTest:
    """Triangulate every corner of every test image with one model and measure the board."""
    from endomeasure.measure.board_test import BoardImage, BoardTestTable, board_test_table
    from endomeasure.solvers.triangulate import triangulate

    images, boards, squares = [], [], []
    c_img, c_id, c_l, c_r, c_xyz, c_gap, c_rms, c_st = ([] for _ in range(8))
    tables = []
    for bs in sets:
        # one triangulation call for all images of the board
        ql = np.concatenate(bs.left)
        qr = np.concatenate(bs.right)
        tri = triangulate(model, ql, qr, "ml")
        bounds = np.cumsum([0] + [ids.size for ids in bs.ids])
        board_images = []
        for k, image in enumerate(bs.images):
            sl = slice(bounds[k], bounds[k + 1])
            index = len(images)
            images.append(image)
            boards.append(bs.board)
            squares.append(bs.square_mm)
            c_img.append(np.full(bs.ids[k].size, index))
            c_id.append(bs.ids[k])
            c_l.append(bs.left[k])
            c_r.append(bs.right[k])
            c_xyz.append(tri.points[sl])
            c_gap.append(tri.gap[sl])
            c_rms.append(tri.rms[sl])
            c_st.append(tri.status[sl])
            board_images.append(BoardImage(bs.ids[k], tri.points[sl], bs.left[k], bs.right[k]))
        t = board_test_table(bs.cols, bs.rows, bs.square_mm, board_images)
        offset = len(images) - len(bs.images)
        tables.append(t._replace(image=t.image + offset))
    table = BoardTestTable(*(np.concatenate(c) for c in zip(*tables, strict=True)))
    board_of_row = (
        np.asarray(boards, dtype=str)[table.image] if table.image.size else np.zeros(0, str)
    )
    summary, summary_board = _zone_summary_by_board(table, model_name, board_of_row, zone_mm)
    return ModelBoardTest(
        model_name,
        boards,
        images,
        squares,
        np.concatenate(c_img),
        np.concatenate(c_id),
        np.concatenate(c_l),
        np.concatenate(c_r),
        np.concatenate(c_xyz),
        np.concatenate(c_gap),
        np.concatenate(c_rms),
        np.concatenate(c_st).astype(np.uint8),
        table,
        summary,
        summary_board,
    )


def _models_to_run(reader, model: str, session) -> list[str]:
    held = reader.model_names()
    if model == "all":
        names = [n for n in ("pinhole", "raytrace") if n in held] + [
            n for n in held if n not in ("pinhole", "raytrace")
        ]
        if not names:
            raise BadInputError(
                "the session holds no calibrated model",
                path=str(session),
                hint=f"run `endomeasure calibrate {session}` first",
            )
        return names
    return [model]


def _board_test_record(bt: ModelBoardTest, zone_mm: float):
    from endomeasure.io.session import Record

    t, s = bt.table, bt.summary
    return Record(
        BOARD_TEST_RECORD,
        bt.model,
        attrs={"model": bt.model, "zone_mm": float(zone_mm), "n_images": len(bt.images)},
        arrays={
            "images": np.array(bt.images, dtype=object),
            "image_board": np.array(bt.board, dtype=object),
            "image_square_mm": np.array(bt.square_mm),
            "corner_image": bt.corner_image.astype(np.int32),
            "corner_id": bt.corner_id.astype(np.int32),
            "corner_left": bt.corner_left,
            "corner_right": bt.corner_right,
            "corner_xyz": bt.corner_xyz,
            "corner_gap": bt.corner_gap,
            "corner_rms": bt.corner_rms,
            "corner_status": bt.corner_status,
            "row_image": t.image.astype(np.int32),
            "row_kind": np.array(t.kind, dtype=object),
            "row_corners": t.corners.astype(np.int32),
            "row_true": t.true,
            "row_measured": t.measured,
            "row_error": t.error,
            "row_z_mean": t.z_mean,
            "row_pixel_mean": t.pixel_mean,
            "zone_board": np.array(bt.summary_board, dtype=object),
            "zone_kind": np.array(s.kind, dtype=object),
            "zone_start": s.zone_start,
            "zone_end": s.zone_end,
            "zone_n": s.n,
            "zone_mean_error": s.mean_error,
            "zone_std_error": s.std_error,
            "zone_true": s.true,
        },
        units={
            "zone_mm": "mm",
            "image_square_mm": "mm",
            "corner_left": "px",
            "corner_right": "px",
            "corner_xyz": "mm",
            "corner_gap": "mm",
            "corner_rms": "px",
            "row_true": "mm or mm^2 (area)",
            "row_measured": "mm or mm^2 (area)",
            "row_error": "mm or mm^2 (area)",
            "row_z_mean": "mm",
            "row_pixel_mean": "px",
            "zone_start": "mm",
            "zone_end": "mm",
            "zone_mean_error": "mm or mm^2 (area)",
            "zone_std_error": "mm or mm^2 (area)",
            "zone_true": "mm or mm^2 (area)",
        },
    )


def board_test(
    session: str | Path,
    model: str = "all",
    zone_mm: float = DEFAULT_ZONE_MM,
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

    Returns
    -------
    BoardTestReport
    """
    from endomeasure.io.session import edit_session, open_session

    if not (math.isfinite(zone_mm) and zone_mm > 0):
        raise BadInputError(f"the zone width must be a positive number of mm, not {zone_mm}")
    with open_session(session) as reader:
        names = _models_to_run(reader, model, session)
        models = {n: load_calibrated_model(reader, n, session).model for n in names}
        sets = _test_board_sets(reader, session)
    results = {}
    for i, (name, m) in enumerate(models.items()):
        results[name] = run_board_test(name, m, sets, zone_mm)
        if on_progress is not None:
            on_progress(i + 1, len(models))
    if store:
        with edit_session(session) as writer:
            for bt in results.values():
                writer.write_record(_board_test_record(bt, zone_mm))
    written = None
    if plot is not None:
        from endomeasure.measure.plots import plot_board_test

        written = str(plot_board_test(results, zone_mm, plot))
    return BoardTestReport(str(session), float(zone_mm), results, written)


def load_board_test(reader, model: str) -> ModelBoardTest:
    """A stored board test (written by :func:`board_test`) read back."""
    from endomeasure.measure.board_test import BoardTestTable, ZoneSummary

    rec = reader.record(BOARD_TEST_RECORD, model)
    a = rec.arrays
    table = BoardTestTable(
        a["row_image"].astype(np.int64),
        np.asarray(a["row_kind"]).astype(str),
        a["row_corners"].astype(np.int64),
        a["row_true"],
        a["row_measured"],
        a["row_error"],
        a["row_z_mean"],
        a["row_pixel_mean"],
    )
    k = np.asarray(a["zone_kind"]).astype(str)
    summary = ZoneSummary(
        np.full(k.shape[0], model).astype(str),
        k,
        a["zone_start"],
        a["zone_end"],
        a["zone_n"].astype(np.int64),
        a["zone_mean_error"],
        a["zone_std_error"],
        a["zone_true"],
    )
    return ModelBoardTest(
        model,
        [str(b) for b in a["image_board"]],
        [str(i) for i in a["images"]],
        [float(s) for s in a["image_square_mm"]],
        a["corner_image"].astype(np.int64),
        a["corner_id"].astype(np.int64),
        a["corner_left"],
        a["corner_right"],
        a["corner_xyz"],
        a["corner_gap"],
        a["corner_rms"],
        a["corner_status"].astype(np.uint8),
        table,
        summary,
        np.asarray(a["zone_board"]).astype(str),
    )
