"""Image-quality figures of one half: edge sharpness at the board, brightness, contrast.

The sharpness figure is the **edge width**: the distance over which the grey level
rises from 10 % to 90 % across the board's square edges, in pixels (lower is sharper;
below about 3 px a board is sharp enough for calibration). It is measured at the edge
midpoints between neighbouring detected corners, on profiles across the edge, so it
says how sharp the corners actually used are, whatever the rest of the image shows.
For a Gaussian blur of standard deviation sigma the width is ``2.563 sigma``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["HalfQuality", "edge_width_px", "half_quality"]

# Profile sampling step along the edge normal, px.
PROFILE_STEP_PX = 0.25
# Positions along each edge (fractions of the corner-to-corner segment) that get a profile.
PROFILE_POSITIONS = (0.35, 0.5, 0.65)
# Fraction of each profile end averaged for the dark and bright plateau levels.
PLATEAU_FRACTION = 0.15
# Profiles shorter than this (px each side) cannot measure a width.
MIN_PROFILE_REACH_PX = 2.0
# Profiles whose plateaus differ by less than this many grey levels are skipped (no edge).
MIN_EDGE_CONTRAST = 10.0


@dataclasses.dataclass(frozen=True)
class HalfQuality:
    """Quality figures of one half.

    Attributes
    ----------
    edge_width_px : float, px
        Median 10-90 % edge rise width at the detected corners; NaN if not measurable.
    brightness : float
        Mean grey level of the half, 0..255.
    contrast : float
        Spread of grey levels (99th minus 1st percentile), 0..255.
    """

    edge_width_px: float
    brightness: float
    contrast: float


def edge_width_px(
    gray: np.ndarray, ids: np.ndarray, pixels: np.ndarray, cols: int, reach_fraction: float
) -> float:
    """Median 10-90 % rise width across the square edges between detected corners.

    Parameters
    ----------
    gray : ndarray, shape (height, width), grey levels
        The image the pixels refer to.
    ids : ndarray, shape (n,), int
        Corner ids (``row * cols + col``).
    pixels : ndarray, shape (n, 2), px
    cols : int
        Inner corners per board row.
    reach_fraction : float
        Profile half-length as a fraction of the corner spacing; it must stay inside
        uniform parts of the two squares the edge separates.

    Returns
    -------
    float, px
        NaN when no edge could be measured.
    """
    from scipy.ndimage import map_coordinates

    ids = np.asarray(ids)
    if len(ids) < 2:
        return float("nan")
    index = {int(i): k for k, i in enumerate(ids)}
    pairs = []
    for k, i in enumerate(ids):
        i = int(i)
        if (i % cols) + 1 < cols and (i + 1) in index:
            pairs.append((k, index[i + 1]))
        if (i + cols) in index:
            pairs.append((k, index[i + cols]))
    if not pairs:
        return float("nan")
    pairs = np.array(pairs)
    start, end = pixels[pairs[:, 0]], pixels[pairs[:, 1]]
    segment = end - start
    length = np.linalg.norm(segment, axis=1)
    tangent = segment / length[:, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    reach = reach_fraction * length
    widths = []
    for e in range(len(pairs)):
        if reach[e] < MIN_PROFILE_REACH_PX:
            continue
        offsets = np.arange(-reach[e], reach[e] + 1e-9, PROFILE_STEP_PX)
        profiles = []
        for t in PROFILE_POSITIONS:
            centre = start[e] + t * segment[e]
            points = centre[None, :] + offsets[:, None] * normal[e][None, :]
            # map_coordinates takes (row, col) = (v, u); pixel centres sit on integers.
            profiles.append(
                map_coordinates(gray, [points[:, 1], points[:, 0]], order=1, mode="nearest")
            )
        profile = np.mean(profiles, axis=0)
        n_plateau = max(1, int(PLATEAU_FRACTION * len(profile)))
        first, last = profile[:n_plateau].mean(), profile[-n_plateau:].mean()
        if abs(last - first) < MIN_EDGE_CONTRAST:
            continue
        if last < first:
            profile, first, last = profile[::-1], last, first
        level = (profile - first) / (last - first)
        # Samples within the 10-90 % band, counted: robust to noise on a monotone rise.
        widths.append(np.count_nonzero((level > 0.1) & (level < 0.9)) * PROFILE_STEP_PX)
    return float(np.median(widths)) if widths else float("nan")


def half_quality(gray: np.ndarray, width_px: float = float("nan")) -> HalfQuality:
    """Brightness and contrast of a half, with an edge width measured elsewhere.

    Parameters
    ----------
    gray : ndarray, shape (height, width), grey levels 0..255
    width_px : float, px
    """
    low, high = np.percentile(gray, [1, 99])
    return HalfQuality(
        edge_width_px=float(width_px), brightness=float(gray.mean()), contrast=float(high - low)
    )
