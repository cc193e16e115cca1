"""The calibration's model misfit: what its residuals hold beyond noise, as a random field.

A model that describes the optics leaves residuals of pure noise, independent from corner
to corner. What it cannot describe is smooth over the field, so neighbouring corners share
it. The residuals of a calibration tell the two apart, per half and coordinate:

- **noise**: from the second differences along board rows and columns
  (:func:`~endomeasure.solvers.verdict.second_differences`), in which a smooth misfit
  cancels; its variance ``s^2``;
- **misfit**: the rest of the residual variance, ``m^2 = max(0, mean r^2 - s^2)``, with a
  correlation ``k(d) = J0(d / a) exp(-d^2 / 2 b^2)`` over the distance ``d`` of two points,
  per coordinate: for the u residuals ``d = sqrt(du^2 + (dv / t)^2)``, for the v residuals
  ``d = sqrt(dv^2 + (du / t)^2)`` (pixel separations ``du, dv``), each with its own ring
  ``a``, decay ``b`` and stretch ``t``. The stretch is what a misfit's pattern needs: a
  radial one (a scale or distortion error, the u error following u and the v error v)
  varies along its own coordinate and little across it (``t > 1``); a prism's misfit
  varies across the apex. ``a, b, t`` are fitted to the covariogram of residual pairs of
  one image half (the mean of ``r_i r_j`` over pairs at distance ``d``; noise does not enter
  it for different corners), ``t = 1`` (isotropic) among the candidates; the correlation
  of one point's misfit in the two halves comes from pairs of *different* corners across
  the halves (free even of noise the two views share, such as print errors).

Why this kernel: each board view's pose absorbs the mean and tilt of the misfit over the
board, so the residuals' covariogram falls below zero at about the board's radius (for
the pinhole pair on the default preset, to -0.46 of its variance at 70 px) before it fades;
a Gaussian cannot follow that and would understate the misfit of longer lengths.
``J0`` (a ring in the frequency plane) is a covariance in two dimensions, the Gaussian
too, and so their product is (Schur).

The misfit offsets of a measurement's points then have, per coordinate, the covariance
``K (x) H``: ``K_ij = k(d_ij)`` over the points' left-half pixels and
``H = [[m_L^2, c], [c, m_R^2]]`` between the halves; a Kronecker product of positive
semi-definite factors is one (a stretched distance is a Euclidean one in scaled
coordinates, so ``k`` stays a covariance), and the two coordinates are independent.
Close points share their misfit, which then cancels in a short length; farther apart, it
adds like noise.

The board poses of a calibration absorb the part of the misfit that a rigid motion of the
board explains. For lengths, areas and depths between points that part is a rigid motion
of the scene, which changes none of them: the misfit left in the residuals is what matters
to a measurement. For the absolute position of a single point it is a lower bound.
"""

from __future__ import annotations

