"""Figures of calibrations, the board test, predicted errors and error maps (matplotlib, Agg).

matplotlib is imported inside each function (it is slow to import and only the commands
that draw need it). Each function writes one PNG and returns its path; given a binary
file object instead of a path it writes there (:func:`png_bytes`).

- :func:`plot_board_test` — the paper's Fig. 4: one row per board-test kind; one column
  per model with the error of every measurement at its place in the (left) image, and a
  last column with mean +- std per distance zone for every model;
- :func:`plot_predicted_vs_actual` — the paper's Fig. 5: per kind, the actual mean error
  and standard deviation per zone against the predicted ones;
- :func:`plot_error_map` — the predicted standard deviation of a template measurement
  over the working volume, one panel per depth plane;
- :func:`plot_matches` — operator points found automatically in the other half: both
  halves with the points, their matches and the searched epipolar curves;
- :func:`plot_residuals` — a calibration's residual vectors over the image and residual
  length against distance;
- :func:`plot_comparison` — where two calibrations disagree: per depth plane, the pixel
  disagreement in both halves and the normalised length difference over the left half.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from endomeasure.conventions import Half

__all__ = [
    "plot_board_test",
    "plot_comparison",
    "plot_error_map",
    "plot_matches",
    "plot_predicted_vs_actual",
    "plot_residuals",
    "png_bytes",
]

_UNITS = {"x-segment": "mm", "y-segment": "mm", "point-plane": "mm", "area": "mm²"}
_KINDS = ("x-segment", "y-segment", "point-plane", "area")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path | BinaryIO, dpi: int = 100) -> Path | BinaryIO:
    """Write ``fig`` as PNG to a path (its folder made) or a binary file object."""
    if not hasattr(path, "write"):
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png", dpi=dpi, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def png_bytes(draw, *args, **kwargs) -> bytes:
    """The PNG that the plot function ``draw(*args, path, **kwargs)`` writes, as bytes
    (figures embedded in a report instead of written beside it)."""
    buffer = io.BytesIO()
    draw(*args, buffer, **kwargs)
    return buffer.getvalue()


def plot_board_test(results: Mapping[str, Any], zone_mm: float, path: str | Path) -> Path:
    """The paper's Fig. 4 for every model of a board test.

    Parameters
    ----------
    results : mapping of model name -> ModelBoardTest
        (:mod:`endomeasure.measure.board_runs`): its ``table`` (kind, error, pixel_mean,
        z_mean) and ``summary`` / ``summary_board``.
    zone_mm : float, mm
    path : path
        PNG to write.
    """
    plt = _pyplot()
    names = list(results)
    n_cols = len(names) + 1
    fig, axes = plt.subplots(
        len(_KINDS),
        n_cols,
        figsize=(4.4 * n_cols, 3.4 * len(_KINDS)),
        squeeze=False,
        layout="constrained",
    )
    for r, kind in enumerate(_KINDS):
        errors = [results[m].table.error[results[m].table.kind == kind] for m in names]
        finite = np.concatenate([e[np.isfinite(e)] for e in errors] + [np.zeros(1)])
        lim = float(np.percentile(np.abs(finite), 98)) or 1e-9
        for c, m in enumerate(names):
            ax = axes[r, c]
            t = results[m].table
            sel = (t.kind == kind) & np.isfinite(t.error)
            sc = ax.scatter(
                t.pixel_mean[sel, 0],
                t.pixel_mean[sel, 1],
                c=t.error[sel],
                s=6,
                cmap="coolwarm",
                vmin=-lim,
                vmax=lim,
            )
            ax.invert_yaxis()
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{m}: {kind}", fontsize=9)
            ax.set_xlabel("u [px] (left half)", fontsize=8)
            ax.set_ylabel("v [px]", fontsize=8)
            fig.colorbar(sc, ax=ax, shrink=0.8, label=f"error [{_UNITS[kind]}]")
        ax = axes[r, -1]
        for m in names:
            s, boards = results[m].summary, results[m].summary_board
            for board in dict.fromkeys(boards.tolist()):
                sel = (s.kind == kind) & (boards == board)
                centre = 0.5 * (s.zone_start[sel] + s.zone_end[sel])
                ax.errorbar(
                    centre,
                    s.mean_error[sel],
                    yerr=s.std_error[sel],
                    marker="o",
                    ms=3,
                    capsize=3,
                    label=f"{m} {board.split(':', 1)[-1]}",
                )
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_title(f"{kind}: mean ± std per {zone_mm:g} mm zone", fontsize=9)
        ax.set_xlabel("z [mm]", fontsize=8)
        ax.set_ylabel(f"error [{_UNITS[kind]}]", fontsize=8)
        ax.legend(fontsize=6)
    fig.suptitle("board test: measurement errors (paper Fig. 4)")
    return _save(fig, path)


def plot_predicted_vs_actual(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """The paper's Fig. 5: actual and predicted mean error and std per zone and kind.

    Parameters
    ----------
    rows : sequence of dict
        One per (board, kind, zone): ``board``, ``kind``, ``zone_start``, ``zone_end``,
        ``actual_mean``, ``actual_std``, ``predicted_mean``, ``predicted_std``.
    path : path
    """
    plt = _pyplot()
    fig, axes = plt.subplots(
        1, len(_KINDS), figsize=(4.2 * len(_KINDS), 3.6), squeeze=False, layout="constrained"
    )
    for c, kind in enumerate(_KINDS):
        ax = axes[0, c]
        sel = [r for r in rows if r["kind"] == kind]
        for board in dict.fromkeys(r["board"] for r in sel):
            rs = sorted((r for r in sel if r["board"] == board), key=lambda r: r["zone_start"])
            z = np.array([0.5 * (r["zone_start"] + r["zone_end"]) for r in rs])
            label = board.split(":", 1)[-1]
            am = np.array([r["actual_mean"] for r in rs])
            sd = np.array([r["actual_std"] for r in rs])
            pm = np.array([r["predicted_mean"] for r in rs])
            ps = np.array([r["predicted_std"] for r in rs])
            line = ax.errorbar(
                z, am, yerr=sd, marker="o", ms=3, capsize=3, ls="none", label=f"actual {label}"
            )
            colour = line[0].get_color()
            ax.plot(z, pm, color=colour, lw=1, label=f"predicted mean {label}")
            ax.fill_between(z, pm - ps, pm + ps, color=colour, alpha=0.2)
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_title(kind, fontsize=9)
        ax.set_xlabel("z [mm]", fontsize=8)
        ax.set_ylabel(f"error [{_UNITS[kind]}]", fontsize=8)
        ax.legend(fontsize=6)
    fig.suptitle("predicted (line ± band: mean ± std) vs actual (points ± bars) per zone (Fig. 5)")
    return _save(fig, path)


def plot_error_map(error_map, path: str | Path, n_panels: int = 4) -> Path:
    """Predicted standard deviation of a template over the working volume.

    Parameters
    ----------
    error_map : ErrorMap
        From :func:`endomeasure.measure.predict.error_map`.
    path : path
    n_panels : int
        Depth planes shown (spread over those in the map).
    """
    plt = _pyplot()
    c = error_map.centres
    depths = np.unique(np.round(c[:, 2], 6))
    show = depths[
        np.unique(np.linspace(0, depths.size - 1, min(n_panels, depths.size)).round().astype(int))
    ]
    fig, axes = plt.subplots(1, show.size + 1, figsize=(3.6 * (show.size + 1), 3.4), squeeze=False)
    std = error_map.errors.std
    finite = std[np.isfinite(std)]
    vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
    unit = "mm²" if error_map.template == "area" else "mm"
    for k, z in enumerate(show):
        ax = axes[0, k]
        sel = np.isclose(c[:, 2], z) & np.isfinite(std)
        sc = ax.scatter(c[sel, 0], c[sel, 1], c=std[sel], s=8, cmap="viridis", vmin=0, vmax=vmax)
        ax.invert_yaxis()
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"z = {z:g} mm", fontsize=9)
        ax.set_xlabel("x [mm]", fontsize=8)
        ax.set_ylabel("y [mm]", fontsize=8)
    fig.colorbar(sc, ax=axes[0, : show.size].tolist(), shrink=0.8, label=f"predicted std [{unit}]")
    ax = axes[0, -1]
    med = [np.nanmedian(std[np.isclose(c[:, 2], z)]) for z in depths]
    hi = [np.nanmax(std[np.isclose(c[:, 2], z)]) for z in depths]
    ax.plot(depths, med, "o-", ms=3, label="median over the field")
    ax.plot(depths, hi, "s--", ms=3, label="worst in the field")
    ax.set_xlabel("z [mm]", fontsize=8)
    ax.set_ylabel(f"predicted std [{unit}]", fontsize=8)
    ax.legend(fontsize=7)
    fig.suptitle(f"predicted std of a {error_map.size_mm:g} mm {error_map.template}")
    return _save(fig, path)


_ZOOM_PX = 24
"""Half-width of the close-ups of a query point and its match, px (a 15 px patch and
the curve around it)."""
_MAX_ZOOMS = 6
"""Points beyond this many get no close-ups (the overview still shows them)."""


def plot_matches(image: np.ndarray, matches: Sequence[Any], path: str | Path, split: int) -> Path:
    """Both halves with operator points, their matches and the searched epipolar curves.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        The whole split image.
    matches : sequence of Match
        (:mod:`endomeasure.measure.correspondence`), one per point, in order: the query
        pixel, its half, status, match (NaN if refused), best candidate and curve.
    path : path
        PNG to write.
    split : int
        First column of the right half (drawn as a line).

    Notes
    -----
    Top: the whole image with every query point (circle), its epipolar curve in the
    other half (the searched samples), and its match (cross) joined to the point by a
    thin line; refused points in red with their best candidate (if any) and the
    reason. Below, for up to :data:`_MAX_ZOOMS` points, close-ups of the query's
    neighbourhood and of the match's (or candidate's).
    """
    plt = _pyplot()
    img = np.asarray(image, dtype=np.float64)
    grey = img[..., :3].mean(axis=-1) if img.ndim == 3 else img
    height, width = grey.shape
    zooms = list(enumerate(matches))[:_MAX_ZOOMS]
    n_zoom_cols = max(2 * len(zooms), 2)
    fig = plt.figure(figsize=(max(9.0, 1.6 * n_zoom_cols), 7.8 if zooms else 5.6))
    rows, ratios = (2, [4, 1.3]) if zooms else (1, [1])
    grid = fig.add_gridspec(rows, n_zoom_cols, height_ratios=ratios)
    ax = fig.add_subplot(grid[0, :])
    vmin, vmax = np.percentile(grey, [0.5, 99.5])
    ax.imshow(grey, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.axvline(split - 0.5, color="yellow", lw=0.8, ls="--")
    colours = plt.get_cmap("tab10")
    for i, m in enumerate(matches):
        c = colours(i % 10) if m.ok else "red"
        q = np.asarray(m.pixel)
        if len(m.curve):
            ax.plot(m.curve[:, 0], m.curve[:, 1], "-", color=c, lw=0.8, alpha=0.8)
        ax.plot(*q, "o", mfc="none", mec=c, ms=8, mew=1.4)
        other = m.match if m.ok else m.candidate
        if np.all(np.isfinite(other)):
            ax.plot(*other, "x", color=c, ms=8, mew=1.6)
            ax.plot([q[0], other[0]], [q[1], other[1]], "-", color=c, lw=0.4, alpha=0.6)
        label = (
            f"{i + 1}: score {m.score:.3f}, gap {m.ray_gap_mm * 1e3:.1f} µm"
            if m.ok
            else f"{i + 1}: refused ({m.status.value})"
        )
        ax.annotate(label, q, xytext=(6, 7), textcoords="offset points", color=c, fontsize=7,
                    bbox=dict(boxstyle="round,pad=0.15", fc="black", alpha=0.45, lw=0))  # fmt: skip
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_title("operator points (o), matches (x) and epipolar curves; red: refused", fontsize=9)
    for k, (i, m) in enumerate(zooms):
        c = colours(i % 10) if m.ok else "red"
        other = m.match if m.ok else m.candidate
        for j, (centre, what) in enumerate(((m.pixel, "point"), (other, "match"))):
            zax = fig.add_subplot(grid[1, 2 * k + j])
            zax.set_xticks([])
            zax.set_yticks([])
            zax.set_title(f"{i + 1} {what}" if m.ok or j == 0 else f"{i + 1} candidate",
                          fontsize=7, color=c)  # fmt: skip
            if not np.all(np.isfinite(centre)):
                zax.text(0.5, 0.5, "none", ha="center", va="center", transform=zax.transAxes)
                continue
            u, v = np.asarray(centre, dtype=np.float64)
            zax.imshow(grey, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
            if j == 1 and len(m.curve):
                zax.plot(m.curve[:, 0], m.curve[:, 1], "-", color=c, lw=0.8)
            zax.plot(u, v, "+", color=c, ms=10, mew=1.2)
            zax.set_xlim(u - _ZOOM_PX, u + _ZOOM_PX)
            zax.set_ylim(v + _ZOOM_PX, v - _ZOOM_PX)
    return _save(fig, path)


def plot_residuals(result, out_dir: str | Path) -> list[str]:
    """A calibration's residual vectors over the image and residual length against
    distance (a ``CalibrationResult``), one PNG each in ``out_dir``; the written paths."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    name = result.model_name
    width, height = result.model.config.image_size
    use = result.inliers & np.all(np.isfinite(result.residuals), axis=-1)
    q, r = result.obs_pixels[use], result.residuals[use]
    length = np.linalg.norm(r, axis=-1)
    written = []

    fig, ax = plt.subplots(figsize=(9, 9 * height / width + 0.8))
    scale = max(float(np.percentile(length, 95)), 1e-12) / 25.0  # 95th percentile ~ 25 px
    ax.quiver(q[:, 0], q[:, 1], r[:, 0], r[:, 1], length, angles="xy", scale_units="xy",
              scale=scale, cmap="viridis", width=0.002)  # fmt: skip
    ax.axvline(result.model.config.split - 0.5, color="0.6", lw=0.8, ls="--")
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px]")
    ax.set_title(
        f"{name}: residual vectors x{1.0 / scale:.0f} (RMS {result.rms:.3f} px, "
        f"left {result.rms_half[0]:.3f}, right {result.rms_half[1]:.3f})"
    )
    written.append(str(_save(fig, out_dir / f"{name}-residual-vectors.png", dpi=110)))

    depth = result.obs_points[use, 2]
    half = result.obs_half[use]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for h, colour in ((0, "tab:blue"), (1, "tab:orange")):
        sel = half == h
        ax.scatter(depth[sel], length[sel], s=4, alpha=0.5, color=colour, label=Half(h).label)
    edges = np.linspace(depth.min(), depth.max(), 9)
    idx = np.clip(np.digitize(depth, edges) - 1, 0, len(edges) - 2)
    centres = 0.5 * (edges[1:] + edges[:-1])
    rms_bin = [np.sqrt(np.mean(length[idx == k] ** 2)) if np.any(idx == k) else np.nan
               for k in range(len(centres))]  # fmt: skip
    ax.plot(centres, rms_bin, "k-o", ms=3, label="RMS per depth bin")
    ax.set_xlabel("corner depth z [mm]")
    ax.set_ylabel("residual length [px]")
    ax.set_title(f"{name}: residual against distance")
    ax.legend(loc="upper right")
    written.append(str(_save(fig, out_dir / f"{name}-residual-vs-distance.png", dpi=110)))
    return written


