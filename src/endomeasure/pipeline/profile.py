"""``endomeasure measure --kind profile | area-profile``: depth profiles of the surface.

Load the image and the calibrated model; match and triangulate the three reference
points when given (the operator search of ``measure``: clicked left pixel exact, the
match at its predicted precision; their covariances by the unscented transform with the
calibration covariance); run the dense search over the smallest region that holds the
path(s) and the reference areas (:func:`~endomeasure.measure.dense.dense_surface`); build
the reference plane and the profile(s) (:mod:`endomeasure.measure.profile`); store them as
a ``profile`` record. Every input is checked before the dense search; a refused one
stores nothing.

``profile``: two ``left`` points, the path's ends; without ``refs`` the reference plane is
the best fit to the dense points within half a correlation window of each end.
``area-profile``: four ``left`` points, reference line 1 (points 1-2) and line 2 (points
3-4); without ``refs`` the plane is the best fit to the dense points along both lines.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure import defaults
from endomeasure.conventions import Half
from endomeasure.errors import BadInputError

__all__ = ["PROFILE_KINDS", "DEFAULT_SLICES", "ProfileReport", "measure_profile"]

PROFILE_KINDS = ("profile", "area-profile")
DEFAULT_SLICES = 5
"""Slices of an area profile unless ``--slices`` says otherwise: the ends and three
between them, as the videoscopes' area depth profile shows a handful."""
REF_POINTS = 3


@dataclasses.dataclass(frozen=True)
class ProfileReport:
    """What :func:`measure_profile` measured (plain data; ``profiles`` are
    :class:`~endomeasure.measure.profile.Profile`)."""

    session: str
    record: str
    model: str
    image: str
    kind: str
    left: list[tuple[float, float]]
    plane: Any  # ReferencePlane
    refs: list[dict[str, Any]] | None
    profiles: list[Any]
    extreme_slice: int
    region: tuple[int, int, int, int]
    plot: str | None = None

    @property
    def extreme(self):
        """The deepest or highest sample of the whole measurement."""
        return self.profiles[self.extreme_slice].extreme

    @property
    def warning(self) -> str | None:
        """Why the extreme may not be the surface's (a gap touches it), else None."""
        if self.extreme.at_gap:
            return (
                "the extreme sample borders a gap without depth: the surface's true extreme "
                "may lie inside the gap"
            )
        return None

    def to_dict(self, samples: bool = True) -> dict[str, Any]:
        return {
            "session": self.session,
            "record": self.record,
            "model": self.model,
            "image": self.image,
            "kind": self.kind,
            "left_px": [list(p) for p in self.left],
            "sign": "height positive towards the probe (in front of the plane), negative behind it",
            "plane": self.plane.to_dict(),
            "refs": self.refs,
            "region": list(self.region),
            "extreme_slice": self.extreme_slice,
            "extreme": self.extreme.to_dict(),
            "warning": self.warning,
            "profiles": [p.to_dict(samples) for p in self.profiles],
            "plot": self.plot,
        }


def _checked_points(kind: str, left, refs, samples, slices):
    from endomeasure.measure.kinds import check_count

    if kind not in PROFILE_KINDS:
        raise BadInputError(f"{kind!r} is not a profile kind ({', '.join(PROFILE_KINDS)})")
    if left is None:
        raise BadInputError(
            f"{kind} needs its points in the left half: --left U,V",
            hint="a profile path is drawn on the left half; its depth comes from both halves",
        )
    check_count(kind, len(left), "--left points")
    if refs is not None and len(refs) != REF_POINTS:
        raise BadInputError(
            f"the reference plane needs exactly {REF_POINTS} --ref points, got {len(refs)}",
            hint="give --ref U,V three times, or none for the best-fit plane",
        )
    if samples is not None and samples < 3:
        raise BadInputError(f"--samples must be at least 3, not {samples}")
    if kind == "profile" and slices is not None:
        raise BadInputError("--slices has no effect on a profile", hint="use --kind area-profile")
    if slices is not None and slices < 1:
        raise BadInputError(f"--slices must be at least 1, not {slices}")
    left = np.asarray(left, dtype=np.float64).reshape(-1, 2)
    refs = None if refs is None else np.asarray(refs, dtype=np.float64).reshape(-1, 2)
    return left, refs


