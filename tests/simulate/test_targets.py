"""The metal cylinder's pits: exact depth, exact intersections, the plain cylinder elsewhere.

The oracle is the closed form of the pitted surface, written here on its own: the
cylinder ``rho = r`` about the axis ``x = 0, z = r`` (surface frame) pressed in along the
inward normal by the bowl ``h = depth (1 - (q / radius)^2)^2`` (``q`` the distance from
the pit centre in arc length and height).
"""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half, Status
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.simulate.optics import Region
from endomeasure.simulate.scenes import Shot
from endomeasure.simulate.targets import MetalCylinder, target_from_preset
from endomeasure.simulate.truth import image_truth, true_depth

DEPTH_TOL_MM = 1e-9
"""A pit seen head-on along its normal is deeper than the cylinder by its depth to this
(the intersection converges to 1e-10 mm; the rest is float64 rounding at 20 mm)."""
SURFACE_TOL_MM = 1e-9
"""Hit points satisfy the surface equation ``F = rho - r + h = 0`` to this; ``|grad F|
>= 1``, so it bounds their distance from the surface."""
FLOAT32_DEPTH_TOL_MM = 4e-6
"""``true_depth`` returns float32: 2 ulp of a depth near 20 mm."""
NORMAL_TOL = 1e-6
"""Returned normal vs the cross product of central differences (step 1e-5 mm) of the
closed-form surface: the differences' truncation and rounding error."""
FIRST_ROOT_SAMPLES = 400
"""Points along each ray before its hit where the surface function must stay positive
(the hit is the first crossing, not a later one through the far wall)."""


def _cylinder(pits=(), R=None, t=(0.3, -0.2, 20.0)) -> MetalCylinder:
    spec = {
        "kind": "cylinder", "radius_mm": 25.0, "albedo": 0.45, "texture_contrast": 0.35,
        "specular": 0.35, "shininess": 18.0, "texture_seed": 7, "mark_radius_mm": 0.2,
        "mark_albedo": 0.05, "marks_mm": [[-3.0, -2.5], [2.5, -3.0], [0.5, 0.5]],
    }  # fmt: skip
    if len(pits):
        spec["pits_mm"] = np.asarray(pits).tolist()
    base = target_from_preset("metal", spec)
    R = rotation_matrix(np.array([0.12, -0.2, 0.3])) if R is None else R
    return base.with_pose(R, np.asarray(t, dtype=np.float64))


def _random_pits(rng, n: int) -> np.ndarray:
    """Pits 0.5-1.5 mm wide and 0.2-0.5 mm deep, apart from each other (by rejection)."""
    pits: list[np.ndarray] = []
    while len(pits) < n:
        s, y = rng.uniform(-3.0, 3.0, 2)
        radius, depth = rng.uniform(0.5, 1.5), rng.uniform(0.2, 0.5)
        if all(np.hypot(s - p[0], y - p[1]) > radius + p[2] for p in pits):
            pits.append(np.array([s, y, radius, depth]))
    return np.array(pits)


# ----- the closed form (surface frame), independent of the code under test ---------------


def _bowl(pits: np.ndarray, s: np.ndarray, y: np.ndarray) -> np.ndarray:
    h = np.zeros(np.shape(s))
    for s0, y0, radius, depth in pits:
        q2 = ((s - s0) ** 2 + (y - y0) ** 2) / radius**2
        h += np.where(q2 < 1.0, depth * (1.0 - q2) ** 2, 0.0)
    return h


def _surface_point(r: float, pits: np.ndarray, s, y) -> np.ndarray:
    """Surface-frame point of the pitted surface at arc length s, height y, (..., 3)."""
    phi = np.asarray(s) / r
    rho = r - _bowl(pits, s, y)
    return np.stack([rho * np.sin(phi), np.asarray(y) + 0 * phi, r - rho * np.cos(phi)], -1)


def _to_surface(cyl: MetalCylinder, p: np.ndarray) -> np.ndarray:
    return (p - cyl.t) @ cyl.R


def _surface_function(cyl: MetalCylinder, p: np.ndarray) -> np.ndarray:
    """``rho - r + h`` at camera-frame points (..., 3): zero on the surface, > 0 outside."""
    x, y, z = np.moveaxis(_to_surface(cyl, p), -1, 0)
    r = cyl.radius_mm
    s = r * np.arctan2(x, r - z)
    return np.hypot(x, z - r) - r + _bowl(cyl.pits, s, y)


def _outward_normal(r: float, s) -> np.ndarray:
    phi = np.asarray(s) / r
    return np.stack([np.sin(phi), 0 * phi, -np.cos(phi)], -1)


def _hit(cyl: MetalCylinder, o: np.ndarray, d: np.ndarray):
    hit = cyl.hit(tuple(o.T.copy()), tuple(d.T.copy()))
    return hit, np.stack(np.broadcast_arrays(*hit.normal), -1)


