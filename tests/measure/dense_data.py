"""A textured plane rendered through a known model: ground truth for the dense search.

Every pixel of both halves samples, at its centre ray, a smooth random texture on the
plane ``z = depth`` (sinusoids of 0.4-1.5 mm wavelength: 5-20 px at 18 mm for fx 230 px),
plus seeded Gaussian noise, quantised to 8 bits. The truth is the plane, never the code
under test.
"""

from __future__ import annotations

import numpy as np

from endomeasure.conventions import Half

NOISE_DN = 1.0


def render_plane(model, depth_mm: float, rng, noise_dn: float = NOISE_DN) -> np.ndarray:
    width, height = model.config.image_size
    split = model.config.split
    uu, vv = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    image = np.zeros((height, width))
    k = rng.uniform(2 * np.pi / 1.5, 2 * np.pi / 0.4, 24)
    angle = rng.uniform(0, np.pi, 24)
    phase = rng.uniform(0, 2 * np.pi, 24)
    for half in Half:
        mask = uu < split if half is Half.LEFT else uu >= split
        rays = model.rays(np.stack([uu[mask], vv[mask]], -1), half)
        t = (depth_mm - rays.origins[:, 2]) / rays.directions[:, 2]
        p = rays.origins + t[:, None] * rays.directions
        tex = sum(
            np.cos(kk * (np.cos(a) * p[:, 0] + np.sin(a) * p[:, 1]) + ph)
            for kk, a, ph in zip(k, angle, phase, strict=True)
        )
        image[mask] = np.nan_to_num(120.0 + 12.0 * tex, nan=0.0)
    image += rng.normal(0.0, noise_dn, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
