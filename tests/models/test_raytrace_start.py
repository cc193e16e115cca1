"""The raytrace start's pieces against independent truth (the whole chain on random
designs is ``tests/solvers/test_calibrate_designs.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from tests.conftest import make_raytrace_model

from endomeasure.conventions import Half, Status
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.models.raytrace import DEFAULT_GLASS_INDEX
from endomeasure.models.raytrace_start import (
    GLASS_CANDIDATES,
    _exit_angle,
    _glasses,
    _ray_fit,
)
from endomeasure.models.start import Observations, StartContext

GLASS_RANGE = (1.45, 1.95)  # fused silica to the densest flints of prism catalogues
EXACT_RAY_PX = 1e-6  # exact points: the ray fit is limited by its tolerances only


def test_exit_angle_obeys_snell_at_both_faces():
    """The 2-D trace against Snell's law written as sines at each face."""
    checked = 0
    for alpha, tilt, n in [(0.1, -0.5, 1.5), (-0.3, 0.4, 1.8), (0.0, 0.2, 1.46)]:
        beta = _exit_angle(alpha, tilt, n)
        inside = math.asin(math.sin(alpha) / n)  # rear face perpendicular to the axis
        # front face normal at angle `tilt`: n sin(inside - tilt) = sin(beta - tilt)
        assert n * math.sin(inside - tilt) == pytest.approx(math.sin(beta - tilt), abs=1e-12)
        checked += 1
    assert checked == 3


def _ctx(values=None, fixed=frozenset()):
    model = make_raytrace_model()
    config = model.config.with_fixed(fixed)
    empty = Observations((), (), *(np.zeros(0, dtype=t) for t in (np.int64, np.int8, np.int64)),
                         np.zeros((0, 3)), np.zeros((0, 2)))  # fmt: skip
    return StartContext(empty, config, dict(values or {}), None, None)


def test_glass_candidates_cover_prism_glasses():
    glasses = _glasses(_ctx())
    assert glasses == GLASS_CANDIDATES
    assert min(glasses) <= GLASS_RANGE[0] + 0.02 and max(glasses) >= GLASS_RANGE[1] - 0.02
    # every catalogue index lies within half a spacing of a candidate
    spacing = max(np.diff(sorted(glasses)))
    for n in np.linspace(*GLASS_RANGE, 51):
        assert min(abs(n - g) for g in glasses) <= 0.5 * spacing + 1e-12


def test_a_given_or_fixed_glass_is_the_only_one_tried():
    assert _glasses(_ctx({"n_glass": 1.7})) == (1.7,)
    assert _glasses(_ctx(fixed=frozenset({"n_glass"}))) == (DEFAULT_GLASS_INDEX,)
    assert _glasses(_ctx({"n_glass": 1.6}, frozenset({"n_glass"}))) == (1.6,)


def _exact_points(truth, R, t):
    """Pixels of both halves and, for each, a point on its truth ray at 10-40 mm, in a
    frame where the lens sits at ``T_lens_frame = (R, t)`` (as the pinhole pair places
    corners in its left virtual frame)."""
    width, height = truth.config.image_size
    rows = []
    for half in Half:
        lo, hi = (0, truth.config.split) if half is Half.LEFT else (truth.config.split, width)
        u, v = np.meshgrid(np.linspace(lo + 10, hi - 10, 8), np.linspace(20, height - 20, 6))
        q = np.stack([u.ravel(), v.ravel()], -1)
        rays = truth.rays(q, half)
        ok = rays.status == Status.OK
        depth = np.linspace(10.0, 40.0, int(ok.sum()))
        s = (depth - rays.origins[ok, 2]) / rays.directions[ok, 2]
        P_lens = rays.origins[ok] + s[:, None] * rays.directions[ok]
        rows.append((q[ok], np.full(int(ok.sum()), int(half)), (P_lens - t) @ R))
    q, h, P = (np.concatenate(a) for a in zip(*rows, strict=True))
    n = q.shape[0]
    obs = Observations(("all",), ("all",), np.zeros(n, dtype=np.int64), h.astype(np.int8),
                       np.arange(n), P, q)  # fmt: skip
    return obs, P


def test_ray_fit_recovers_the_truth_and_the_frame():
    """Exact points on the truth's rays, seen from an unknown frame: the backward fit
    from a perturbed model and frame returns the truth (n held at its value)."""
    truth = make_raytrace_model(cx=323.0, k1=-0.1, left_a=-0.33, right_a=0.30, rear_d=0.7)
    R_true = rotation_matrix(np.array([0.01, -0.03, 0.002]))
    t_true = np.array([0.2, -0.05, 0.1])
    obs, P = _exact_points(truth, R_true, t_true)
    assert obs.image.size > 80
    fixed = frozenset({"k3", "p1", "p2", "n_glass"})
    start = truth.with_config(fixed=fixed).with_values(
        {"fx": 236.0, "cx": 318.0, "k1": -0.08, "left_a": -0.31, "right_a": 0.32, "rear_d": 0.6}
    )
    R0 = rotation_matrix(np.array([0.0, -0.02, 0.0]))
    fitted, R, t, rms = _ray_fit(start, R0, np.zeros(3), obs, P, 200)
    assert rms < EXACT_RAY_PX
    np.testing.assert_allclose(R, R_true, atol=1e-7)
    np.testing.assert_allclose(t, t_true, atol=1e-6)
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "left_a", "right_a", "rear_d"):
        tol = 1e-5 if fitted.unit(name) == "px" else 1e-6
        assert getattr(fitted, name) == pytest.approx(getattr(truth, name), abs=tol), name