def _region(model, pixels: np.ndarray, window: int):
    """The dense region (u0, v0, u1, v1) holding ``pixels`` (n, 2), clipped to the half."""
    from endomeasure.measure.dense import check_region

    lo = np.floor(pixels.min(axis=0)).astype(int)
    hi = np.ceil(pixels.max(axis=0)).astype(int) + 1
    # at least a window each way (the dense search's own minimum), centred on the pixels
    grow = np.maximum(window - (hi - lo), 0)
    lo, hi = lo - (grow + 1) // 2, hi + (grow + 1) // 2
    return check_region(model, (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])), window)


def _reference_points(cm, image_pixels, refs, patch: int, model_name: str):
    """The matched, triangulated reference points (3, 3) mm, their covariances and what
    the report shows of them."""
    from endomeasure.measure.predict import ImageNoise
    from endomeasure.measure.profile import point_covariances
    from endomeasure.pipeline.measure import (
        _match_other_half,
        _refusal,
        _triangulated,
        search_depths,
    )

    model = cm.model
    matches = _match_other_half(model, image_pixels, refs, Half.LEFT, patch, search_depths(cm))
    if not all(m.ok for m in matches):
        raise _refusal(matches, Half.LEFT, None)
    ql = np.array([m.left for m in matches])
    qr = np.array([m.right for m in matches])
    tri = _triangulated(model, model_name, ql, qr)
    pixel_std = np.zeros((REF_POINTS, 2))
    pixel_std[:, 1] = [m.precision_px for m in matches]  # the clicked pixel is exact
    noise = ImageNoise.per_point(pixel_std, "match precision, left pixels exact")
    # without the calibration's parameters, as the dense samples: they move the plane and
    # the surface alike, and counted per point their shift of the model frame (which no
    # height sees, docs/models.md) would make up most of every height's +-
    cov = point_covariances(model, ql, qr, noise, None, cm.misfit)
    shown = [
        {"left_px": ql[i].tolist(), "right_px": qr[i].tolist(), "xyz_mm": tri.points[i].tolist(),
         "sigma_mm": np.sqrt(np.diag(cov[i])).tolist(), "match": matches[i].to_dict()}
        for i in range(REF_POINTS)
    ]  # fmt: skip
    return tri.points, cov, shown


def measure_profile(
    session: str | Path,
    model_name: str,
    image: str,
    left: Sequence[tuple[float, float]] | None,
    kind: str = "profile",
    *,
    refs: Sequence[tuple[float, float]] | None = None,
    samples: int | None = None,
    slices: int | None = None,
    patch: int = defaults.PATCH_PX,
    plot: str | Path | None = None,
    store: bool = True,
) -> ProfileReport:
    """A depth profile (or area profile) of an image's surface, stored as a record.

    Parameters
    ----------
    session : path
    model_name : str
        A model stored by ``calibrate``.
    image : str
    left : sequence of (u, v), px
        Left-half pixels: the path's two ends (``profile``) or the two reference lines'
        ends (``area-profile``: line 1 = points 1-2, line 2 = points 3-4).
    kind : {'profile', 'area-profile'}
    refs : sequence of three (u, v), px, optional
        Left-half pixels of three points on the undamaged surface: the reference plane
        goes through them (matched in the right half automatically). Default: the
        best-fit plane (module docstring).
    samples : int, optional
        Samples per profile; default about one per pixel of the path.
    slices : int, optional
        Slices of an area profile (default :data:`DEFAULT_SLICES`).
    patch : int, px
        The reference points' correlation patch (odd).
    plot : path, optional
        PNG: the path(s) on the image and the profile with its +-2 sigma band.
    store : bool
        Write the ``profile`` record.

    Raises
    ------
    BadInputError
        Wrong point counts, points outside the left half, collinear reference points,
        a path without depth (untextured, or outside the halves' overlap).
    MatchRefusedError
        A reference point was not matched in the right half (exit 1, nothing stored).
    """
    from endomeasure.io import records
    from endomeasure.io.session import edit_session, open_session
    from endomeasure.measure import profile as core
    from endomeasure.measure.dense import DenseSettings, dense_surface
    from endomeasure.pipeline import calibrated_model
    from endomeasure.pipeline.measure import _check_pixels, _checked_plot, search_depths

    left, refs = _checked_points(kind, left, refs, samples, slices)
    plot = _checked_plot(plot, session, store)
    with open_session(session) as reader:
        reader.image_info(image)
        if refs is not None:
            from endomeasure.measure.correspondence import MatchSettings

            MatchSettings(patch=patch)
        cm = calibrated_model(reader, model_name, session)
        model = cm.model
        _check_pixels(left, Half.LEFT, model, "left")
        if refs is not None:
            _check_pixels(refs, Half.LEFT, model, "--ref")
        settings = DenseSettings(
            depth_range_mm=search_depths(cm), window_range_px=defaults.PROFILE_WINDOW_RANGE_PX
        )
        window = settings.window_px
        if kind == "profile":
            ends = left[None]
            areas = [core.disc_pixels(p, window / 2) for p in left]
        else:
            ends = core.slice_ends(left[:2], left[2:], DEFAULT_SLICES if slices is None else slices)
            areas = [core.line_pixels(left[0], left[1]), core.line_pixels(left[2], left[3])]
        paths = [core.path_pixels(a, b, samples) for a, b in ends]
        needed = np.vstack(paths + ([] if refs is not None else areas))
        region = _region(model, needed, window)
        pixels = reader.image(image)
    refs_shown = None
    if refs is not None:  # the reference plane first: a refused one costs no dense search
        ref_xyz, ref_cov, refs_shown = _reference_points(cm, pixels, refs, patch, model_name)
        plane = core.plane_through_points(ref_xyz, ref_cov)
    if pixels.ndim == 3:
        pixels = pixels[..., :3].mean(axis=2)
    surface = dense_surface(model, pixels, region, settings)
    if refs is None:
        plane = core.plane_fit([core.area_points(model, surface, a) for a in areas], window)
    if kind == "profile":
        profiles, extreme_slice = [core.profile_of(model, surface, plane, paths[0])], 0
    else:
        area = core.area_profile_of(model, surface, plane, ends, samples)
        profiles, extreme_slice = area.slices, area.extreme_slice
    report = ProfileReport(str(session), "", model_name, image, kind,
                           [tuple(map(float, p)) for p in left], plane, refs_shown, profiles,
                           extreme_slice, tuple(int(x) for x in surface.region))  # fmt: skip
    if plot is not None:
        written = plot_profile(report, pixels, model.config.split, ends, plot)
        report = dataclasses.replace(report, plot=str(written))
    if store:
        with edit_session(session) as writer:
            name = records.next_profile_name(writer.record_names(records.PROFILE_RECORD))
            report = dataclasses.replace(report, record=name)
            writer.write_record(records.profile_record(name, report))
    return report


