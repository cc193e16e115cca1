"""``endomeasure report``: one self-contained HTML file answering "is this calibration good,
where can I trust it, what was measured with it".

The session is only read. Each section is built from what the session holds and says
what is missing, with the command that adds it, instead of failing: a session with only
detections gives a report of its images and boards. Per calibrated model: the verdict
and its reasons, the field the calibration corners covered, residual vectors, residual
bias per region tested against the noise floor, the residual histogram against the
expected Gaussian, outliers, per-image RMS (worst first), parameters with +- and strong
correlations, the stereo baseline with +-, and a trust map (the predicted 95 % error of
a 1 mm length over the left half at a few working distances, in bands the user sets).
Then the board test (paper Fig. 4), predicted against actual errors (Fig. 5) and the
stored measurements with their +-.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure import __version__, defaults
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError, EndomeasureError

__all__ = ["ReportSummary", "write_report"]

TRUST_DEPTHS = 3
"""Working distances of the trust map when none are given: the nearest, middle and
farthest of the depths where the calibration saw the board."""
TRUST_GRID = (16, 12)
"""Grid points of the trust map over the left half (per row, per column)."""
WORST_OBSERVATIONS = 10
"""Corners listed in the table of the largest residuals."""
STRONG_CORRELATION = 0.9
"""Parameter pairs correlated beyond this are listed: the images cannot tell them apart."""


@dataclasses.dataclass(frozen=True)
class ReportSummary:
    """What ``report`` wrote: the file, and per section ``present`` or why it is missing."""

    session: str
    out: str
    sections: dict[str, str]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _b64(png: bytes) -> str:
    return base64.b64encode(png).decode("ascii")


def _finite(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _calibration_section(record, cm, image_size, split: int, session: str) -> dict[str, Any]:
    """Verdict, coverage, residual figures, per-image RMS, parameters of one model."""
    from endomeasure.io.records import stored_verdict
    from endomeasure.measure import diagnostics as dg
    from endomeasure.measure import report_plots as rp

    a, attrs = record.arrays, record.attrs
    level, reasons = stored_verdict(record)
    name = record.name
    floor = _finite(attrs.get("noise_floor_px"))
    sigma = cm.sigma_px
    section: dict[str, Any] = {
        "name": name,
        "registry_name": record.registry_name,
        "verdict": level,
        "reasons": reasons,
        "rms": _finite(attrs.get("rms")),
        "rms_half": [_finite(v) for v in np.asarray(a.get("rms_half", [np.nan, np.nan]))],
        "noise_floor": floor,
        "formal_floor": _finite(attrs.get("formal_floor_px")),
        "scatter_floor": _finite(attrs.get("scatter_floor_px")),
        "rms_ratio": _finite(attrs.get("rms_ratio")),
        "residual_sigma": sigma,
        "outlier_threshold": _finite(attrs.get("outlier_threshold_px")),
        "missing": [],
    }
    needed = ("obs_pixels", "residuals", "obs_half", "obs_image", "inliers")
    if all(k in a for k in needed):
        pixels = np.asarray(a["obs_pixels"], dtype=float)
        residuals = np.asarray(a["residuals"], dtype=float)
        half = np.asarray(a["obs_half"]).astype(int)
        image = np.asarray(a["obs_image"]).astype(int)
        finite = np.all(np.isfinite(pixels), axis=-1) & np.all(np.isfinite(residuals), axis=-1)
        inlier = np.asarray(a["inliers"]).astype(bool) & finite
        noise = floor if floor else (sigma or float(np.sqrt(np.mean(residuals[inlier] ** 2))))
        boxes = {h: dg.half_box(image_size, split, h) for h in Half}
        fractions = {h.label: dg.coverage(pixels[inlier & (half == h)], boxes[h]) for h in Half}
        biases = {
            h: dg.region_bias(
                pixels[inlier & (half == h)], residuals[inlier & (half == h)], boxes[h], noise
            )  # fmt: skip
            for h in Half
        }
        edges, counts, expected = dg.residual_histogram(residuals[inlier], noise)
        outside = np.sum(np.abs(residuals[inlier]) > 3 * noise)
        names = [str(n) for n in a.get("image_names", [])]
        boards = [str(b) for b in a["image_boards"]] if "image_boards" in a else None
        length = np.linalg.norm(residuals, axis=-1)
        worst = np.argsort(-np.where(finite, length, -np.inf))[:WORST_OBSERVATIONS]
        ids = np.asarray(a["obs_ids"]).astype(int) if "obs_ids" in a else None
        section.update(
            n_corners=int(finite.sum()),
            n_inliers=int(inlier.sum()),
            n_outliers=int((finite & ~inlier).sum()),
            coverage=fractions,
            bias={
                h.label: {
                    "regions": int(np.isfinite(b.magnitude).sum()),
                    "significant": b.n_significant,
                    "max_px": _finite(np.nanmax(b.magnitude))
                    if np.isfinite(b.magnitude).any()
                    else None,
                }
                for h, b in biases.items()
            },
            histogram={
                "sigma": noise,
                "beyond_3sigma_percent": float(100.0 * outside / max(counts.sum(), 1)),
                "expected_beyond_3sigma_percent": 0.27,
            },
            images=dg.image_rms_table(
                image[inlier], half[inlier], residuals[inlier], names, boards
            ),  # fmt: skip
            worst=[
                {
                    "image": names[image[i]] if image[i] < len(names) else str(image[i]),
                    "half": Half(half[i]).label,
                    "corner": None if ids is None else int(ids[i]),
                    "u": float(pixels[i, 0]),
                    "v": float(pixels[i, 1]),
                    "residual": float(length[i]),
                    "outlier": not bool(inlier[i]),
                }
                for i in worst
            ],
            figures={
                "coverage": _b64(
                    rp.coverage_figure(pixels[inlier], half[inlier], image_size, split, fractions)
                ),  # fmt: skip
                "residuals": _b64(
                    rp.residual_field_figure(
                        pixels[inlier], residuals[inlier], image_size, split, name
                    )
                ),  # fmt: skip
                "bias": _b64(rp.bias_figure(biases, image_size, split, name)),
                "histogram": _b64(rp.histogram_figure(edges, counts, expected, noise, name)),
                "outliers": _b64(
                    rp.outliers_figure(pixels[finite], ~inlier[finite], image_size, split, name)
                ),  # fmt: skip
            },
        )
    else:
        section["missing"].append(
            "the model was stored without its residuals (not by `calibrate`, or by an "
            f"older version): re-run `endomeasure calibrate {session} --model {name}`"
        )
    section.update(_parameters(record, cm))
    return section


def _parameters(record, cm) -> dict[str, Any]:
    """Free parameters with +-, strong correlations and the baseline with +-."""
    from endomeasure.measure.diagnostics import effective_baseline, strong_correlations

    a, model = record.arrays, cm.model
    values = model.named_params()
    out: dict[str, Any] = {}
    if "free_names" in a and "std" in a:
        free = [str(n) for n in a["free_names"]]
        units = [str(u) for u in a["free_units"]] if "free_units" in a else [""] * len(free)
        std = np.asarray(a["std"], dtype=float)
        out["parameters"] = [
            {"name": n, "value": float(values[n]), "std": _finite(s), "unit": u}
            for n, s, u in zip(free, std, units, strict=True)
        ]
        if "correlation" in a:
            out["correlations"] = [
                {"a": p, "b": q, "r": r}
                for p, q, r in strong_correlations(free, a["correlation"], STRONG_CORRELATION)
            ]
    else:
        out["parameters"] = [
            {"name": n, "value": float(v), "std": None, "unit": model.unit(n)}
            for n, v in values.items()
        ]
    baseline, std = effective_baseline(model, cm.param_cov)
    out["baseline"] = {"value": _finite(baseline), "std": _finite(std)}
    return out


def _trust_section(session, name: str, cm, depths, limits, image_size, split) -> dict[str, Any]:
    """The trust map of one model: bands of the predicted 95 % error of a 1 mm length."""
    from endomeasure.measure.diagnostics import TRUST_LABELS, trust_bands
    from endomeasure.measure.predict import Z95
    from endomeasure.measure.report_plots import trust_figure
    from endomeasure.pipeline.predict import predict_map

    if depths is None:
        seen = cm.depth_range_mm
        if seen is None:
            return {"missing": "the calibration stored no corner depths: give --depths"}
        depths = np.linspace(seen[0], seen[1], TRUST_DEPTHS).round(1).tolist()
    report = predict_map(session, model=name, depths=depths, grid=TRUST_GRID, calibrated=cm)
    em = report.error_map
    relative = 100.0 * (np.abs(em.errors.bias) + Z95 * em.errors.std) / abs(em.true)
    relative[~em.visible] = np.nan
    band = trust_bands(relative, limits)
    left = cm.model.project(em.centres, Half.LEFT).pixels
    panels, rows = [], []
    for z in report.depths:
        sel = np.isclose(em.centres[:, 2], z) & np.all(np.isfinite(left), axis=-1)
        panels.append((z, left[sel], band[sel]))
        row = {"z_mm": z, "n": int(sel.sum())}
        for k, label in enumerate(TRUST_LABELS):
            row[label] = float(100.0 * np.mean(band[sel] == k)) if sel.any() else None
        r = relative[sel][np.isfinite(relative[sel])]
        row["median_percent"] = float(np.median(r)) if r.size else None
        rows.append(row)
    sigma = np.max(np.atleast_1d(report.noise.sigma))
    title = (f"{name}: predicted 95 % error of a 1 mm length "
             f"(image noise {sigma:.4f} px, {report.noise.source})")  # fmt: skip
    return {
        "rows": rows,
        "limits": list(limits),
        "calibration": report.calibration,
        "model_error": report.model_error,
        "figure": _b64(trust_figure(panels, image_size, split, limits, title)),
    }


def _board_test_section(reader, session: str, models: Sequence[str]) -> dict[str, Any]:
    from endomeasure.io.records import BOARD_TEST_RECORD, board_test_fields
    from endomeasure.measure.board_runs import ModelBoardTest
    from endomeasure.measure.plots import plot_board_test, png_bytes

    names = reader.record_names(BOARD_TEST_RECORD)
    if not names:
        return {"missing": f"no board test yet: run `endomeasure measure {session} --board-test "
                           "--model all` (needs test images: `detect ... --set test`)"}  # fmt: skip
    results, zone_mm, rows = {}, None, {}
    for name in names:
        record = reader.record(BOARD_TEST_RECORD, name)
        results[name] = ModelBoardTest.from_fields(board_test_fields(record))
        zone_mm = float(record.attrs.get("zone_mm", defaults.ZONE_MM))
        s = results[name].summary
        for k in range(len(s.kind)):
            key = (name, str(results[name].summary_board[k]), float(s.zone_start[k]),
                   float(s.zone_end[k]))  # fmt: skip
            row = rows.setdefault(key, dict(zip(("model", "board", "zone_start", "zone_end"),
                                                key, strict=True), kinds={}))  # fmt: skip
            row["kinds"][str(s.kind[k])] = {
                "n": int(s.n[k]), "mean": _finite(s.mean_error[k]), "std": _finite(s.std_error[k])
            }  # fmt: skip
    figure = png_bytes(plot_board_test, results, zone_mm)
    kinds = list(dict.fromkeys(k for r in rows.values() for k in r["kinds"]))
    return {"zone_mm": zone_mm, "rows": list(rows.values()), "kinds": kinds,
            "figure": _b64(figure)}  # fmt: skip


def _predicted_section(reader, session: str) -> dict[str, Any]:
    from endomeasure.io.records import PREDICTION_RECORD
    from endomeasure.measure.plots import plot_predicted_vs_actual, png_bytes

    entries = []
    for name in reader.record_names(PREDICTION_RECORD):
        record = reader.record(PREDICTION_RECORD, name)
        if record.attrs.get("mode") != "board-test":
            continue
        zones = json.loads(str(record.attrs["zones"]))
        entries.append({
            "model": str(record.attrs.get("model", name)),
            "within_band": _finite(record.attrs.get("within_band")),
            "zones": len(zones),
            "figure": _b64(png_bytes(plot_predicted_vs_actual, zones)),
        })  # fmt: skip
    if not entries:
        return {"missing": f"no prediction of the board test yet: run `endomeasure predict-error "
                           f"{session} --board-test --model raytrace`"}  # fmt: skip
    return {"entries": entries}


def _measurements_section(reader, session: str) -> dict[str, Any]:
    from endomeasure.io.records import MEASUREMENT_RECORD

    rows = []
    for name in reader.record_names(MEASUREMENT_RECORD):
        record = reader.record(MEASUREMENT_RECORD, name)
        at = record.attrs
        rows.append({
            "id": name, "kind": str(at.get("measurement_kind", "")),
            "image": str(at.get("image", "")), "model": str(at.get("model", "")),
            "value": _finite(at.get("value")), "ci95": _finite(at.get("ci95")),
            "unit": str(record.units.get("value", "")),
            "relative_percent": _finite(at.get("relative_percent")),
            "warning": str(at.get("warning", "") or ""),
        })  # fmt: skip
    if not rows:
        return {"missing": f"no measurements yet: `endomeasure measure {session} --image NAME "
                           "--kind length --left U,V --left U,V`"}  # fmt: skip
    return {"rows": rows}


def _section_states(context: dict[str, Any]) -> dict[str, str]:
    states = {"overview": "present"}
    for m in context["models"]:
        states[f"calibration-{m['name']}"] = "; ".join(m["missing"]) or "present"
        states[f"trust-{m['name']}"] = m["trust"].get("missing", "present")
    for missing in context["missing_models"]:
        states[f"calibration-{missing['name']}"] = missing["why"]
    for key in ("board_test", "predicted", "measurements"):
        states[key.replace("_", "-")] = context[key].get("missing", "present")
    return states


def write_report(
    session: str | os.PathLike,
    out: str | os.PathLike | None = None,
    *,
    depths: Sequence[float] | None = None,
    bands: tuple[float, float] = defaults.TRUST_BANDS_PERCENT,
) -> ReportSummary:
    """Write the HTML report of ``session`` to ``out`` (default: beside it, ``.html``)."""
    from endomeasure.io.outputs import checked_output
    from endomeasure.io.report_html import render_report
    from endomeasure.io.session import open_session
    from endomeasure.models import MODELS
    from endomeasure.pipeline import calibrated_model
    from endomeasure.pipeline.info import summarise_session

    session = str(session)
    low, high = bands
    if not (np.isfinite(low) and np.isfinite(high) and 0 < low < high):
        raise BadInputError(
            f"trust bands must be two increasing positive percentages, got {low:g},{high:g}",
            hint="e.g. --bands 1,5",
        )
    target = Path(session).with_suffix(".html") if out is None else Path(out)
    target = checked_output(target, "report", inputs=[session], suffixes=(".html", ".htm"))
    summary = summarise_session(session)
    models, missing_models = [], []
    with open_session(session) as reader:
        meta = reader.metadata()
        image_size, split = meta.image_size, meta.split
        for name in reader.model_names():
            record = reader.model(name)
            cm = calibrated_model(reader, name, session, allow_failed=True)
            section = _calibration_section(record, cm, image_size, split, session)
            models.append((section, cm))
        held = {s["registry_name"] for s, _ in models}
        for name in MODELS:
            if name not in held:
                why = "no images detected yet" if not summary.detections else "not calibrated"
                missing_models.append({
                    "name": name,
                    "why": f"{why}: run `endomeasure calibrate {session} --model {name}`",
                })  # fmt: skip
        board_test = _board_test_section(reader, session, [s["name"] for s, _ in models])
        predicted = _predicted_section(reader, session)
        measurements = _measurements_section(reader, session)
    for section, cm in models:
        if section["verdict"] == "failed":
            section["trust"] = {"missing": "the calibration failed: no trust map for it"}
        elif cm.param_cov is None or cm.sigma_px is None:
            section["trust"] = {"missing": "the model has no covariance or residual sigma"}
        else:
            try:
                section["trust"] = _trust_section(session, section["name"], cm, depths,
                                                  (low, high), image_size, split)  # fmt: skip
            except EndomeasureError as exc:
                section["trust"] = {"missing": exc.what}
    context = {
        "title": f"Calibration report: {Path(session).name}",
        "generated": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "version": __version__,
        "session": summary.to_dict(),
        "models": [s for s, _ in models],
        "missing_models": missing_models,
        "board_test": board_test,
        "predicted": predicted,
        "measurements": measurements,
        "bands": [low, high],
    }
    context["sections"] = _section_states(context)
    render_report(context, target)
    return ReportSummary(session, str(target), context["sections"])
