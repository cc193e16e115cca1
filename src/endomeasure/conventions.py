"""Units, frames, the pixel-centre rule, halves and per-point status codes.

This module is the single place where conventions are fixed; ``docs/conventions.md``
explains them in prose. Everything else imports from here.

- Lengths in millimetres, image coordinates in pixels, angles in radians internally
  (degrees only at the user interface).
- Pixel coordinates ``(u, v)`` are full-image coordinates for both halves. The centre of
  the top-left pixel is ``(0.0, 0.0)`` (OpenCV's rule); ``u`` grows right, ``v`` down.
  A pixel of column ``c`` covers ``c - 0.5 <= u < c + 0.5``.
- The split is a column index ``split``: columns ``< split`` form the left half,
  columns ``>= split`` the right half. In continuous coordinates the boundary is
  ``u = split - 0.5``.
- Camera frame: x right, y down, z forward along the optical axis, origin at the lens
  projection centre (for the ``pinhole`` model: the left virtual camera's centre).
- Shapes: points ``(..., 3)``, pixels ``(..., 2)``, leading dimensions broadcast;
  Jacobians put the dependent dimension first, ``(..., 2, 3)``.
- Rotations are rotation vectors (Rodrigues) in parameter vectors; a transform named
  ``T_a_b`` maps coordinates in frame b into frame a.
- Board frame: corners on z = 0, corner id = ``row * cols + col``.
"""

from __future__ import annotations

import enum

import numpy as np

__all__ = [
    "Half",
    "Status",
    "in_half",
]


class Half(enum.IntEnum):
    """One half of the split sensor."""

    LEFT = 0
    RIGHT = 1

    @classmethod
    def parse(cls, value: Half | str | int) -> Half:
        """Accept ``Half``, ``'left'``/``'right'`` (any case) or ``0``/``1``."""
        if isinstance(value, Half):
            return value
        if isinstance(value, str):
            try:
                return cls[value.strip().upper()]
            except KeyError:
                raise ValueError(f"half must be 'left' or 'right', not {value!r}") from None
        return cls(int(value))

    @property
    def label(self) -> str:
        return self.name.lower()


class Status(enum.IntEnum):
    """Per-point outcome of a vectorised optical computation.

    Vectorised code never raises for a single bad point: it returns NaN for that point
    and one of these codes (stored as ``uint8`` arrays).
    """

    OK = 0
    OUTSIDE_HALF = 1
    """The pixel or projection is not inside the requested half of the image."""
    TOTAL_INTERNAL_REFLECTION = 2
    """A ray met a glass-air face beyond the critical angle."""
    NOT_CONVERGED = 3
    """An iterative inverse (undistortion, ray aiming, triangulation) did not converge."""
    INVALID_INPUT = 4
    """NaN or infinite input."""
    BEHIND = 5
    """The point lies behind the probe, or a ray misses a surface in its forward direction."""
    PARALLEL = 6
    """Two rays are parallel, so they have no unique common perpendicular."""


STATUS_DTYPE = np.uint8


def in_half(pixels: np.ndarray, half: Half, split: int, image_size: tuple[int, int]) -> np.ndarray:
    """Whether each pixel lies inside the given half of the image.

    Parameters
    ----------
    pixels : ndarray, shape (..., 2), px
        Full-image pixel coordinates.
    half : Half
    split : int
        First column of the right half.
    image_size : (width, height), px

    Returns
    -------
    ndarray of bool, shape (...)
        False for NaN pixels.
    """
    width, height = image_size
    u = pixels[..., 0]
    v = pixels[..., 1]
    edge = split - 0.5
    if Half.parse(half) is Half.LEFT:
        inside_u = (u >= -0.5) & (u < edge)
    else:
        inside_u = (u >= edge) & (u < width - 0.5)
    return inside_u & (v >= -0.5) & (v < height - 0.5)
