"""The contract every camera model fulfils, run on each registered model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from endomeasure.conventions import Half, Status
from endomeasure.models import MODELS, model_from_dict
from endomeasure.models.base import ParamBatch

ROUND_TRIP_TOL_PX = 1e-6  # SPEC 4.2: iterative inverses must agree to < 1e-6 px
MIN_VALID_FRACTION = 0.95
DEPTHS_MM = (8.0, 10.0, 20.0, 45.0, 60.0)


def _half_grid(model, half, n_u=48, n_v=36):
    width, height = model.config.image_size
    edge = model.config.split - 0.5
    lo, hi = (-0.5, edge) if half is Half.LEFT else (edge, width - 0.5)
    pad = 1e-6  # stay strictly inside the half's pixel rectangle
    uu, vv = np.meshgrid(
        np.linspace(lo + pad, hi - pad, n_u), np.linspace(-0.5, height - 0.5 - pad, n_v)
    )
    return np.stack([uu, vv], axis=-1)


def _points_at_depth(rays, depth):
    s = (depth - rays.origins[..., 2]) / rays.directions[..., 2]
    return rays.origins + s[..., None] * rays.directions


@pytest.mark.parametrize("half", list(Half))
def test_project_inverts_rays_on_a_dense_grid(any_model, half):
    q = _half_grid(any_model, half)
    rays = any_model.rays(q, half)
    checked = 0
    for depth in DEPTHS_MM:
        proj = any_model.project(_points_at_depth(rays, depth), half)
        valid = proj.status == Status.OK
        assert valid.mean() >= MIN_VALID_FRACTION, (depth, np.bincount(proj.status.ravel()))
        err = np.linalg.norm(proj.pixels[valid] - q[valid], axis=-1)
        assert err.max() < ROUND_TRIP_TOL_PX, depth
        checked += valid.sum()
    assert checked > 5 * 0.95 * q[..., 0].size


@pytest.mark.parametrize("shape", [(), (1,), (7,), (4, 5)])
def test_batch_shapes(any_model, shape, rng):
    points = np.stack(
        [rng.uniform(-3, 3, shape), rng.uniform(-3, 3, shape), rng.uniform(15, 30, shape)], axis=-1
    )
    proj = any_model.project(points, "left")
    assert proj.pixels.shape == (*shape, 2) and proj.status.shape == shape
    pixels = np.stack([rng.uniform(50, 250, shape), rng.uniform(50, 400, shape)], axis=-1)
    rays = any_model.rays(pixels, Half.LEFT)
    assert rays.origins.shape == (*shape, 3) and rays.directions.shape == (*shape, 3)
    assert rays.status.shape == shape
    np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=-1), 1.0, atol=1e-14)


def test_named_views_and_dict_round_trip(any_model):
    cls = type(any_model)
    assert MODELS[cls.NAME] is cls
    assert len(any_model.params) == len(cls.PARAM_NAMES)
    for i, name in enumerate(cls.PARAM_NAMES):
        assert getattr(any_model, name) == any_model.params[i]
    for group, sl in cls.GROUPS.items():
        view = getattr(any_model, group)
        np.testing.assert_array_equal(view, any_model.params[sl])
        with pytest.raises(ValueError):
            view[0] = 1.0  # read-only
    with pytest.raises(ValueError):
        any_model.params[0] = 1.0
    back = model_from_dict(json.loads(json.dumps(any_model.to_dict())))
    assert type(back) is cls and back.config == any_model.config
    np.testing.assert_array_equal(back.params, any_model.params)
    changed = any_model.with_params(any_model.params * 1.001)
    assert changed.config == any_model.config and changed.params[0] != any_model.params[0]


def test_bad_input_gives_status_never_an_exception(any_model):
    points = np.array(
        [
            [np.nan, 0.0, 20.0],
            [0.0, np.inf, 20.0],
            [0.0, 0.0, -20.0],  # behind the probe
            [0.5, 0.3, 0.01],  # inside the probe, before the prism
            [400.0, 0.0, 10.0],  # far outside the field
            [-400.0, 50.0, 10.0],
        ]
    )
    for half in Half:
        proj = any_model.project(points, half)
        assert proj.status[0] == proj.status[1] == Status.INVALID_INPUT
        assert proj.status[2] == Status.BEHIND
        assert np.all(proj.status[3:] != Status.OK)
        assert np.all(np.isnan(proj.pixels))
    pixels = np.array([[np.nan, 10.0], [100.0, 100.0], [500.0, 100.0], [100.0, 600.0], [-3.0, 5.0]])
    rays = any_model.rays(pixels, "right")
    np.testing.assert_array_equal(
        rays.status, [Status.INVALID_INPUT, Status.OUTSIDE_HALF, Status.OK, Status.OUTSIDE_HALF,
                      Status.OUTSIDE_HALF],
    )  # fmt: skip
    assert np.all(np.isnan(rays.origins[rays.status != Status.OK]))


def test_every_ok_projection_is_right(any_model, rng):
    """Random points anywhere in front of the probe: whatever the model calls OK must map
    back onto the point (no wrong-but-plausible pixels at the edges of the field)."""
    n = 4000
    points = np.stack(
        [rng.uniform(-80, 80, n), rng.uniform(-80, 80, n), rng.uniform(0.5, 70, n)], axis=-1
    )
    checked = 0
    for half in Half:
        proj = any_model.project(points, half)
        ok = proj.status == Status.OK
        rays = any_model.rays(proj.pixels[ok], half)
        assert np.all(rays.status == Status.OK)
        # distance of each point from the ray of its pixel
        rel = points[ok] - rays.origins
        along = np.sum(rel * rays.directions, axis=-1)
        miss = np.linalg.norm(rel - along[:, None] * rays.directions, axis=-1)
        assert np.all(along > 0)
        assert miss.max() < 1e-7 * np.maximum(1.0, along).max()
        checked += ok.sum()
    assert checked > 500


JACOBIAN_REL_TOL = 1e-6  # central differences with a 1e-4 mm step are good to ~1e-8 here


@pytest.mark.parametrize("half", list(Half))
def test_point_jacobian_matches_central_differences(any_model, half, rng):
    n = 300
    z = rng.uniform(8, 60, n)
    sign = -1.0 if half is Half.LEFT else 1.0
    points = np.stack([sign * rng.uniform(0, 0.6, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
    jac = any_model.project_jacobian(points, half)
    plain = any_model.project(points, half)
    np.testing.assert_array_equal(jac.status, plain.status)
    ok = jac.status == Status.OK
    assert ok.sum() > 200
    np.testing.assert_allclose(jac.pixels[ok], plain.pixels[ok], atol=1e-12, rtol=0)
    h = 1e-4
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        numeric = (any_model.project(points + step, half).pixels
                   - any_model.project(points - step, half).pixels) / (2 * h)  # fmt: skip
        scale = np.abs(jac.dq_dp[ok]).max()
        np.testing.assert_allclose(jac.dq_dp[ok][:, :, axis], numeric[ok],
                                   atol=JACOBIAN_REL_TOL * scale, rtol=0)  # fmt: skip
    assert jac.dq_dp.shape == (n, 2, 3)


PER_ROW_TOL = 1e-12
"""Rays traced with a parameter vector per pixel must equal those of the model built
from that vector: the same arithmetic, only batched (mm and unit-direction units)."""


def _perturbed_params(model, rng, k):
    """``k`` parameter vectors near the model's: relative 1e-3 steps on every parameter,
    and also the distortion terms a calibration usually holds at zero."""
    scale = np.maximum(np.abs(model.params), 1e-2)
    return model.params + 1e-3 * scale * rng.standard_normal((k, model.params.size))


@pytest.mark.parametrize("half", list(Half))
def test_rays_with_a_parameter_vector_per_pixel_equal_each_models_rays(any_model, half, rng):
    q = _half_grid(any_model, half, 6, 5).reshape(-1, 2)
    params = _perturbed_params(any_model, rng, q.shape[0])
    batched = any_model.rays(q, half, params)
    assert np.all(batched.status == Status.OK)
    # the same vectors as a table and an index per pixel (each used twice)
    table = ParamBatch(params[::2], np.arange(q.shape[0]) // 2)
    twice = any_model.rays(q, half, table)
    np.testing.assert_array_equal(twice.status, Status.OK)
    for i in range(q.shape[0]):
        own = any_model.with_params(params[i]).rays(q[i], half)
        np.testing.assert_allclose(batched.origins[i], own.origins, rtol=0, atol=PER_ROW_TOL)
        np.testing.assert_allclose(batched.directions[i], own.directions, rtol=0, atol=PER_ROW_TOL)
        shared = any_model.with_params(params[i - i % 2]).rays(q[i], half)
        np.testing.assert_allclose(twice.directions[i], shared.directions, rtol=0, atol=PER_ROW_TOL)


def test_invalid_parameter_vectors_are_refused_per_pixel(any_model, rng):
    q = _half_grid(any_model, Half.LEFT, 2, 2).reshape(-1, 2)
    params = np.repeat(any_model.params[None], q.shape[0], axis=0)
    bad_focal = [i for i, n in enumerate(any_model.PARAM_NAMES) if n.endswith("fx")][0]
    params[1, bad_focal] = -1.0
    params[2, 0] = np.nan
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        any_model.with_params(params[1])
    np.testing.assert_array_equal(any_model.valid_params(params), [True, False, False, True])
    rays = any_model.rays(q, Half.LEFT, params)
    np.testing.assert_array_equal(
        rays.status, [Status.OK, Status.INVALID_INPUT, Status.INVALID_INPUT, Status.OK]
    )
    assert np.all(np.isnan(rays.origins[1:3]))
    with pytest.raises(ValueError, match="params must have shape"):
        any_model.rays(q, Half.LEFT, params[:2])


def test_every_parameter_has_a_unit(any_model):
    units = {any_model.unit(name) for name in any_model.PARAM_NAMES}
    assert units <= {"px", "mm", "rad", "1"}
    assert len(units) >= 3
    with pytest.raises(KeyError):
        any_model.unit("no_such_parameter")


def test_the_registered_start_chain_is_complete():
    from endomeasure.models import model_start

    for name, cls in MODELS.items():
        assert callable(model_start(name))
        assert cls.SEEDED_FROM is None or cls.SEEDED_FROM in MODELS
