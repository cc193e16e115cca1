"""An independent check of rendered chessboard corners: the centre of point symmetry.

Near a chessboard corner, an image formed by a locally affine mapping, a point-symmetric
blur and locally uniform lighting is point-symmetric about the corner: opposite
quadrants have the same colour, so ``I(c + h) = I(c - h)``. The corner is the point
``c`` minimising ``sum_h w(h) (I(c + h) - I(c - h))^2`` over a small disc (bicubic
interpolation, Gaussian weights). This locator shares nothing with the renderer or with
OpenCV's detectors, so it tells whether the renderer put each corner where the truth
says (it measures the renderer, not a detector). Its own floor on ideal, analytically
rendered boards and what it finds on the renders: ``docs/simulator.md``, "Accuracy of
the rendered truth".
"""

from __future__ import annotations

import numpy as np

__all__ = ["symmetric_corners"]


def symmetric_corners(image: np.ndarray, guesses: np.ndarray, radius_px: float = 4.0) -> np.ndarray:
    """Locate chessboard corners as centres of point symmetry.

    Parameters
    ----------
    image : ndarray, shape (height, width)
        Grey image (any numeric type).
    guesses : ndarray, shape (N, 2), px
        Starting points within about ``radius_px / 2`` of the corners.
    radius_px : float
        Radius of the disc compared, px; keep it below half a square.

    Returns
    -------
    ndarray, shape (N, 2), px
        Corner positions ``(u, v)``, pixel centres at integers.
    """
    from scipy.ndimage import map_coordinates, spline_filter
    from scipy.optimize import least_squares

    coeffs = spline_filter(np.asarray(image, dtype=np.float64), order=3)
    r = int(np.ceil(radius_px))
    grid = np.arange(-r, r + 0.5, 0.5)
    hx, hy = np.meshgrid(grid, grid)
    # one of each pair (h, -h): the upper half-plane
    keep = (hx**2 + hy**2 <= radius_px**2) & ((hy > 0) | ((hy == 0) & (hx > 0)))
    hx, hy = hx[keep], hy[keep]
    weight = np.exp(-0.5 * (hx**2 + hy**2) / (radius_px / 2.0) ** 2)

    def residual(c: np.ndarray) -> np.ndarray:
        a = map_coordinates(coeffs, [c[1] + hy, c[0] + hx], order=3, prefilter=False)
        b = map_coordinates(coeffs, [c[1] - hy, c[0] - hx], order=3, prefilter=False)
        return weight * (a - b)

    out = np.empty((len(guesses), 2))
    for i, guess in enumerate(np.asarray(guesses, dtype=np.float64)):
        out[i] = least_squares(residual, guess, x_scale=0.1).x
    return out