def plot_comparison(comparison, path: str | Path, labels: tuple[str, str] = ("A", "B")) -> Path:
    """Disagreement maps of two calibrations, one row per depth plane.

    Columns: ``|q_B - q_A|`` in the left and in the right half, px, and the normalised
    length difference ``(L_B - L_A) / sigma`` of the segment, each at the grid point's
    left-half pixel (:class:`endomeasure.measure.compare.Comparison`).
    """
    plt = _pyplot()
    c = comparison
    n = c.depths.size
    fig, axes = plt.subplots(n, 3, figsize=(11.5, 2.9 * n), squeeze=False)
    maps = (
        ("left |q_B - q_A| [px]", np.linalg.norm(c.diff_left, axis=1), "viridis"),
        ("right |q_B - q_A| [px]", np.linalg.norm(c.diff_right, axis=1), "viridis"),
        (f"(L_B - L_A) / sigma, {c.size_mm:g} mm segment", c.z, "coolwarm"),
    )
    for col, (title, values, cmap) in enumerate(maps):
        finite = values[np.isfinite(values)]
        top = float(np.max(np.abs(finite))) if finite.size else 1.0
        top = top if top > 0 else 1.0
        lo = -top if cmap == "coolwarm" else 0.0
        for k, depth in enumerate(c.depths):
            ax = axes[k, col]
            sel = (c.depth_index == k) & np.isfinite(values)
            sc = ax.scatter(c.pixels[sel, 0], c.pixels[sel, 1], c=values[sel], s=14, cmap=cmap,
                            vmin=lo, vmax=top)  # fmt: skip
            ax.invert_yaxis()
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{title}, z = {depth:g} mm", fontsize=8)
            ax.tick_params(labelsize=7)
        fig.colorbar(sc, ax=axes[:, col].tolist(), shrink=0.8)
    fig.suptitle(f"{labels[1]} against {labels[0]}, over {labels[0]}'s left half [px]", fontsize=10)
    return _save(fig, path)