def plot_profile(report: ProfileReport, image: np.ndarray, split: int, ends, path) -> Path:
    """The path(s) on the left half and the profile(s) with the +-2 sigma band."""
    from endomeasure.measure.plots import _pyplot, _save

    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 5), width_ratios=(1, 1.4))
    axes[0].imshow(image[:, :split], cmap="gray", vmin=0, vmax=255)
    for k, (a, b) in enumerate(ends):
        colour = "tab:red" if k == report.extreme_slice else "tab:cyan"
        axes[0].plot([a[0], b[0]], [a[1], b[1]], color=colour, lw=1.2)
    if report.refs:
        q = np.array([r["left_px"] for r in report.refs])
        axes[0].plot(q[:, 0], q[:, 1], "y+", ms=10, label="reference points")
        axes[0].legend(loc="lower right", fontsize=8)
    e = report.extreme
    axes[0].plot(*e.pixel, "rx", ms=9)
    axes[0].set_title(f"{report.image}: {report.kind} (red: the extreme slice)")
    ax = axes[1]
    for k, prof in enumerate(report.profiles):
        s = prof.samples
        if k != report.extreme_slice:
            ax.plot(s.position_mm, s.height, color="tab:cyan", lw=0.7, alpha=0.6)
    s = report.profiles[report.extreme_slice].samples
    ax.fill_between(s.position_mm, s.height - 2 * s.sigma, s.height + 2 * s.sigma,
                    color="tab:red", alpha=0.2, label="+-2 sigma")  # fmt: skip
    ax.plot(s.position_mm, s.height, color="tab:red", lw=1.2, label="height")
    for a, b in report.profiles[report.extreme_slice].gaps:
        ax.axvspan(s.position_mm[a], s.position_mm[b], color="0.8", alpha=0.7)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.plot(e.position_mm, e.height_mm, "rx", ms=9)
    ax.set_xlabel("position along the path in the reference plane (mm)")
    ax.set_ylabel("height above the reference plane (mm, + towards the probe)")
    ax.set_title(f"extreme {e.height_mm:+.3f} +- {e.sigma_mm:.3f} mm at {e.position_mm:.2f} mm "
                 "(grey: no depth)")  # fmt: skip
    ax.legend(fontsize=8)
    return _save(fig, path)
