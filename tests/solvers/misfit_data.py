"""Calibration residuals with a known split into noise and a smooth misfit field.

Seeded Gaussian noise, independent from corner to corner, plus a plane wave of random
phase per image (variance half its squared amplitude), on square boards placed at random
in both halves: the truth for solvers/misfit.py and the sessions that carry a misfit.
"""

from __future__ import annotations

import numpy as np

NOISE = 0.03
AMPLITUDE = 0.1  # px: field variance AMPLITUDE^2 / 2 per coordinate
WAVELENGTH = 240.0  # px
SPACING = 12.0  # px between neighbouring corners
GRID = 8


def board_residuals(rng, n_images=30, field_l=1.0, field_r=-0.5, shared=0.0):
    """Stacked (board_points, image, half, pixels, residuals) of ``n_images`` boards seen
    in both halves: the field times ``field_l`` / ``field_r`` in each half, independent noise
    of NOISE, and noise ``shared`` common to a corner's two views."""
    ij = np.stack(np.meshgrid(np.arange(GRID), np.arange(GRID)), -1).reshape(-1, 2)
    X = np.column_stack([ij * 1.0, np.zeros(len(ij))])
    direction = np.array([0.8, 0.6])
    out = {k: [] for k in ("X", "image", "half", "q", "r")}
    for i in range(n_images):
        origin = rng.uniform(20, 120, 2)
        phase = rng.uniform(0, 2 * np.pi, 2)
        common = rng.normal(0, shared, (len(ij), 2)) if shared else 0.0
        for h, scale in enumerate((field_l, field_r)):
            q = origin + SPACING * ij + (0 if h == 0 else 320)
            arg = 2 * np.pi * (q - (0 if h == 0 else 320)) @ direction / WAVELENGTH
            field = AMPLITUDE * np.sin(arg[:, None] + phase[None])
            r = scale * field + rng.normal(0, NOISE, (len(ij), 2)) + common
            for k, v in zip(out, (X, np.full(len(ij), i), np.full(len(ij), h), q, r),
                            strict=True):  # fmt: skip
                out[k].append(v)
    return [np.concatenate(v) for v in out.values()]
