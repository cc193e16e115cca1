"""The simulator's own truth optics against physics and against the calibrated model's code.

Oracles: Snell's law as sines and coplanarity at each face, Fermat's principle on the
traced path, the closed-form pupil law, and the independent ``RaytraceModel`` on the
default preset (the two codes share nothing).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from endomeasure.conventions import Half, Status
from endomeasure.simulate.preset import Preset, load_preset
from endomeasure.simulate.truth_optics import LensMap

SNELL_TOL = 1e-12
"""Snell's law holds to rounding on unit vectors."""
FERMAT_STEP_MM = 1e-4
FERMAT_SLOPE_TOL = 1e-8
"""The optical path's slope against moving an entry/exit point along its face, 1 (mm per
mm): zero at the true path, O(step) from the curvature; a path off by 1e-3 rad gives ~1e-3."""
ROUND_TRIP_TOL_PX = 1e-9
CROSS_CHECK_TOL_PX = 1e-6
"""The truth optics and RaytraceModel aim rays to 1e-11 and 1e-8 px respectively."""


def _exotic_data() -> dict:
    """The default probe with every effect the calibrated models lack switched on."""
    data = copy.deepcopy(load_preset("default").data)
    lens = data["lens"]
    lens.update(distortion_direction="pixel_to_ray", k1=0.11, k2=0.015, k3=-0.002, k4=0.0004)
    lens.update(pupil_shift_mm=0.08, pupil_edge_deg=50.0, cx=331.0, cy=229.5)
    data["prism"]["left_face"]["offset_mm"] = 0.012
    data["prism"]["right_face"]["offset_mm"] = -0.009
    data["prism"]["rear_face"]["a_deg"] = 0.8
    return data


@pytest.fixture(scope="module")
def exotic() -> Preset:
    return Preset.from_dict(_exotic_data(), source="tests exotic")


@pytest.fixture(scope="module", params=["default", "exotic"])
def optics(request, exotic):
    return (
        load_preset("default").truth_optics if request.param == "default" else exotic.truth_optics
    )


def _half_pixels(optics, half, rng, n=400):
    width, height = optics.config.image_size
    split = optics.config.split
    lo, hi = (0.0, split - 1.0) if half is Half.LEFT else (float(split), width - 1.0)
    return np.stack([rng.uniform(lo, hi, n), rng.uniform(0, height - 1, n)], -1)


def _sin(a, b):
    return np.linalg.norm(np.cross(a, b), axis=-1)


@pytest.mark.parametrize("half", list(Half))
def test_snell_at_both_faces(optics, half, rng):
    x, y, ok = optics.lens.pixel_to_ideal(*_half_pixels(optics, half, rng).T)
    path = optics.trace_path(x[ok], y[ok], half)
    good = path.status == Status.OK
    assert good.sum() > 300
    n = optics.n_glass
    faces = [
        (path.lens_directions, path.glass_directions, optics.rear.normal, 1.0, n),
        (path.glass_directions, path.out_directions, optics.front(half).normal, n, 1.0),
    ]
    for d_in, d_out, normal, n_in, n_out in faces:
        d_in, d_out = d_in[good], d_out[good]
        np.testing.assert_allclose(
            n_in * _sin(d_in, normal), n_out * _sin(d_out, normal), atol=SNELL_TOL
        )
        coplanar = np.einsum("ij,ij->i", np.cross(d_in, d_out), np.broadcast_to(normal, d_in.shape))
        np.testing.assert_allclose(coplanar, 0.0, atol=SNELL_TOL)
        # transmitted, not reflected: same side of the face
        assert np.all(np.sign(d_in @ normal) == np.sign(d_out @ normal))
    # the entry and exit points lie on their faces
    np.testing.assert_allclose(
        path.rear_points[good] @ optics.rear.normal, optics.rear.d, atol=1e-12
    )
    front = optics.front(half)
    np.testing.assert_allclose(path.front_points[good] @ front.normal, front.d, atol=1e-12)