import dataclasses
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
    ring_px, decay_px : ndarray, shape (2,), px
        The kernel's lengths ``a`` and ``b`` for the u and the v residuals (one number
        for both is accepted).
    noise : ndarray, shape (2, 2), px
        The residuals' noise per half and coordinate, ``sqrt(mean r^2 - m^2)``.
    stretch : ndarray, shape (2,)
        The kernel's stretch ``t`` across each coordinate (1: isotropic).
    """

    std: np.ndarray
    rho_halves: np.ndarray
    ring_px: np.ndarray
    decay_px: np.ndarray
    noise: np.ndarray
    stretch: np.ndarray = (1.0, 1.0)

    def __post_init__(self):
        for name in ("ring_px", "decay_px", "stretch"):
            object.__setattr__(self, name, np.broadcast_to(getattr(self, name), (2,)))
        shapes = {"std": (2, 2), "rho_halves": (2,), "noise": (2, 2), "ring_px": (2,),
                  "decay_px": (2,), "stretch": (2,)}  # fmt: skip
        for name, shape in shapes.items():
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"ModelMisfit.{name} must be finite of shape {shape}")
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        if np.any(self.std < 0) or np.any(np.abs(self.rho_halves) > 1):
            raise ValueError("ModelMisfit needs std >= 0 and |rho_halves| <= 1")
        for length in (self.ring_px, self.decay_px, self.stretch):
            if not np.all(length > 0):
                raise ValueError("ModelMisfit's kernel lengths and stretches must be positive")

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
        sep = np.abs(q[..., :, None, :] - q[..., None, :, :])  # (..., n, n, 2): du, dv
        n = q.shape[-2]
        cov = np.zeros((*q.shape[:-2], n, 4, n, 4))
        for c in range(2):
            d = _distance(sep[..., c], sep[..., 1 - c], self.stretch[c])
            K = _kernel(d, self.ring_px[c], self.decay_px[c])
            G = np.zeros((4, 4))  # (half, coordinate) x (half, coordinate) of one point
            s_l, s_r = self.std[0, c], self.std[1, c]
            G[c, c], G[2 + c, 2 + c] = s_l**2, s_r**2
            G[c, 2 + c] = G[2 + c, c] = self.rho_halves[c] * s_l * s_r
            cov += K[..., :, None, :, None] * G[:, None, :]
        return cov.reshape(*q.shape[:-2], 4 * n, 4 * n)

    def to_dict(self) -> dict[str, Any]:
        """Report fields: the misfit and noise per half and coordinate, px."""
        return {
            "misfit_std_px": self.std.tolist(),
            "misfit_rho_halves": self.rho_halves.tolist(),
            "misfit_kernel_px": [self.ring_px.tolist(), self.decay_px.tolist()],
            "misfit_kernel_stretch": self.stretch.tolist(),
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
    fits = [_fitted_kernel(pairs, std[:, c], c) for c in range(2)]
    ring, decay, stretch = (np.array(v) for v in zip(*fits, strict=True))
    rho = np.array([_half_correlation(pairs, std[:, c], c, *fits[c]) for c in range(2)])
    return ModelMisfit(std, rho, ring, decay, np.sqrt(noise2), stretch)


@dataclasses.dataclass
class _Pairs:
    """Residual products of corner pairs and their pixel separations."""

    sep: np.ndarray  # (P, 2) |du|, |dv| of same-half pairs, px
    half: np.ndarray  # (P,) their half
    product: np.ndarray  # (P, 2) r_i r_j per coordinate
    cross_sep: np.ndarray  # (Q, 2) left-pixel separations of cross-half pairs
    cross_product: np.ndarray  # (Q, 2): left residual of one corner x right of another
    nearest: float  # half the median spacing of neighbouring corners, px


def _pairs(X, image, half, q, r) -> _Pairs:
    seps, halves, products, cross_seps, cross_products, spacing = [], [], [], [], [], []
    for i in np.unique(image):
        views = []
        for h in range(2):
            sel = np.flatnonzero((image == i) & (half == h))
            views.append((X[sel, :2], q[sel], r[sel]))
        (xl, ql, rl), (xr, qr, rr) = views
        for h, (qq, rr_h) in enumerate(((ql, rl), (qr, rr))):
            if qq.shape[0] < 2:
                continue
            iu, ju = np.triu_indices(qq.shape[0], 1)
            seps.append(np.abs(qq[iu] - qq[ju]))
            halves.append(np.full(iu.size, h))
            products.append(rr_h[iu] * rr_h[ju])
            d = np.linalg.norm(qq[:, None] - qq[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            spacing.append(np.median(d.min(axis=1)))
        twin = _twins(xl, xr)
        j_r = np.flatnonzero(twin >= 0)  # right corners seen in the left half too
        if j_r.size < 2:
            continue
        i_l = twin[j_r]
        a, c = np.meshgrid(np.arange(j_r.size), np.arange(j_r.size), indexing="ij")
        a, c = a[a != c], c[a != c]  # ordered pairs of different corners
        cross_seps.append(np.abs(ql[i_l[a]] - ql[i_l[c]]))
        cross_products.append(rl[i_l[a]] * rr[j_r[c]])

    def joined(parts, shape):
        return np.concatenate(parts) if parts else np.zeros(shape)

    return _Pairs(
        joined(seps, (0, 2)), joined(halves, (0,)).astype(np.int64), joined(products, (0, 2)),
        joined(cross_seps, (0, 2)), joined(cross_products, (0, 2)),
        0.5 * float(np.median(spacing)) if spacing else 1.0,
    )  # fmt: skip


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


def _distance(along: np.ndarray, across: np.ndarray, stretch: float) -> np.ndarray:
    """The kernel's distance of a coordinate's residuals: their separation along the
    coordinate's own axis, and across it divided by the stretch."""
    return np.sqrt(along**2 + (across / stretch) ** 2)


