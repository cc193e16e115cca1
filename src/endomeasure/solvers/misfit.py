"""The calibration's model misfit: what its residuals hold beyond noise, as a random field.

A model that describes the optics leaves residuals of pure noise, independent from corner
to corner. What it cannot describe is smooth over the field, so neighbouring corners share
it. The residuals of a calibration tell the two apart, per half and coordinate:

- **noise**: from the second differences along board rows and columns
  (:func:`~endomeasure.solvers.verdict.second_differences`), in which a smooth misfit
  cancels; its variance ``s^2``;
- **misfit**: the rest of the residual variance, ``m^2 = max(0, mean r^2 - s^2)``, with a
  correlation ``k(d) = J0(d / a) exp(-d^2 / 2 b^2)`` over the pixel distance ``d`` of two
  points. The ring ``a`` and decay ``b`` are fitted to the covariogram of residual pairs of
  one image half (the mean of ``r_i r_j`` over pairs at distance ``d``; noise does not enter
  it for different corners); the correlation of one point's misfit in the two halves comes
  from pairs of *different* corners across the halves (free even of noise the two views
  share, such as print errors).

Why this kernel: each board view's pose absorbs the mean and tilt of the misfit over the
board, so the residuals' covariogram falls below zero at about the board's radius (for
the pinhole pair on the default preset, to -0.46 of its variance at 70 px) before it fades;
a Gaussian cannot follow that and would understate the misfit of longer lengths.
``J0`` (a ring in the frequency plane) is a covariance in two dimensions, the Gaussian
too, and so their product is (Schur).

The misfit offsets of a measurement's points then have the covariance ``K (x) H``:
``K_ij = k(d_ij)`` over the points' left-half pixels and, per coordinate,
``H = [[m_L^2, c], [c, m_R^2]]`` between the halves; a Kronecker product of positive
semi-definite factors is one. Close points share their misfit, which then cancels in a short
length; farther apart, it adds like noise.

The board poses of a calibration absorb the part of the misfit that a rigid motion of the
board explains. For lengths, areas and depths between points that part is a rigid motion
of the scene, which changes none of them: the misfit left in the residuals is what matters
to a measurement. For the absolute position of a single point it is a lower bound.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from scipy.special import j0

from endomeasure.solvers.verdict import MIN_NEIGHBOUR_PAIRS, second_differences

__all__ = ["ModelMisfit", "fit_misfit", "COVARIOGRAM_BINS"]

COVARIOGRAM_BINS = 16
"""Log-spaced bins of pixel distance for the covariogram, from half the median distance of
neighbouring corners to the longest pair."""
_LENGTH_CANDIDATES = 48


@dataclasses.dataclass(frozen=True)
class ModelMisfit:
    """The misfit field of one calibration (see the module notes).

    Attributes
    ----------
    std : ndarray, shape (2, 2), px
        Misfit standard deviation ``m`` per half (left, right) and coordinate (u, v).
    rho_halves : ndarray, shape (2,)
        Correlation of one point's misfit in the two halves, for u and for v.
    ring_px, decay_px : float
        The kernel's lengths ``a`` and ``b`` over the field, px.
    noise : ndarray, shape (2, 2), px
        The residuals' noise per half and coordinate, ``sqrt(mean r^2 - m^2)``.
    """

    std: np.ndarray
    rho_halves: np.ndarray
    ring_px: float
    decay_px: float
    noise: np.ndarray

    def __post_init__(self):
        for name, shape in (("std", (2, 2)), ("rho_halves", (2,)), ("noise", (2, 2))):
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"ModelMisfit.{name} must be finite of shape {shape}")
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        if np.any(self.std < 0) or np.any(np.abs(self.rho_halves) > 1):
            raise ValueError("ModelMisfit needs std >= 0 and |rho_halves| <= 1")
        for length in (self.ring_px, self.decay_px):
            if not (math.isfinite(length) and length > 0):
                raise ValueError("ModelMisfit's kernel lengths must be positive")

    @property
    def present(self) -> bool:
        """Whether there is any misfit to propagate."""
        return bool(np.any(self.std > 0))

    @property
    def noise_sigma(self) -> float:
        """One image noise for every coordinate: the RMS of :attr:`noise`, px."""
        return float(np.sqrt(np.mean(self.noise**2)))

    def covariance(self, pixels_left: np.ndarray) -> np.ndarray:
        """Covariance of the misfit offsets of measurements with these left pixels.

        ``pixels_left`` (..., n, 2) px; returns (..., 4 n, 4 n), px^2, in the input order
        ``u_L, v_L, u_R, v_R`` per point.
        """
        q = np.asarray(pixels_left, dtype=np.float64)
        d2 = np.sum((q[..., :, None, :] - q[..., None, :, :]) ** 2, axis=-1)
        K = _kernel(np.sqrt(d2), self.ring_px, self.decay_px)
        G = np.zeros((4, 4))  # (half, coordinate) x (half, coordinate) of one point
        for c in range(2):
            s_l, s_r = self.std[0, c], self.std[1, c]
            cross = self.rho_halves[c] * s_l * s_r
            G[c, c], G[2 + c, 2 + c] = s_l**2, s_r**2
            G[c, 2 + c] = G[2 + c, c] = cross
        n = q.shape[-2]
        cov = K[..., :, None, :, None] * G[:, None, :]
        return cov.reshape(*q.shape[:-2], 4 * n, 4 * n)

    def to_dict(self) -> dict[str, Any]:
        """Report fields: the misfit and noise per half and coordinate, px."""
        return {
            "misfit_std_px": self.std.tolist(),
            "misfit_rho_halves": self.rho_halves.tolist(),
            "misfit_kernel_px": [self.ring_px, self.decay_px],
            "misfit_noise_px": self.noise.tolist(),
        }


def fit_misfit(board_points, image, half, pixels, residuals) -> ModelMisfit | None:
    """The misfit field of a calibration's inlier residuals (see the module notes).

    Parameters
    ----------
    board_points : ndarray, shape (K, 3), mm
        Corners in the board frame (a square grid).
    image, half : ndarray, shape (K,), int
    pixels, residuals : ndarray, shape (K, 2), px
        Detected corners and their residuals.

    Returns
    -------
    ModelMisfit, or None when either half has fewer than
    :data:`~endomeasure.solvers.verdict.MIN_NEIGHBOUR_PAIRS` runs of three corners to
    measure its noise.
    """
    X = np.asarray(board_points, dtype=np.float64)
    image = np.asarray(image, dtype=np.int64)
    half = np.asarray(half, dtype=np.int64)
    q = np.asarray(pixels, dtype=np.float64)
    r = np.asarray(residuals, dtype=np.float64)
    total = np.zeros((2, 2))
    second = np.zeros((2, 2))
    runs = np.zeros(2, dtype=np.int64)
    for h in range(2):
        sel_h = half == h
        if not sel_h.any():
            return None
        total[h] = np.mean(r[sel_h] ** 2, axis=0)
        for i in np.unique(image[sel_h]):
            sel = np.flatnonzero(sel_h & (image == i))
            dd = second_differences(X[sel], r[sel])
            second[h] += np.sum(dd**2, axis=0)
            runs[h] += dd.shape[0]
    if np.any(runs < MIN_NEIGHBOUR_PAIRS):
        return None
    noise2 = np.minimum(second / (6.0 * runs[:, None]), total)
    std = np.sqrt(total - noise2)
    pairs = _pairs(X, image, half, q, r)
    ring, decay = _fitted_kernel(pairs, std)
    rho = _half_correlation(pairs, std, ring, decay)
    return ModelMisfit(std, rho, ring, decay, np.sqrt(noise2))


@dataclasses.dataclass
class _Pairs:
    """Residual products of corner pairs binned by pixel distance."""

    centres: np.ndarray  # (B,) px
    same_sum: np.ndarray  # (2, B, 2): half, bin, coordinate
    same_n: np.ndarray  # (2, B)
    cross_sum: np.ndarray  # (B, 2): left residual of one corner x right of another
    cross_n: np.ndarray  # (B,)


def _pairs(X, image, half, q, r) -> _Pairs:
    groups = []  # per image: (left pixels, left residuals, right pixels, right residuals,
    # left index of each right corner's twin)
    spacing = []
    for i in np.unique(image):
        views = []
        for h in range(2):
            sel = np.flatnonzero((image == i) & (half == h))
            views.append((X[sel, :2], q[sel], r[sel]))
        (xl, ql, rl), (xr, qr, rr) = views
        twin = _twins(xl, xr)
        groups.append((ql, rl, qr, rr, twin))
        for qq in (ql, qr):
            if qq.shape[0] > 1:
                d = np.linalg.norm(qq[:, None] - qq[None], axis=-1)
                np.fill_diagonal(d, np.inf)
                spacing.append(np.median(d.min(axis=1)))
    longest = max(
        (np.ptp(qq, axis=0).max() * math.sqrt(2) for g in groups for qq in (g[0], g[2])
         if qq.shape[0] > 1),
        default=1.0,
    )  # fmt: skip
    nearest = 0.5 * float(np.median(spacing)) if spacing else 1.0
    edges = np.geomspace(nearest, max(longest, 2 * nearest), COVARIOGRAM_BINS + 1)
    out = _Pairs(
        np.sqrt(edges[:-1] * edges[1:]),
        np.zeros((2, COVARIOGRAM_BINS, 2)),
        np.zeros((2, COVARIOGRAM_BINS)),
        np.zeros((COVARIOGRAM_BINS, 2)),
        np.zeros(COVARIOGRAM_BINS),
    )
    for ql, rl, qr, rr, twin in groups:
        for h, (qq, rr_h) in enumerate(((ql, rl), (qr, rr))):
            iu, ju = np.triu_indices(qq.shape[0], 1)
            b = _bin(np.linalg.norm(qq[iu] - qq[ju], axis=1), edges)
            ok = b >= 0
            np.add.at(out.same_sum[h], b[ok], rr_h[iu[ok]] * rr_h[ju[ok]])
            np.add.at(out.same_n[h], b[ok], 1)
        j_r = np.flatnonzero(twin >= 0)  # right corners seen in the left half too
        if j_r.size < 2:
            continue
        i_l = twin[j_r]
        a, c = np.meshgrid(np.arange(j_r.size), np.arange(j_r.size), indexing="ij")
        a, c = a[a != c], c[a != c]  # ordered pairs of different corners
        b = _bin(np.linalg.norm(ql[i_l[a]] - ql[i_l[c]], axis=1), edges)
        ok = b >= 0
        np.add.at(out.cross_sum, b[ok], rl[i_l[a[ok]]] * rr[j_r[c[ok]]])
        np.add.at(out.cross_n, b[ok], 1)
    return out


def _twins(xl: np.ndarray, xr: np.ndarray) -> np.ndarray:
    """For every right-half corner, the index of the left-half corner at the same board
    point, or -1."""
    twin = np.full(xr.shape[0], -1, dtype=np.int64)
    if xl.shape[0] == 0 or xr.shape[0] == 0:
        return twin
    d = np.linalg.norm(xr[:, None] - xl[None], axis=-1)
    best = d.argmin(axis=1)
    same = d[np.arange(xr.shape[0]), best] < 1e-6 * (1.0 + np.abs(xl).max())
    twin[same] = best[same]
    return twin


def _bin(d: np.ndarray, edges: np.ndarray) -> np.ndarray:
    b = np.searchsorted(edges, d, side="right") - 1
    return np.where((b >= 0) & (b < edges.size - 1), b, -1)


def _kernel(d: np.ndarray, ring: float, decay: float) -> np.ndarray:
    return j0(d / ring) * np.exp(-0.5 * (d / decay) ** 2)


def _fitted_kernel(pairs: _Pairs, std: np.ndarray) -> tuple[float, float]:
    """The kernel's ring and decay lengths that, scaled by each half's misfit variance,
    fit the covariogram best (weighted by pair counts)."""
    var = np.mean(std**2, axis=1)  # (2,) per half
    gamma = pairs.same_sum.mean(axis=2) / np.maximum(pairs.same_n, 1)  # (2, B)
    lengths = np.geomspace(pairs.centres[0] / 2, 2 * pairs.centres[-1], _LENGTH_CANDIDATES)
    if not np.any(var > 0):
        return float(pairs.centres[0]), float(pairs.centres[0])
    best, best_cost = (lengths[0], lengths[0]), np.inf
    for ring in lengths:
        for decay in lengths[lengths >= ring]:
            model = var[:, None] * _kernel(pairs.centres, ring, decay)[None]
            cost = float(np.sum(pairs.same_n * (gamma - model) ** 2))
            if cost < best_cost:
                best, best_cost = (float(ring), float(decay)), cost
    return best


def _half_correlation(pairs: _Pairs, std: np.ndarray, ring: float, decay: float) -> np.ndarray:
    """Correlation of a point's misfit in the two halves per coordinate: the least-squares
    amplitude of the kernel in the cross-half covariogram, over the halves' misfit std."""
    k = _kernel(pairs.centres, ring, decay)
    amplitude = k @ pairs.cross_sum / max(float(np.sum(pairs.cross_n * k**2)), 1e-300)
    scale = std[0] * std[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(scale > 0, amplitude / scale, 0.0)
    return np.clip(rho, -1.0, 1.0)