def _tangents(normal):
    a = np.cross(normal, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(normal, a)


@pytest.mark.parametrize("half", list(Half))
def test_traced_paths_are_stationary_in_optical_length(optics, half, rng):
    """Fermat: moving the entry or exit point along its face changes the optical path
    length from the pupil point to a far point of the ray only to second order."""
    x, y, ok = optics.lens.pixel_to_ideal(*_half_pixels(optics, half, rng, 60).T)
    path = optics.trace_path(x[ok], y[ok], half)
    good = np.flatnonzero(path.status == Status.OK)
    assert good.size > 40
    n = optics.n_glass
    end = path.front_points + 20.0 * path.out_directions

    def length(o, a, b, q):
        return np.linalg.norm(a - o) + n * np.linalg.norm(b - a) + np.linalg.norm(q - b)

    rear_t = _tangents(optics.rear.normal)
    front_t = _tangents(optics.front(half).normal)
    h = FERMAT_STEP_MM
    for i in good:
        o, a, b, q = path.lens_origins[i], path.rear_points[i], path.front_points[i], end[i]
        for t in rear_t:
            slope = (length(o, a + h * t, b, q) - length(o, a - h * t, b, q)) / (2 * h)
            assert abs(slope) < FERMAT_SLOPE_TOL
        for t in front_t:
            slope = (length(o, a, b + h * t, q) - length(o, a, b - h * t, q)) / (2 * h)
            assert abs(slope) < FERMAT_SLOPE_TOL
    # the oracle has teeth: with the exit point 0.05 mm off the true one the path is
    # not stationary against moving the entry point
    i = good[0]
    b = path.front_points[i] + 0.05 * front_t[0]
    slope = (
        length(path.lens_origins[i], path.rear_points[i] + h * rear_t[0], b, end[i])
        - length(path.lens_origins[i], path.rear_points[i] - h * rear_t[0], b, end[i])
    ) / (2 * h)
    assert abs(slope) > 1e3 * FERMAT_SLOPE_TOL


@pytest.mark.parametrize("half", list(Half))
def test_project_inverts_rays_to_1e_9_px(optics, half, rng):
    q = _half_pixels(optics, half, rng)
    rays = optics.rays(q, half)
    ok = rays.status == Status.OK
    assert ok.sum() > 300
    depth = rng.uniform(5.0, 80.0, ok.sum())
    points = rays.origins[ok] + depth[:, None] * rays.directions[ok]
    proj = optics.project(points, half)
    assert np.mean(proj.status == Status.OK) > 0.99
    good = proj.status == Status.OK
    err = np.abs(proj.pixels[good] - q[ok][good]).max()
    assert err < ROUND_TRIP_TOL_PX


def test_points_no_ray_of_a_half_reaches_are_not_ok(optics):
    width, height = optics.config.image_size
    # far outside any field, and behind the probe
    points = np.array([[500.0, 0.0, 10.0], [0.0, -900.0, 5.0], [0.0, 0.0, -10.0], [np.nan, 0, 1]])
    for half in Half:
        proj = optics.project(points, half)
        assert np.all(proj.status != Status.OK)
        assert np.all(np.isnan(proj.pixels))


def test_lens_maps_invert_each_other():
    lm = LensMap((-0.3, 0.08, -0.01, 0.001), 4e-4, -3e-4)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-1.0, 1.0, (2, 1000))
    keep = np.hypot(x, y) < 0.9 * lm.max_radius
    mx, my = lm.apply(x[keep], y[keep])
    bx, by, ok = lm.invert(mx, my)
    assert ok.all()
    np.testing.assert_allclose(np.stack([bx, by]), np.stack([x[keep], y[keep]]), atol=1e-14)


def test_pupil_moves_along_the_axis_with_the_field_angle(exotic):
    lens = exotic.truth_optics.lens
    theta = np.radians([0.0, 25.0, 50.0])
    x = np.tan(theta)
    o, d = lens.lens_rays(x, np.zeros(3))
    np.testing.assert_allclose(o[:, :2], 0.0)
    np.testing.assert_allclose(o[:, 2], 0.08 * (theta / np.radians(50.0)) ** 2, atol=1e-15)
    np.testing.assert_allclose(np.arccos(d[:, 2]), theta, atol=1e-12)


