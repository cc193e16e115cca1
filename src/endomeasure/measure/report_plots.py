"""Figures of the calibration report (``endomeasure report``), each returned as PNG bytes.

One figure per question an engineer asks of a calibration: where the calibration corners
were (:func:`coverage_figure`), what the residuals look like over each half
(:func:`residual_field_figure`) and per region (:func:`bias_figure`), whether their
distribution is the expected noise (:func:`histogram_figure`), where the outliers are
(:func:`outliers_figure`) and where a measurement can be trusted (:func:`trust_figure`).
The numbers come from :mod:`endomeasure.measure.diagnostics`; drawing only here.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np

from endomeasure.conventions import Half
from endomeasure.measure.diagnostics import TRUST_LABELS, RegionBias, half_box
from endomeasure.measure.plots import _pyplot, _save

__all__ = [
    "bias_figure",
    "coverage_figure",
    "histogram_figure",
    "outliers_figure",
    "residual_field_figure",
    "trust_figure",
]

_HALF_COLOURS = {Half.LEFT: "tab:blue", Half.RIGHT: "tab:orange"}
_BAND_COLOURS = {"green": "#2ca02c", "yellow": "#f2c80f", "red": "#d62728"}


def _png(fig) -> bytes:
    buffer = io.BytesIO()
    _save(fig, buffer, dpi=90)
    return buffer.getvalue()


def _image_axes(ax, image_size: Sequence[int], split: int) -> None:
    width, height = image_size
    ax.axvline(split - 0.5, color="0.6", lw=0.8, ls="--")
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("u [px]", fontsize=8)
    ax.set_ylabel("v [px]", fontsize=8)
    ax.tick_params(labelsize=7)


def _image_figure(image_size: Sequence[int]):
    width, height = image_size
    plt = _pyplot()
    return plt.subplots(figsize=(8.5, 8.5 * height / width + 0.9))


def coverage_figure(
    pixels: np.ndarray, half: np.ndarray, image_size, split: int, fractions: dict[str, float]
) -> bytes:
    """Every calibration corner at its place on the sensor, coloured by half, with the
    fraction of each half's regions that hold one."""
    fig, ax = _image_figure(image_size)
    for h in Half:
        sel = half == h
        label = f"{h.label} ({fractions[h.label]:.0%} of the regions)"
        ax.scatter(*pixels[sel].T, s=1.5, color=_HALF_COLOURS[h], alpha=0.5, label=label)
    _image_axes(ax, image_size, split)
    ax.legend(fontsize=7, loc="lower right", markerscale=5)
    ax.set_title("calibration corners over the sensor", fontsize=9)
    return _png(fig)


def residual_field_figure(
    pixels: np.ndarray, residuals: np.ndarray, image_size, split: int, title: str
) -> bytes:
    """Residual vectors at their corners, magnified so that the 95th percentile of their
    lengths draws as 25 px."""
    fig, ax = _image_figure(image_size)
    length = np.linalg.norm(residuals, axis=-1)
    scale = max(float(np.percentile(length, 95)) if length.size else 0.0, 1e-12) / 25.0
    ax.quiver(*pixels.T, *residuals.T, length, angles="xy", scale_units="xy", scale=scale,
              cmap="viridis", width=0.0018)  # fmt: skip
    _image_axes(ax, image_size, split)
    ax.set_title(f"{title}: residual vectors x{1.0 / scale:.0f}", fontsize=9)
    return _png(fig)