def _fan(rng, cyl: MetalCylinder, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from near the probe towards points around the pits (up to 1.4 radii out)."""
    k = rng.integers(0, len(cyl.pits), n)
    reach = rng.uniform(0.0, 1.4, n) * cyl.pits[k, 2]
    angle = rng.uniform(0.0, 2 * np.pi, n)
    s = cyl.pits[k, 0] + reach * np.cos(angle)
    y = cyl.pits[k, 1] + reach * np.sin(angle)
    aim = _surface_point(cyl.radius_mm, np.zeros((0, 4)), s, y) @ cyl.R.T + cyl.t
    o = rng.uniform([-2.5, -2.5, 0.0], [2.5, 2.5, 2.0], (n, 3))
    d = aim - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


# ----- tests ------------------------------------------------------------------------------


def test_pit_centre_seen_along_its_normal_is_exactly_depth_deeper(rng):
    pits = _random_pits(rng, 4)
    plain, pitted = _cylinder(), _cylinder(pits)
    r = plain.radius_mm
    centre = _surface_point(r, np.zeros((0, 4)), pits[:, 0], pits[:, 1]) @ plain.R.T + plain.t
    normal = _outward_normal(r, pits[:, 0]) @ plain.R.T
    for standoff in (4.0, 12.0, 21.5):
        o = centre + standoff * normal
        hit_plain, _ = _hit(plain, o, -normal)
        hit_pit, n_pit = _hit(pitted, o, -normal)
        np.testing.assert_allclose(hit_plain.t, standoff, atol=DEPTH_TOL_MM, rtol=0)
        np.testing.assert_allclose(hit_pit.t - hit_plain.t, pits[:, 3], atol=DEPTH_TOL_MM, rtol=0)
        # the bowl is flat at its centre: the normal there is the cylinder's
        np.testing.assert_allclose(n_pit, normal, atol=DEPTH_TOL_MM)
    np.testing.assert_allclose(
        pitted.pit_bottoms_camera, centre - pits[:, 3:] * normal, atol=DEPTH_TOL_MM, rtol=0
    )


def test_true_depth_of_a_pit_seen_head_on_through_the_truth_optics(default_preset):
    """Pose the part so that one pixel's ray runs along a pit's normal into its centre."""
    optics = default_preset.truth_optics
    u, v, along = 190, 230, 19.0
    ray = optics.rays(np.array([[u, v]], dtype=np.float64), Half.LEFT)
    assert ray.status[0] == Status.OK
    o, d = ray.origins[0], ray.directions[0]
    pit = np.array([[0.7, -0.4, 1.1, 0.35]])
    r = 25.0
    n_surface = _outward_normal(r, pit[0, 0])
    axis = np.cross(n_surface, -d)
    angle = np.arctan2(np.linalg.norm(axis), n_surface @ -d)
    R = rotation_matrix(axis / np.linalg.norm(axis) * angle)
    centre = _surface_point(r, np.zeros((0, 4)), pit[0, 0], pit[0, 1])
    t = o + along * d - R @ centre
    region = Region(u, v, u + 1, v + 1)
    plain = true_depth(default_preset, _cylinder(R=R, t=t), region)[0, 0]
    pitted = true_depth(default_preset, _cylinder(pit, R=R, t=t), region)[0, 0]
    assert abs(plain - (o[2] + along * d[2])) <= FLOAT32_DEPTH_TOL_MM
    assert abs(pitted - (o[2] + (along + pit[0, 3]) * d[2])) <= FLOAT32_DEPTH_TOL_MM


def test_hits_lie_on_the_pitted_surface_and_are_the_first_crossing(rng):
    cyl = _cylinder(_random_pits(rng, 3))
    plain = _cylinder()
    o, d = _fan(rng, cyl, 3000)
    hit, _ = _hit(cyl, o, d)
    t_plain = _hit(plain, o, d)[0].t
    assert hit.hit.all()
    p = o + hit.t[:, None] * d
    assert np.max(np.abs(_surface_function(cyl, p))) <= SURFACE_TOL_MM
    in_pit = hit.t > t_plain + 1e-6
    assert in_pit.sum() > 1500  # most rays of the fan go into a pit
    # nothing is crossed on the way: F > 0 from the plain cylinder up to the hit
    f = np.linspace(0.0, 1.0, FIRST_ROOT_SAMPLES, endpoint=False)
    t_before = t_plain[in_pit, None] + f * (hit.t[in_pit] - t_plain[in_pit] - 1e-7)[:, None]
    before = o[in_pit, None, :] + t_before[..., None] * d[in_pit, None, :]
    assert np.min(_surface_function(cyl, before)) > 0.0


def test_pit_normals_are_the_pitted_surface_normals(rng):
    cyl = _cylinder(_random_pits(rng, 3))
    o, d = _fan(rng, cyl, 500)
    hit, normal = _hit(cyl, o, d)
    sx, sy, sz = _to_surface(cyl, o + hit.t[:, None] * d).T
    r = cyl.radius_mm
    s = r * np.arctan2(sx, r - sz)
    step = 1e-5
    d_s = _surface_point(r, cyl.pits, s + step, sy) - _surface_point(r, cyl.pits, s - step, sy)
    d_y = _surface_point(r, cyl.pits, s, sy + step) - _surface_point(r, cyl.pits, s, sy - step)
    expected = np.cross(d_y, d_s)  # outward: (d_y x d_s) is -z at the origin, towards the probe
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    tilted = np.linalg.norm(expected - _outward_normal(r, s), axis=1) > 1e-3
    assert tilted.sum() > 200  # on the pit walls, not only the flat surface
    np.testing.assert_allclose(normal, expected @ cyl.R.T, atol=NORMAL_TOL)


def test_rays_outside_the_pits_meet_the_plain_cylinder_exactly(rng):
    pits = _random_pits(rng, 3)
    plain, pitted = _cylinder(), _cylinder(pits)
    o = np.zeros((4000, 3))
    tilt = rng.uniform(-0.3, 0.3, (4000, 2))
    d = np.column_stack([tilt, np.ones(4000)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a, a_normal = _hit(plain, o, d)
    b, b_normal = _hit(pitted, o, d)
    sx, sy, sz = _to_surface(plain, o + a.t[:, None] * d).T
    s = plain.radius_mm * np.arctan2(sx, plain.radius_mm - sz)
    outside = _bowl(pits, s, sy) == 0
    assert 1000 < outside.sum() < 4000  # some rays meet pits, most do not
    assert np.array_equal(a.hit, b.hit)
    assert np.array_equal(a.t[outside], b.t[outside])
    assert np.array_equal(a_normal[outside], b_normal[outside])
    assert np.array_equal(a.albedo[outside], b.albedo[outside])
    # and the others are deeper (by more than rounding where the bowl is)
    assert np.all(b.t[~outside] >= a.t[~outside])
    deep = _bowl(pits, s, sy) > 1e-6
    assert np.all(b.t[deep] - a.t[deep] > 1e-7)


def test_a_cylinder_without_pits_is_the_plain_one(rng, default_preset):
    spec = default_preset.targets["metal"]
    plain = target_from_preset("metal", spec)
    empty = target_from_preset("metal", {**spec, "pits_mm": []})
    assert plain.pits.shape == (0, 4)
    assert plain.to_dict() == empty.to_dict()
    assert not any(k.startswith("pit") for k in plain.to_dict())
    o = np.zeros((2000, 3), dtype=np.float32)
    d = np.column_stack([rng.uniform(-0.4, 0.4, (2000, 2)), np.ones(2000)]).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pose = (rotation_matrix(np.array([0.1, 0.05, 0.2])), np.array([0.0, 0.0, 18.0]))
    a = plain.with_pose(*pose).hit(tuple(o.T.copy()), tuple(d.T.copy()))
    b = empty.with_pose(*pose).hit(tuple(o.T.copy()), tuple(d.T.copy()))
    assert a.hit.sum() > 1000
    for x, y in zip([a.t, a.albedo, *a.normal], [b.t, b.albedo, *b.normal], strict=True):
        assert np.array_equal(x, y, equal_nan=True)


def test_pits_travel_through_the_preset_and_the_truth_file(default_preset):
    pits = [[0.4, -1.0, 1.2, 0.3], [-1.5, 1.5, 0.6, 0.25]]
    cyl = target_from_preset("metal", {**default_preset.targets["metal"], "pits_mm": pits})
    assert cyl.to_dict()["pits_mm"] == pits
    posed = cyl.with_pose(np.eye(3), np.array([0.0, 0.0, 20.0]))
    doc = image_truth(default_preset, Shot("scene", 0, posed), "scene_000.png", {})
    bottoms = np.array(doc["pits"]["bottom_points_mm"])
    np.testing.assert_allclose(_surface_function(posed, bottoms), 0.0, atol=SURFACE_TOL_MM)
    axis_distance = np.hypot(bottoms[:, 0], bottoms[:, 2] - (20.0 + posed.radius_mm))
    np.testing.assert_allclose(posed.radius_mm - axis_distance, [0.3, 0.25], atol=DEPTH_TOL_MM)
    assert doc["pits"]["depth_mm"] == [0.3, 0.25]
    assert all(q is not None for q in doc["pits"]["bottom_pixels"]["left"])


@pytest.mark.parametrize(
    "pits", [[[0.0, 0.0, 0.0, 0.3]], [[0.0, 0.0, 1.0, -0.2]], [[0.0, 0.0, 1.0, 30.0]]]
)
def test_impossible_pits_are_refused(default_preset, pits):
    with pytest.raises(ValueError, match="pits"):
        target_from_preset("metal", {**default_preset.targets["metal"], "pits_mm": pits})