def test_steep_faces_give_total_internal_reflection():
    data = copy.deepcopy(load_preset("default").data)
    data["prism"]["left_face"]["a_deg"] = -60.0  # n sin(60 deg) > 1 for N-BK7
    optics = Preset.from_dict(data).truth_optics
    width, height = optics.config.image_size
    rays = optics.rays(np.array([[optics.config.split - 2.0, height / 2.0]]), Half.LEFT)
    assert rays.status[0] == Status.TOTAL_INTERNAL_REFLECTION
    assert np.all(np.isnan(rays.directions))


def test_apex_column_is_where_both_front_faces_meet_the_ray(optics):
    rows = np.array([150.0, 240.0, 330.0])  # the apex top and bottom rows are in TIR
    cols = optics.apex_columns(rows)
    assert np.all(np.isfinite(cols))
    x, y, ok = optics.lens.pixel_to_ideal(cols, rows)
    for half in Half:
        path = optics.trace_path(x, y, half)
        other = optics.front(Half.RIGHT if half is Half.LEFT else Half.LEFT)
        # the exit point through either face lies on the other face too
        np.testing.assert_allclose(path.front_points @ other.normal, other.d, atol=1e-8)


def test_default_agrees_with_the_raytrace_model_over_the_field(default_preset, rng):
    """Two independent codes, the same physics: the default preset is representable."""
    assert default_preset.raytrace_representable
    optics, model = default_preset.truth_optics, default_preset.truth_model
    assert optics.config.split == model.config.split
    checked = 0
    for half in Half:
        q = _half_pixels(optics, half, rng, 1500)
        a, b = optics.rays(q, half), model.rays(q, half)
        np.testing.assert_array_equal(a.status, b.status)
        ok = a.status == Status.OK
        np.testing.assert_allclose(a.directions[ok], b.directions[ok], atol=1e-11)
        np.testing.assert_allclose(a.origins[ok], b.origins[ok], atol=1e-11)
        depth = rng.uniform(8.0, 50.0, ok.sum())
        points = a.origins[ok] + depth[:, None] * a.directions[ok]
        pa, pb = optics.project(points, half), model.project(points, half)
        both = (pa.status == Status.OK) & (pb.status == Status.OK)
        assert both.mean() > 0.99
        assert np.abs(pa.pixels[both] - pb.pixels[both]).max() < CROSS_CHECK_TOL_PX
        checked += both.sum()
        # points anywhere in front of the probe: the two codes find the same ones
        anywhere = rng.uniform(-30.0, 30.0, (600, 3)) + np.array([0.0, 0.0, 35.0])
        pa, pb = optics.project(anywhere, half), model.project(anywhere, half)
        np.testing.assert_array_equal(pa.status == Status.OK, pb.status == Status.OK)
        assert (pa.status == Status.OK).sum() > 100
    assert checked > 2500


def test_exotic_preset_is_not_representable_and_keeps_an_approximate_seed(exotic):
    assert not exotic.raytrace_representable
    truth = exotic.truth_model.named_params()
    assert truth["k1"] == pytest.approx(0.11)  # the same numbers, without the extra effects
    assert truth["n_glass"] == exotic.truth_optics.n_glass


def test_a_moving_pupil_is_the_raytrace_models_e1(rng):
    """The truth's pupil law ``z = shift (theta / theta_edge)^2`` is the model's
    ``e1 theta^2``: with the pupil moving, the two codes still agree."""
    data = copy.deepcopy(load_preset("default").data)
    data["lens"].update(pupil_shift_mm=0.08, pupil_edge_deg=50.0)
    preset = Preset.from_dict(data)
    assert preset.raytrace_representable
    optics, model = preset.truth_optics, preset.truth_model
    for half in Half:
        q = _half_pixels(optics, half, rng, 300)
        a = optics.rays(q, half)
        ok = a.status == Status.OK
        points = a.origins[ok] + 20.0 * a.directions[ok]
        pa, pb = optics.project(points, half), model.project(points, half)
        both = (pa.status == Status.OK) & (pb.status == Status.OK)
        assert both.sum() > 250
        assert np.abs(pa.pixels[both] - pb.pixels[both]).max() < CROSS_CHECK_TOL_PX