def bias_figure(biases: dict[Half, RegionBias], image_size, split: int, title: str) -> bytes:
    """Mean residual length per region (colour), its direction (arrow) and the regions
    where it exceeds the noise (outlined red)."""
    fig, ax = _image_figure(image_size)
    vmax = max((np.nanmax(b.magnitude) for b in biases.values() if np.isfinite(b.magnitude).any()),
               default=1e-9)  # fmt: skip
    image = None
    for b in biases.values():
        u0, u1, v0, v1 = b.box
        image = ax.imshow(b.magnitude, extent=(u0, u1, v1, v0), cmap="magma", vmin=0, vmax=vmax,
                          interpolation="nearest")  # fmt: skip
        n_v, n_u = b.count.shape
        du, dv = (u1 - u0) / n_u, (v1 - v0) / n_v
        uc, vc = np.meshgrid(u0 + du * (np.arange(n_u) + 0.5), v0 + dv * (np.arange(n_v) + 0.5))
        mean = np.nan_to_num(b.mean)
        ax.quiver(uc, vc, mean[..., 0], mean[..., 1], color="c", angles="xy", width=0.004)
        for iv, iu in zip(*np.nonzero(b.significant), strict=True):
            ax.add_patch(
                _pyplot().Rectangle(
                    (u0 + iu * du, v0 + iv * dv), du, dv, fill=False, edgecolor="red", lw=1.5
                )  # fmt: skip
            )
    _image_axes(ax, image_size, split)
    if image is not None:
        fig.colorbar(image, ax=ax, shrink=0.7, label="mean residual per region [px]")
    ax.set_title(f"{title}: residual bias per region (red: beyond the noise)", fontsize=9)
    return _png(fig)


def histogram_figure(
    edges: np.ndarray, counts: np.ndarray, expected: np.ndarray, sigma_px: float, title: str
) -> bytes:
    """Residual coordinates against the Gaussian of the noise floor (log scale, so the
    tails show)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.6))
    centres = 0.5 * (edges[1:] + edges[:-1])
    ax.bar(centres, counts, width=np.diff(edges), color="tab:blue", alpha=0.6, label="residuals")
    ax.plot(centres, expected, "k-", lw=1.2, label=f"Gaussian, sigma {sigma_px:.4f} px")
    ax.set_yscale("log")
    ax.set_ylim(bottom=0.5)
    ax.set_xlabel("residual per coordinate [px]", fontsize=8)
    ax.set_ylabel("corners", fontsize=8)
    ax.legend(fontsize=7)
    ax.set_title(f"{title}: residual distribution against the expected noise", fontsize=9)
    return _png(fig)


def outliers_figure(
    pixels: np.ndarray, outlier: np.ndarray, image_size, split: int, title: str
) -> bytes:
    """The corners the calibration dropped as outliers (red) among the ones it used."""
    fig, ax = _image_figure(image_size)
    ax.scatter(*pixels[~outlier].T, s=1, color="0.7", label="used")
    ax.scatter(*pixels[outlier].T, s=14, color="red", marker="x", label="outlier")
    _image_axes(ax, image_size, split)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"{title}: {int(outlier.sum())} outliers", fontsize=9)
    return _png(fig)


def trust_figure(
    panels: Sequence[tuple[float, np.ndarray, np.ndarray]],
    image_size,
    split: int,
    limits: tuple[float, float],
    title: str,
) -> bytes:
    """One panel per depth: the left half with each grid point coloured by its trust band
    (``panels``: ``(depth_mm, pixels (K, 2), band (K,))``)."""
    plt = _pyplot()
    width, height = image_size
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(3.4 * n, 3.4 * height / split + 0.9), squeeze=False)
    u0, u1, v0, v1 = half_box(image_size, split, Half.LEFT)
    for ax, (depth, pixels, band) in zip(axes[0], panels, strict=True):
        ax.add_patch(plt.Rectangle((u0, v0), u1 - u0, v1 - v0, color=_BAND_COLOURS["red"],
                                   alpha=0.25, lw=0))  # fmt: skip
        colours = [_BAND_COLOURS[TRUST_LABELS[b]] for b in band]
        ax.scatter(*pixels.T, c=colours, s=30, marker="s")
        ax.set_xlim(u0, u1)
        ax.set_ylim(v1, v0)
        ax.set_aspect("equal")
        ax.set_title(f"z = {depth:g} mm", fontsize=9)
        ax.tick_params(labelsize=6)
    handles = [
        plt.Line2D([], [], ls="none", marker="s", color=_BAND_COLOURS[label], label=text)
        for label, text in zip(
            TRUST_LABELS,
            (f"95 % error <= {limits[0]:g} %", f"<= {limits[1]:g} %", "beyond, or one half only"),
            strict=True,
        )
    ]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=7)
    fig.suptitle(title, fontsize=9)
    return _png(fig)
