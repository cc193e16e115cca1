"""Finding the split column: the dark, blurred band the prism apex leaves between halves.

Method (``find_split``)
-----------------------
The apex of the biprism sends almost no light to the sensor and what it sends is out of
focus, so the columns under it are darker and flatter than the columns of either view.
For every column the function computes

- ``b``: the median grey level of the column (robust to a few bright rows), and
- ``g``: the mean gradient energy ``|dI/du| + |dI/dv|`` of the column,

smooths both along u with a Gaussian (sigma = ``width / 200``, at least 2 px), divides
each by its median over the whole image and forms the score ``s = b + g / 2``. Within
the middle third of the image the column of lowest score is the band's core; the band
is the run of columns around it whose score stays below halfway between that minimum
and the median score of the middle third, and its centre is the centroid of the run
weighted by how far each column's score lies below that level. The split (the first
column of the right half) is ``floor(centre + 1)``, so that the half boundary
``u = split - 0.5`` lies within half a pixel of the band centre.

How it fails, and what is checked
---------------------------------
- No band (a uniform or featureless image, or optics without a dark apex band): the
  minimum is not clearly below its surroundings (``s_min > 0.6 * median``) -> error.
- The darkest columns at the edge of the middle third (a band off-centre by more than
  a sixth of the width, or a dark object in the middle of the view) -> error.
- A band wider than a quarter of the image -> error.
- A dark object that happens to sit exactly in the middle third of both views (a dark
  vertical stripe in the scene) can be mistaken for the band; use several images (the
  caller takes the median over a set) or give the column with ``--split COLUMN``.

Every failure is a :class:`~endomeasure.errors.BadInputError` suggesting ``--split``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from endomeasure.errors import BadInputError

__all__ = ["SplitEstimate", "find_split", "to_gray_float"]

# A band must be this much darker-and-flatter than the median of the middle third.
BAND_MAX_RELATIVE_SCORE = 0.6
# Weight of gradient energy against brightness in the column score.
GRADIENT_WEIGHT = 0.5
# Widest band accepted, as a fraction of the image width.
MAX_BAND_FRACTION = 0.25
MIN_IMAGE_WIDTH = 16


@dataclasses.dataclass(frozen=True)
class SplitEstimate:
    """Where the band between the halves is.

    Attributes
    ----------
    split : int
        First column of the right half.
    centre_px : float, px
        Band centre in u.
    width_px : float, px
        Width of the run of band columns.
    contrast : float
        Band score over the middle third's median score (lower is a clearer band).
    """

    split: int
    centre_px: float
    width_px: float
    contrast: float


def to_gray_float(image: np.ndarray) -> np.ndarray:
    """A grey image as float64 in 0..255, from grey or colour, 8- or 16-bit input.

    Parameters
    ----------
    image : ndarray, shape (height, width) or (height, width, channels)
        Colour channels in OpenCV's BGR(A) order; uint8, uint16 or float (0..255).
    """
    image = np.asarray(image)
    scale = 255.0 / 65535.0 if image.dtype == np.uint16 else 1.0
    data = image.astype(np.float64) * scale
    if data.ndim == 3:
        if data.shape[2] == 1:
            data = data[..., 0]
        else:
            # ITU-R BT.601 luma, as cv2.cvtColor(..., COLOR_BGR2GRAY).
            data = 0.114 * data[..., 0] + 0.587 * data[..., 1] + 0.299 * data[..., 2]
    return data


def _smooth(profile: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(profile, sigma, mode="nearest")


def find_split(image: np.ndarray, path: str | None = None) -> SplitEstimate:
    """Find the split column of one image from the dark band between the halves.

    Parameters
    ----------
    image : ndarray, shape (height, width[, channels])
    path : str, optional
        Named in the error message.

    Returns
    -------
    SplitEstimate

    Raises
    ------
    BadInputError
        No clear band in the middle third of the image (see the module notes).
    """
    gray = to_gray_float(image)
    height, width = gray.shape
    hint = "give the first column of the right half with --split COLUMN"
    if width < MIN_IMAGE_WIDTH or height < 2:
        raise BadInputError(
            f"image of {width}x{height} px is too small to split", path=path, hint=hint
        )
    brightness = np.median(gray, axis=0)
    energy = np.zeros_like(gray)
    energy[:, 1:-1] += np.abs(gray[:, 2:] - gray[:, :-2]) / 2
    energy[1:-1, :] += np.abs(gray[2:, :] - gray[:-2, :]) / 2
    gradient = energy.mean(axis=0)
    sigma = max(2.0, width / 200.0)
    brightness = _smooth(brightness, sigma)
    gradient = _smooth(gradient, sigma)
    eps = 1e-9
    score = brightness / (np.median(brightness) + eps) + GRADIENT_WEIGHT * gradient / (
        np.median(gradient) + eps
    )
    lo, hi = width // 3, (2 * width) // 3
    middle = score[lo:hi]
    core = lo + int(np.argmin(middle))
    reference = float(np.median(middle))
    contrast = float(score[core] / (reference + eps))
    if not np.isfinite(contrast) or contrast > BAND_MAX_RELATIVE_SCORE:
        raise BadInputError(
            f"no dark band between the halves found (darkest middle column at {contrast:.0%} "
            f"of the typical level, needs below {BAND_MAX_RELATIVE_SCORE:.0%})",
            path=path,
            hint=hint,
        )
    if core <= lo + 1 or core >= hi - 2:
        raise BadInputError(
            "the darkest columns lie at the edge of the middle third of the image, not in a band",
            path=path,
            hint=hint,
        )
    level = score[core] + 0.5 * (reference - score[core])
    left = core
    while left > 0 and score[left - 1] < level:
        left -= 1
    right = core
    while right < width - 1 and score[right + 1] < level:
        right += 1
    band_width = right - left + 1
    if band_width > MAX_BAND_FRACTION * width:
        raise BadInputError(
            f"the dark region in the middle is {band_width} px wide, too wide for the prism band",
            path=path,
            hint=hint,
        )
    # Sub-column centre: centroid of the run, weighted by depth below the level.
    columns = np.arange(left, right + 1)
    weights = np.maximum(level - score[left : right + 1], 0.0)
    centre = (
        float((columns * weights).sum() / weights.sum())
        if weights.sum() > 0
        else 0.5 * (left + right)
    )
    return SplitEstimate(
        split=int(np.floor(centre + 1.0)),
        centre_px=centre,
        width_px=float(band_width),
        contrast=contrast,
    )
