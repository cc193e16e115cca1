"""``endomeasure calibrate``: fit camera models to a session's detections and store them.

Steps: read the session (image size, split, boards, the detections of the calibration
images); calibrate each requested model (:func:`endomeasure.solvers.calibrate.calibrate`;
with ``all``, every registered model, each seed model before the models seeded from it,
which start from its result); store every
model that succeeded in one atomic session edit; draw residual plots if asked; report.
A model whose calibration is refused is not stored, and the report carries the refusal
(the command then exits 1). Every stored calibration carries its verdict
(:mod:`endomeasure.solvers.verdict`); one that failed is stored for diagnosis (the board
test shows its errors) but refused by every command that measures with it, and makes
the command exit 1 unless ``all`` was asked for and another model passed.

What is stored per model (group ``models/<name>``) is defined in
:func:`endomeasure.io.records.calibration_record` and ``docs/session-format.md``: the
parameters, the covariance a later measurement's uncertainty needs, and everything
needed to recompute it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure import defaults
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError, CalibrationError

__all__ = [
    "ALL_MODELS",
    "CalibrateReport",
    "ModelSummary",
    "calibrate_session",
    "calibration_order",
    "load_calibration_inputs",
    "export_session_model",
]

ALL_MODELS = defaults.ALL_MODELS


@dataclasses.dataclass(frozen=True)
class ModelSummary:
    """What the report says about one calibrated model (plain data)."""

    name: str
    rms: float
    rms_half: tuple[float, float]
    n_images: int
    n_corners: int
    n_outliers: int
    worst_images: list[tuple[str, float]]
    params: dict[str, float]
    std: dict[str, float]
    correlations: list[tuple[str, str, float]]
    residual_sigma: float
    status: int
    nfev: int
    start: str
    verdict: str = "unjudged"
    reasons: list[str] = dataclasses.field(default_factory=list)
    noise_floor: float = float("nan")
    formal_floor: float = float("nan")
    scatter_floor: float = float("nan")
    rms_ratio: float = float("nan")
    extensions: list[str] = dataclasses.field(default_factory=list)
    selection: list[str] = dataclasses.field(default_factory=list)
    uncertain_std: dict[str, float] = dataclasses.field(default_factory=dict)
    plots: list[str] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["rms_px"] = d.pop("rms")
        d["rms_half_px"] = {"left": self.rms_half[0], "right": self.rms_half[1]}
        del d["rms_half"]
        d["worst_images"] = [{"image": n, "rms_px": r} for n, r in self.worst_images]
        d["correlations"] = [{"a": a, "b": b, "r": r} for a, b, r in self.correlations]
        d["residual_sigma_px"] = d.pop("residual_sigma")
        for key in ("noise_floor", "formal_floor", "scatter_floor"):
            d[f"{key}_px"] = d.pop(key)
        return d


@dataclasses.dataclass(frozen=True)
class CalibrateReport:
    session: str
    image_size: tuple[int, int]
    split: int
    n_images: int
    models: dict[str, ModelSummary]
    refused: dict[str, str]
    all_models: bool = False

    @property
    def failed(self) -> dict[str, str]:
        """Models stored with the verdict ``failed``, with the first reason."""
        return {n: (m.reasons or ["failed"])[0] for n, m in self.models.items()
                if m.verdict == "failed"}  # fmt: skip

    @property
    def ok(self) -> bool:
        """Whether the command succeeded: nothing refused, and no failed calibration except,
        with ``all``, models that another usable model makes up for."""
        if self.refused:
            return False
        usable = [m for m in self.models.values() if m.verdict != "failed"]
        return bool(usable) and (self.all_models or not self.failed)

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "image_size": list(self.image_size),
            "split": self.split,
            "n_images": self.n_images,
            "models": {k: v.to_dict() for k, v in self.models.items()},
            "refused": dict(self.refused),
            "failed": self.failed,
            "ok": self.ok,
        }


# ----- reading ------------------------------------------------------------------------------


def load_calibration_inputs(session: str | Path):
    """Detections of the session's calibration images, as the solver takes them.

    Returns
    -------
    views : list of ViewDetections
    boards : dict of str to ndarray, shape (N, 3), mm
    image_size : (int, int)
    split : int
    """
    from endomeasure.features.boards import parse_board_spec
    from endomeasure.io.session import open_session
    from endomeasure.solvers.calibrate import ViewDetections

    with open_session(session) as s:
        meta = s.metadata()
        if meta.image_size is None or meta.split is None:
            raise BadInputError(
                "the session has no image size or split yet",
                path=str(session),
                hint="run `endomeasure detect` first",
            )
        calib_images = set(s.image_names("calib"))
        other_images = set(s.image_names()) - calib_images
        boards = {name: parse_board_spec(b.spec).object_points for name, b in s.boards().items()}
        detections = s.detections()
    # Detections of test and scene images never enter a calibration (the board test would
    # then judge the model on its own data); those of images not embedded (a session of
    # detections only) have no set and are taken.
    usable = [det for det in detections if det.image not in other_images]
    if detections and not usable:
        what = (
            f"none of the session's {len(calib_images)} calibration images has detections"
            if calib_images
            else "the session has no calibration images"
        )
        raise BadInputError(
            f"{what}: its detections are all of test or scene images",
            path=str(session),
            hint="add calibration images with `endomeasure detect SESSION IMAGES --board "
            "SPEC --set calib`",
        )
    by_view: dict[tuple[str, str], dict[Half, Any]] = {}
    for det in usable:
        by_view.setdefault((det.image, det.board), {})[Half.parse(det.half)] = det
    boards_per_image: dict[str, int] = {}
    for image, _ in by_view:
        boards_per_image[image] = boards_per_image.get(image, 0) + 1
    views = []
    for (image, board), halves in sorted(by_view.items()):
        ids, pixels, covariance = [], [], []
        for h in Half:
            det = halves.get(h)
            if det is None or not det.ok:
                ids.append(np.zeros(0, dtype=np.int64))
                pixels.append(np.zeros((0, 2)))
                covariance.append(None)
            else:
                ids.append(np.asarray(det.ids, dtype=np.int64))
                pixels.append(np.asarray(det.pixels, dtype=np.float64))
                covariance.append(det.covariance)
        name = image if boards_per_image[image] == 1 else f"{image}@{board}"
        views.append(ViewDetections(name, board, tuple(ids), tuple(pixels), tuple(covariance)))
    if not views:
        raise CalibrationError(
            "the session holds no detections of calibration images",
            path=str(session),
            hint="run `endomeasure detect SESSION IMAGES --board SPEC` first",
        )
    return views, boards, meta.image_size, meta.split


# ----- the command ------------------------------------------------------------------------------


def _summary(result, plots: list[str]) -> ModelSummary:
    return ModelSummary(
        name=result.model_name,
        rms=result.rms,
        rms_half=(float(result.rms_half[0]), float(result.rms_half[1])),
        n_images=len(result.image_names),
        n_corners=result.n_inliers,
        n_outliers=result.outlier_count,
        worst_images=result.worst_images(3),
        params=result.model.named_params(),
        std=result.named_std(),
        correlations=result.strongest_correlations(5),
        residual_sigma=float(np.sqrt(result.residual_variance)),
        status=result.status,
        nfev=result.nfev,
        start=result.start,
        verdict=result.verdict.level,
        reasons=list(result.verdict.reasons),
        noise_floor=result.verdict.floor_px,
        formal_floor=result.verdict.formal_px,
        scatter_floor=result.verdict.scatter_px,
        rms_ratio=result.verdict.rms_ratio,
        extensions=list(result.extensions),
        selection=list(result.selection),
        uncertain_std=_uncertain_std(result),
        plots=plots,
    )


def _uncertain_std(result) -> dict[str, float]:
    """The sigma of each extension the fit held but cannot rule out, by name."""
    model = result.uncertainty_model
    free = [model.PARAM_NAMES[i] for i in np.flatnonzero(model.free_mask)]
    std = np.sqrt(np.diag(result.measurement_covariance))
    return {n: float(std[free.index(n)]) for n in result.uncertain}


def _read_seed(path: str | Path | None):
    if path is None:
        return None
    from endomeasure.io.export import read_model_document

    return read_model_document(path, "seed model")


def calibration_order(model: str) -> list[str]:
    """The registered models ``model`` asks for (one, or all for :data:`ALL_MODELS`), in
    registry order, which puts a model's seed model (``SEEDED_FROM``) before it
    (:func:`~endomeasure.models.register_model` enforces it), so that its result can
    seed the models after it."""
    from endomeasure.models import MODELS

    if model == ALL_MODELS:
        return list(MODELS)
    if model not in MODELS:
        choices = ", ".join((*MODELS, ALL_MODELS))
        raise BadInputError(f"unknown model {model!r}; choose one of {choices}")
    return [model]


def calibrate_session(
    session: str | Path,
    model: str = ALL_MODELS,
    values: Mapping[str, float] | None = None,
    free: Sequence[str] = (),
    seed: str | Path | None = None,
    plot_dir: str | Path | None = None,
    hold: Sequence[str] = (),
) -> CalibrateReport:
    """Calibrate the requested model(s) from a session's detections and store them.

    Parameters
    ----------
    session : path
    model : str
        A registered model name or ``'all'`` (:func:`calibration_order`).
    values : mapping of str to float, optional
        Parameter values to start from (and keep where fixed), e.g. a glass index; each
        model takes those it has.
    free : sequence of str
        Parameters to estimate that the models hold fixed by default.
    hold : sequence of str
        Parameters to hold at their values that the models estimate by default.
    seed : path, optional
        JSON file of a model with nominal design values: seeds the model of its kind.
    plot_dir : path, optional
        Where to write residual plots (PNG).

    Returns
    -------
    CalibrateReport
        ``refused`` names the models whose calibration was refused (not stored).
    """
    from endomeasure.io.outputs import checked_output_dir, checked_session_target
    from endomeasure.io.records import calibration_record
    from endomeasure.io.session import edit_session
    from endomeasure.measure.plots import plot_residuals
    from endomeasure.solvers.calibrate import calibrate

    checked_session_target(session, create=False)  # the models are stored in it at the end
    if plot_dir is not None:
        plot_dir = checked_output_dir(plot_dir, "plot folder")
    names = calibration_order(model)
    options = _options_per_model(names, dict(values or {}), frozenset(free), frozenset(hold),
                                 _read_seed(seed))  # fmt: skip
    views, boards, image_size, split = load_calibration_inputs(session)
    results: dict[str, Any] = {}
    refused: dict[str, str] = {}
    for name in names:
        try:
            # the earlier results: the solver starts from those in the model's seeding chain
            results[name] = calibrate(name, views, boards, image_size, split, options[name],
                                      start=tuple(results.values()))  # fmt: skip
        except CalibrationError as exc:
            refused[name] = exc.one_line()
    if results:
        with edit_session(session) as writer:
            for name, res in results.items():
                writer.write_model(calibration_record(res, name))
    summaries = {}
    for name, res in results.items():
        plots = plot_residuals(res, Path(plot_dir)) if plot_dir is not None else []
        summaries[name] = _summary(res, plots)
    return CalibrateReport(str(session), tuple(image_size), int(split), len(views),
                           summaries, refused, model == ALL_MODELS)  # fmt: skip


def _options_per_model(names, values: dict, free: frozenset, hold: frozenset, seed) -> dict:
    """Each model's CalibrationOptions: the values and freed parameters it has, and the
    seed if it is of its kind; BadInputError for what applies to none of them."""
    from endomeasure.models import MODELS
    from endomeasure.solvers.calibrate import CalibrationOptions

    known = {p for name in names for p in MODELS[name].PARAM_NAMES}
    unused = sorted((set(values) | free | hold) - known)
    if unused:
        raise BadInputError(
            f"no model to calibrate ({', '.join(names)}) has the parameter(s) {unused}",
            hint="choose the model with --model",
        )
    if seed is not None and seed.get("model") not in names:
        raise BadInputError(
            f"the seed describes a {seed.get('model')!r} model, which is not being calibrated",
            hint=f"calibrate it with --model {seed.get('model')} or --model all",
        )
    options = {}
    for name in names:
        params = set(MODELS[name].PARAM_NAMES)
        options[name] = CalibrationOptions(
            values={k: v for k, v in values.items() if k in params},
            free=free & params,
            hold=hold & params,
            seed=seed if seed is not None and seed.get("model") == name else None,
        )
    return options


def export_session_model(
    session: str | Path, name: str, fmt: str, out: str | Path
) -> tuple[Path, ...]:
    """``endomeasure export``: write a stored model (and its calibration figures) to the
    file or files of format ``fmt`` (:func:`~endomeasure.io.export.export_files`)."""
    from endomeasure.io.export import export_files, export_model
    from endomeasure.io.outputs import checked_outputs
    from endomeasure.io.records import calibration_extras, check_usable, model_from_record
    from endomeasure.io.session import open_session

    names = export_files(fmt, out)
    whats = (
        ["exported model"]
        if len(names) == 1
        else [f"exported model of the {half} half" for half in ("left", "right")]
    )
    files = checked_outputs(
        [(path, what, None) for path, what in zip(names, whats, strict=True)], inputs=[session]
    )
    with open_session(session) as s:
        record = s.model(name)
    check_usable(record, session)
    return export_model(
        model_from_record(record), fmt, out, calibration_extras(record), files=tuple(files)
    )