_MASK_COLOURS = {0: (0.1, 0.75, 0.2), 1: (0.95, 0.8, 0.1), 2: (0.85, 0.1, 0.1)}
"""The surface picture's mask: green accurate, yellow inaccurate, red not measurable."""


def plot_surface(surface, classes: np.ndarray, path: str | Path, title: str = "") -> Path:
    """The shaded depth picture of a dense surface with its red/yellow/green mask.

    Left: the depth map, hill-shaded (light from the top left) and coloured by z; pixels
    without depth are shown red. Right: the mask over the grey image (green: the 2-sigma
    error within the first trust band, yellow: within the warning, red: no depth).
    """
    plt = _pyplot()
    depth = surface.depth
    u0, v0, u1, v1 = surface.region
    extent = (u0 - 0.5, u1 - 0.5, v1 - 0.5, v0 - 0.5)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    gy, gx = np.gradient(np.where(np.isfinite(depth), depth, np.nanmedian(depth)))
    shade = np.clip(0.6 + 4.0 * (gx + gy), 0.0, 1.0)
    from matplotlib import cm, colors

    finite = np.isfinite(depth)
    lo, hi = np.nanpercentile(depth, [1, 99]) if finite.any() else (0.0, 1.0)
    norm = colors.Normalize(lo, hi)
    rgb = cm.viridis(norm(np.nan_to_num(depth, nan=lo)))[..., :3] * shade[..., None]
    rgb[~finite] = _MASK_COLOURS[2]
    axes[0].imshow(rgb, extent=extent)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap="viridis"), ax=axes[0], label="z (mm)")
    axes[0].set_title("depth, shaded (red: no depth)")
    grey = surface.grey / max(float(np.max(surface.grey)), 1.0)
    overlay = np.repeat(grey[..., None], 3, axis=-1) * 0.55
    for level, colour in _MASK_COLOURS.items():
        overlay[classes == level] += 0.45 * np.asarray(colour)
    axes[1].imshow(np.clip(overlay, 0, 1), extent=extent)
    axes[1].set_title("mask: green accurate, yellow inaccurate, red not measurable")
    for ax in axes:
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    if title:
        fig.suptitle(title)
    return _save(fig, path)
