"""Supersampling pattern, apex image and the cached ray bundles."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half
from endomeasure.simulate.optics import Region, apex_columns, ray_bundle, sample_offsets

FLOAT32_RAY_TOL = 1e-5
"""Bundles are float32: directions and origins (mm, about 2) agree to ~1e-7 relative."""


@pytest.mark.parametrize("n", [1, 2, 4, 5])
def test_sample_pattern_is_centred_symmetric_and_n_rooks(n):
    offsets = sample_offsets(n)
    assert offsets.shape == (n * n, 2)
    np.testing.assert_allclose(offsets.mean(axis=0), 0.0, atol=1e-15)
    # point symmetry about the pixel centre: the set equals its mirror image
    mirrored = -offsets
    d = np.linalg.norm(offsets[:, None] - mirrored[None], axis=-1)
    assert d.min(axis=1).max() < 1e-12
    # every sample has its own column and row of the n^2 x n^2 sub-grid
    for axis in (0, 1):
        assert len(np.unique(np.round(offsets[:, axis], 12))) == n * n
    assert offsets.min() > -0.5 and offsets.max() < 0.5


def test_apex_columns_mark_where_the_exit_face_changes(default_preset):
    model = default_preset.truth_optics
    rows = np.array([10.0, 240.0, 470.0])
    cols = apex_columns(model, rows)
    assert np.all(np.isfinite(cols))
    # the apex line is tilted only slightly (face b tilts of a tenth of a degree)
    assert np.ptp(cols) < 3.0


def test_bundle_rays_are_the_truth_optics_rays(default_preset):
    model = default_preset.truth_optics
    split = model.config.split
    region = Region(split - 3, 200, split + 3, 203)
    n = default_preset.supersampling
    bundle = ray_bundle(model, region, n)
    offsets = sample_offsets(n)
    checked = 0
    for r in range(region.height):
        for c in range(region.width):
            u, v = region.u0 + c, region.v0 + r
            half = Half.LEFT if u < split else Half.RIGHT
            rays = model.rays(np.array([u, v]) + offsets, half)
            ok = rays.status == 0
            np.testing.assert_array_equal(bundle.valid[r, c], ok)
            o = bundle.origins[:, r, c].T[ok]
            d = bundle.directions[:, r, c].T[ok]
            np.testing.assert_allclose(o, rays.origins[ok], atol=FLOAT32_RAY_TOL)
            np.testing.assert_allclose(d, rays.directions[ok], atol=FLOAT32_RAY_TOL)
            checked += ok.sum()
    assert checked > 200
    # the second request is served from the cache
    assert ray_bundle(model, region, n) is bundle
