"""bench/texture_bound.py's window energy against a least-squares fit of each window."""

from __future__ import annotations

import numpy as np
import pytest
from tests.bench.bench_scripts import load_bench_script

texture = load_bench_script("texture_bound.py", "bench_texture_bound")
WINDOW = 7


@pytest.fixture(scope="module")
def field():
    rng = np.random.default_rng(5)
    g = rng.normal(size=(24, 30))
    mask = rng.random(g.shape) > 0.2  # some pixels without a true match
    return g, mask


def _direct(g, mask, row, col):
    """The residual energy of g over one window after its own least-squares plane."""
    r = WINDOW // 2
    rows, cols = np.mgrid[row - r : row + r + 1, col - r : col + r + 1]
    keep = mask[rows, cols]
    design = np.stack([np.ones(keep.sum()), cols[keep], rows[keep]], axis=1).astype(float)
    values = g[rows, cols][keep]
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    return float(np.sum((values - design @ coef) ** 2)), int(keep.sum())


@pytest.mark.parametrize(("row", "col"), [(10, 12), (3, 3), (20, 26)])
def test_the_detrended_energy_is_each_windows_residual_about_its_plane(field, row, col):
    g, mask = field
    energy, n = texture.detrended_energy(g, mask, WINDOW)
    expected, count = _direct(g, mask, row, col)
    assert n[row, col] == pytest.approx(count)
    assert energy[row, col] == pytest.approx(expected, rel=1e-8)


def test_a_plane_leaves_no_energy(field):
    _, mask = field
    rows, cols = np.mgrid[0:24, 0:30].astype(float)
    energy, _ = texture.detrended_energy(2.0 + 0.3 * cols - 0.7 * rows, mask, WINDOW)
    assert np.max(energy[5:-5, 5:-5]) < 1e-8
