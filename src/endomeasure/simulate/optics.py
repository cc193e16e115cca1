"""Ground-truth optics for rendering: supersampled ray bundles and the apex image.

The optics never change between images of one preset, so the object-space rays of all
sub-pixel samples are traced once through the truth optics
(:class:`~endomeasure.simulate.truth_optics.TruthOptics`) and kept (as float32: the
rounding moves a ray by about 1e-7 rad, i.e. 3e-5 px, far below anything measured).
"""

from __future__ import annotations

import dataclasses
import threading
from typing import NamedTuple

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.simulate.truth_optics import TruthOptics

__all__ = [
    "RayBundle",
    "Region",
    "apex_columns",
    "sample_offsets",
    "trace_region",
    "ray_bundle",
    "clear_ray_cache",
]


def sample_offsets(n: int) -> np.ndarray:
    """Sub-pixel sample offsets of an ``n x n`` N-rooks (rotated-grid) pattern.

    Parameters
    ----------
    n : int
        Samples per axis; the pattern has ``n * n`` samples.

    Returns
    -------
    ndarray, shape (n * n, 2), px
        Offsets ``(du, dv)`` from the pixel centre, inside ``[-0.5, 0.5)``.

    Notes
    -----
    Sample ``(i, j)`` sits at ``((n i + j + 0.5) / n^2, (n j + i + 0.5) / n^2) - 0.5``.
    Every sample has its own column and its own row of an ``n^2 x n^2`` sub-grid, so a
    near-vertical or near-horizontal edge (the edges of a chessboard) is resolved in
    ``n^2`` coverage steps instead of the ``n`` of a regular grid. The pattern is
    point-symmetric about the pixel centre (sample ``(i, j)`` mirrors ``(n-1-i, n-1-j)``)
    and its mean is the centre, so the box filter it samples is unbiased: a pixel of
    column ``c`` covers ``c - 0.5 <= u < c + 0.5`` (conventions).
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    du = (n * i + j + 0.5) / (n * n) - 0.5
    dv = (n * j + i + 0.5) / (n * n) - 0.5
    return np.stack([du.ravel(), dv.ravel()], axis=-1)


def apex_columns(optics: TruthOptics, rows: np.ndarray) -> np.ndarray:
    """Image column where the prism apex appears, for each row (R,) px; NaN where none.

    A lens ray entering the glass leaves it through the front face it meets first; the
    apex image is where it meets both at once
    (:meth:`~endomeasure.simulate.truth_optics.TruthOptics.apex_columns`).
    """
    return optics.apex_columns(rows)


@dataclasses.dataclass(frozen=True)
class Region:
    """A rectangle of whole pixels: columns ``u0 <= c < u1``, rows ``v0 <= r < v1``."""

    u0: int
    v0: int
    u1: int
    v1: int

    @classmethod
    def full(cls, image_size: tuple[int, int]) -> Region:
        return cls(0, 0, int(image_size[0]), int(image_size[1]))

    @property
    def width(self) -> int:
        return self.u1 - self.u0

    @property
    def height(self) -> int:
        return self.v1 - self.v0

    def check(self, image_size: tuple[int, int]) -> None:
        width, height = image_size
        if not (0 <= self.u0 < self.u1 <= width and 0 <= self.v0 < self.v1 <= height):
            raise ValueError(f"region {self} is not inside the {width}x{height} image")


class RayBundle(NamedTuple):
    """Object-space rays of every sub-pixel sample of a region (camera frame).

    Arrays are indexed ``[component, row, column, sample]`` relative to ``region``
    (``valid`` and ``cos_lens`` without the component axis); rays that fail
    (total internal reflection, a missed face) have ``valid`` False and zero vectors.
    """

    region: Region
    origins: np.ndarray  # (3, H, W, S) float32, mm (component-major: fast chunked slices)
    directions: np.ndarray  # (3, H, W, S) float32, unit
    valid: np.ndarray  # (H, W, S) bool
    cos_lens: np.ndarray  # (H, W) float64: cosine of the lens-space field angle per pixel


def trace_region(
    model: TruthOptics, region: Region, supersampling: int, chunk_rays: int = 262144
) -> RayBundle:
    """Trace the rays of all sub-pixel samples of a region through the truth optics.

    Each pixel's samples are traced through the front face of the pixel's own half
    (by its column and the split), as the calibrated models do for any pixel.
    """
    region.check(model.config.image_size)
    offsets = sample_offsets(supersampling)
    S = offsets.shape[0]
    H, W = region.height, region.width
    origins = np.zeros((3, H, W, S), dtype=np.float32)
    directions = np.zeros((3, H, W, S), dtype=np.float32)
    valid = np.zeros((H, W, S), dtype=bool)
    cols = np.arange(region.u0, region.u1)
    split = model.config.split
    rows_per_chunk = max(1, chunk_rays // max(1, W * S))
    for r0 in range(0, H, rows_per_chunk):
        r1 = min(H, r0 + rows_per_chunk)
        vv = np.arange(region.v0 + r0, region.v0 + r1, dtype=np.float64)
        uu, vv = np.meshgrid(cols.astype(np.float64), vv)  # (h, W)
        for half in (Half.LEFT, Half.RIGHT):
            in_half = (uu < split) if half is Half.LEFT else (uu >= split)
            if not in_half.any():
                continue
            rr, cc = np.nonzero(in_half)
            pix = np.stack([uu[rr, cc], vv[rr, cc]], axis=-1)[:, None, :] + offsets[None]
            rays = model.rays(pix.reshape(-1, 2), half)
            ok = rays.status == Status.OK
            o = np.where(ok[:, None], rays.origins, 0.0).reshape(-1, S, 3)
            d = np.where(ok[:, None], rays.directions, 0.0).reshape(-1, S, 3)
            for k in range(3):
                origins[k, r0 + rr, cc] = o[..., k]
                directions[k, r0 + rr, cc] = d[..., k]
            valid[r0 + rr, cc] = ok.reshape(-1, S)
    uu, vv = np.meshgrid(cols.astype(np.float64), np.arange(region.v0, region.v1, dtype=np.float64))
    x, y, ok = model.lens.pixel_to_ideal(uu.ravel(), vv.ravel())
    cos_lens = np.where(ok, 1.0 / np.sqrt(1.0 + x * x + y * y), 0.0).reshape(uu.shape)
    return RayBundle(region, origins, directions, valid, cos_lens)


_CACHE: dict[tuple, RayBundle] = {}
_CACHE_LOCK = threading.Lock()
_CACHE_MAX = 2  # bundles kept; a full 640x480 4x4 bundle is about 120 MB


def _optics_key(optics: TruthOptics) -> tuple:
    """Hashable identity of the truth optics' numbers."""
    planes = tuple((p.normal.tobytes(), p.d) for p in (optics.rear, optics.left, optics.right))
    return (repr(optics.lens), planes, optics.n_glass)


def ray_bundle(model: TruthOptics, region: Region, supersampling: int, chunk_rays: int = 262144):
    """:func:`trace_region`, cached per optics, configuration, region and sampling."""
    key = (
        _optics_key(model),
        model.config.image_size,
        model.config.split,
        dataclasses.astuple(region),
        int(supersampling),
    )
    with _CACHE_LOCK:
        hit = _CACHE.get(key)
    if hit is not None:
        return hit
    bundle = trace_region(model, region, supersampling, chunk_rays)
    with _CACHE_LOCK:
        while len(_CACHE) >= _CACHE_MAX:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = bundle
    return bundle


def clear_ray_cache() -> None:
    """Forget all cached ray bundles (frees their memory)."""
    with _CACHE_LOCK:
        _CACHE.clear()
