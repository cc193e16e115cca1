"""``endomeasure surface``: the dense 3D surface of a region of one image.

Load the image and the calibrated model, run the dense search
(:func:`~endomeasure.measure.dense.dense_surface`), store the depth map with its sigma
and status as a ``surface`` record, and optionally write a PLY point cloud and a shaded
depth picture with the red/yellow/green mask. Every output path and the region are
checked before any work; a refused input stores nothing.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

from endomeasure import defaults
from endomeasure.errors import BadInputError

__all__ = ["SurfaceReport", "surface"]

METHOD = (
    "plane sweep (ZNCC) + refinement along the exact curve, window per pixel by "
    "intersecting confidence intervals; sigma: UT of the match and the calibration"
)


@dataclasses.dataclass(frozen=True)
class SurfaceReport:
    """What :func:`surface` computed (and stored)."""

    session: str
    record: str
    model: str
    image: str
    region: tuple[int, int, int, int]
    pixels: int
    measured: int
    counts: dict[str, int]
    median_depth_mm: float | None
    median_sigma_mm: float | None
    classes: dict[str, int]
    levels: int
    seconds: float
    ply: str | None
    plot: str | None
    surface: Any = dataclasses.field(repr=False, compare=False, default=None)

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out.pop("surface")
        out["region"] = list(self.region)
        return out


def _checked_outputs(session, ply, plot):
    from endomeasure.io.outputs import PLOT_SUFFIXES, checked_output, checked_session_target

    checked_session_target(session, create=False)
    ply = None if ply is None else checked_output(ply, "point cloud", inputs=[session],
                                                  suffixes=(".ply",))  # fmt: skip
    plot = None if plot is None else checked_output(plot, "plot", inputs=[session],
                                                    suffixes=PLOT_SUFFIXES)  # fmt: skip
    return ply, plot


def surface(
    session: str | Path,
    image: str,
    model_name: str = "raytrace",
    region: tuple[int, int, int, int] | None = None,
    *,
    ply: str | Path | None = None,
    plot: str | Path | None = None,
    window_px: int = defaults.DENSE_WINDOW_PX,
    store: bool = True,
) -> SurfaceReport:
    """Dense depth of a region of an image's left half, stored as a ``surface`` record.

    Parameters
    ----------
    session : path
    image : str
        An image of the session.
    model_name : str
        A model stored by ``calibrate`` (not a failed one).
    region : (u0, v0, u1, v1), optional, px
        Left-half rectangle, columns ``u0 <= u < u1``; default the whole left half.
    ply, plot : path, optional
        Point cloud (``.ply``) and picture (``.png``) to write.
    window_px : int
        Side of the plane sweep's correlation window (odd); the refinement chooses its
        windows per pixel (``defaults.DENSE_WINDOW_RANGE_PX``).
    store : bool
        Write the record (replacing that of the same image and model).

    Raises
    ------
    BadInputError
        Unknown image or model, a region outside the left half, unwritable outputs.
    GoalNotMetError
        No pixel of the region could be measured (nothing is stored).
    """
    import numpy as np

    from endomeasure.errors import GoalNotMetError
    from endomeasure.io import records
    from endomeasure.io.session import edit_session, open_session
    from endomeasure.measure.dense import (
        DenseSettings,
        DenseStatus,
        accuracy_classes,
        check_region,
        dense_surface,
    )
    from endomeasure.pipeline import calibrated_model, search_depths

    start = time.perf_counter()
    ply_path, plot_path = _checked_outputs(session, ply, plot) if store else (ply, plot)
    with open_session(session) as reader:
        reader.image_info(image)
        cm = calibrated_model(reader, model_name, session)
        # the operator search's depths: where the user calibrated is where the probe works
        settings = DenseSettings(window_px=window_px, depth_range_mm=search_depths(cm))
        clipped = check_region(cm.model, region, settings.window_px)  # before the pixels
        pixels = reader.image(image)
    if pixels.ndim == 3:
        pixels = pixels[..., :3].mean(axis=2)
    misfit = None if cm.misfit is None else cm.misfit.covariance(np.zeros((1, 2)))
    result = dense_surface(cm.model, pixels, clipped, settings, param_cov=cm.param_cov,
                           misfit_cov=misfit)  # fmt: skip
    ok = result.status == DenseStatus.OK
    if not ok.any():
        raise GoalNotMetError(
            f"no pixel of region {','.join(map(str, clipped))} of {image!r} could be measured "
            "(untextured, not seen by the right half, or no clear correlation peak)",
            path=str(session),
            hint="choose a textured region that both halves see",
        )
    counts = {s.label: int((result.status == s).sum()) for s in DenseStatus}
    classes = accuracy_classes(result, defaults.TRUST_BANDS_PERCENT)
    class_counts = {n: int((classes == k).sum()) for k, n in enumerate(("green", "yellow", "red"))}
    import numpy as np

    name = records.surface_record_name(image, model_name)
    if ply_path is not None:
        from endomeasure.io.ply import write_ply

        vv, uu = np.nonzero(ok)
        write_ply(
            ply_path, result.points[ok], result.sigma_point[ok], result.grey[ok],
            np.stack([uu + clipped[0], vv + clipped[1]], axis=-1),
            comment=f"endomeasure surface {name}: mm, model frame of {model_name}",
        )  # fmt: skip
    if plot_path is not None:
        from endomeasure.measure.plots import plot_surface

        plot_surface(result, classes, plot_path, title=f"{image}, {model_name}")
    report = SurfaceReport(
        session=str(session), record=name if store else "", model=model_name, image=image,
        region=tuple(int(x) for x in clipped), pixels=int(ok.size), measured=int(ok.sum()),
        counts=counts, median_depth_mm=float(np.median(result.depth[ok])),
        median_sigma_mm=float(np.median(result.sigma_depth[ok])), classes=class_counts,
        levels=result.levels, seconds=time.perf_counter() - start,
        ply=None if ply_path is None else str(ply_path),
        plot=None if plot_path is None else str(plot_path), surface=result,
    )  # fmt: skip
    if store:
        attrs = {"method": METHOD, "window_px": settings.window_px,
                 "window_range_px": list(settings.window_range_px),
                 "prefilter_px": settings.prefilter_px,
                 "depth_range_mm": list(settings.depth_range_mm), "levels": result.levels,
                 "noise_level": [list(n) for n in result.noise], "counts": counts}  # fmt: skip
        with edit_session(session) as writer:
            if name in writer.record_names(records.SURFACE_RECORD):
                writer.delete_record(records.SURFACE_RECORD, name)
            writer.write_record(
                records.surface_record(name, result, image=image, model=model_name, attrs=attrs)
            )
    return report


def check_region_text(text: str | None) -> tuple[int, int, int, int] | None:
    """``U0,V0,U1,V1`` as four integers (None stays None)."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        values = tuple(int(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4:
        raise BadInputError(f"region {text!r} is not U0,V0,U1,V1 (four integers, px)")
    return values