STRETCHES = np.geomspace(1 / 8, 8, 13)
"""Candidate stretches of the kernel (1, isotropic, among them): from a misfit that
varies 8 times faster across its coordinate than along it to 8 times slower."""


def _fitted_kernel(pairs: _Pairs, std: np.ndarray, c: int) -> tuple[float, float, float]:
    """The ring, decay and stretch of coordinate ``c``'s kernel that, scaled by each
    half's misfit variance ``std**2`` (2,), fit the covariogram of the residual products
    best. The cost is the sum over pairs of ``(r_i r_j - m^2 k(d))^2`` less its constant
    part (binned by ``d``, log-spaced), so that stretches, which bin the pairs apart,
    compare on one scale."""
    var = std**2
    fallback = (pairs.nearest, pairs.nearest, 1.0)
    if not np.any(var > 0) or pairs.sep.shape[0] == 0:
        return fallback
    best, best_cost = fallback, np.inf
    for stretch in STRETCHES:
        d = _distance(pairs.sep[:, c], pairs.sep[:, 1 - c], stretch)
        edges = np.geomspace(pairs.nearest, max(d.max(), 2 * pairs.nearest) * (1 + 1e-9),
                             COVARIOGRAM_BINS + 1)  # fmt: skip
        b = _bin(d, edges)
        ok = b >= 0
        centres = np.sqrt(edges[:-1] * edges[1:])
        n = np.zeros((2, COVARIOGRAM_BINS))
        total = np.zeros((2, COVARIOGRAM_BINS))
        np.add.at(n, (pairs.half[ok], b[ok]), 1)
        np.add.at(total, (pairs.half[ok], b[ok]), pairs.product[ok, c])
        lengths = np.geomspace(centres[0] / 2, 2 * centres[-1], _LENGTH_CANDIDATES)
        # every (ring, decay) candidate at once: k[i, j, bin] for ring i and decay j
        k = (
            j0(centres / lengths[:, None])[:, None, :]
            * np.exp(-0.5 * (centres / lengths[:, None]) ** 2)[None, :, :]
        )
        cost = np.einsum("h,ijb,hb->ij", var**2, k**2, n) - 2 * np.einsum(
            "h,ijb,hb->ij", var, k, total
        )
        cost[np.tril_indices(lengths.size, -1)] = np.inf  # a decay shorter than its ring
        i, j = np.unravel_index(np.argmin(cost), cost.shape)  # the first best, ring-major
        if cost[i, j] < best_cost:
            best, best_cost = (float(lengths[i]), float(lengths[j]), float(stretch)), cost[i, j]
    return best


def _half_correlation(
    pairs: _Pairs, std: np.ndarray, c: int, ring: float, decay: float, stretch: float
) -> float:
    """Correlation of a point's misfit in the two halves for coordinate ``c``: the
    least-squares amplitude of its kernel in the cross-half products, over the halves'
    misfit std."""
    if pairs.cross_sep.shape[0] == 0 or std[0] * std[1] <= 0:
        return 0.0
    k = _kernel(_distance(pairs.cross_sep[:, c], pairs.cross_sep[:, 1 - c], stretch), ring, decay)
    amplitude = float(k @ pairs.cross_product[:, c]) / max(float(k @ k), 1e-300)
    return float(np.clip(amplitude / (std[0] * std[1]), -1.0, 1.0))
