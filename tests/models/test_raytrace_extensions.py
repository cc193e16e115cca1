"""The raytrace model's lens extensions: moving entrance pupil, rational radial factor,
image-side decentering, and what they buy against optics the model does not share.

Oracles: OpenCV's rational undistortion and Snell's law in its angle form for the
backward trace from the moving pupil; central differences for every Jacobian; an
independent truth (a few lines of vector Snell below, a pixel-to-ray lens polynomial
and a pupil that moves as ``sin^2`` of the field angle, a law the model does not have)
for the fits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares
from tests.conftest import assert_snell

from endomeasure.conventions import Half, Status
from endomeasure.geometry.distortion import distort
from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.models import ModelConfig, RaytraceModel, model_from_dict

ROUND_TRIP_TOL_PX = 1e-6  # SPEC 4.2
JACOBIAN_REL_TOL = 1e-5  # central differences of the aimed pixel, relative to the largest entry
EXTENSIONS_ON = dict(
    k3=0.001, p1=2e-4, p2=-1e-4, k4=0.03, k5=-0.004, k6=0.0005,
    e1=0.06, e2=-0.01, p1_image=-3e-4, p2_image=2e-4,
    rear_a=0.01, rear_b=-0.02, right_a=0.33, right_b=-0.01, right_d=2.05,
)  # fmt: skip
"""Every extension switched on at values of the size real probe lenses show."""
NEUTRAL = dict.fromkeys(("k4", "k5", "k6", "e1", "e2", "p1_image", "p2_image"), 0.0)
"""The extensions off, given by name to the test designs' factory."""


@pytest.fixture
def extended(model_factory):
    return model_factory["raytrace"](**EXTENSIONS_ON)


def _half_pixels(model, half, n_u=40, n_v=30):
    width, height = model.config.image_size
    edge = model.config.split - 0.5
    lo, hi = (-0.5, edge) if half is Half.LEFT else (edge, width - 0.5)
    pad = 1e-6  # strictly inside the half's pixel rectangle, as rounding leaves it
    uu, vv = np.meshgrid(np.linspace(lo + pad, hi - pad, n_u),
                         np.linspace(-0.5 + pad, height - 0.5 - pad, n_v))  # fmt: skip
    return np.stack([uu.ravel(), vv.ravel()], axis=-1)


def _at_depth(rays, depth):
    s = (depth - rays.origins[:, 2]) / rays.directions[:, 2]
    return rays.origins + s[:, None] * rays.directions


def test_extension_parameters_are_listed_fixed_and_neutral():
    names = [n for group in RaytraceModel.EXTENSIONS for n in group]
    assert len(names) == len(set(names))
    assert set(names) <= RaytraceModel.DEFAULT_FIXED
    assert {"k4", "k5", "k6", "e1", "e2", "p1_image", "p2_image"} <= set(names)
    assert RaytraceModel.unit("e1") == "mm" and RaytraceModel.unit("k4") == "1"


@pytest.mark.parametrize("half", list(Half))
def test_project_inverts_rays_with_every_extension(extended, half):
    q = _half_pixels(extended, half)
    rays = extended.rays(q, half)
    assert np.mean(rays.status == Status.OK) > 0.95
    checked = 0
    for depth in (8.0, 20.0, 60.0):
        proj = extended.project(_at_depth(rays, depth), half)
        ok = proj.status == Status.OK
        assert np.array_equal(ok, rays.status == Status.OK)  # every traceable pixel projects
        err = np.linalg.norm(proj.pixels[ok] - q[ok], axis=-1)
        assert err.max() < ROUND_TRIP_TOL_PX
        checked += ok.sum()
    assert checked > 2500


def test_rays_leave_the_moving_pupil_and_obey_snell(model_factory, rng):
    """Rebuild each pixel's path from OpenCV's rational undistortion, the pupil law and
    the faces alone, and check Snell's law in its angle form at both faces."""
    import cv2

    m = model_factory["raytrace"](**{**EXTENSIONS_ON, "p1_image": 0.0, "p2_image": 0.0})
    q = np.stack([rng.uniform(0, 319, 300), rng.uniform(0, 479, 300)], axis=-1)
    rays = m.rays(q, "left")
    assert np.all(rays.status == Status.OK)
    K = np.array([[m.fx, 0, m.cx], [0, m.fy, m.cy], [0, 0, 1.0]])
    dist = np.array([m.k1, m.k2, m.p1, m.p2, m.k3, m.k4, m.k5, m.k6])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    xy = cv2.undistortPoints(q[:, None], K, dist, None, None, None, crit)[:, 0]
    theta = np.arctan(np.hypot(xy[:, 0], xy[:, 1]))
    pupil = np.zeros((len(q), 3))
    pupil[:, 2] = m.e1 * theta**2 + m.e2 * theta**4
    assert np.ptp(pupil[:, 2]) > 0.01  # the pupil does move over this field (mm)
    lens = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    air_in = lens / np.linalg.norm(lens, axis=1, keepdims=True)
    n_rear, d_rear = m.face("rear")
    P1 = pupil + air_in * ((d_rear - pupil @ n_rear) / (air_in @ n_rear))[:, None]
    glass = rays.origins - P1
    glass /= np.linalg.norm(glass, axis=1, keepdims=True)
    n_front, _ = m.face("left")
    assert_snell([(air_in, glass, n_rear, 1.0, m.n_glass),
                  (glass, rays.directions, n_front, m.n_glass, 1.0)])  # fmt: skip


@pytest.mark.parametrize("half", list(Half))
def test_every_parameter_jacobian_matches_central_differences(extended, half, rng):
    n = 200
    z = rng.uniform(8, 60, n)
    sign = -1.0 if half is Half.LEFT else 1.0
    points = np.stack([sign * rng.uniform(0, 0.6, n) * z, rng.uniform(-0.5, 0.5, n) * z, z], -1)
    free = np.arange(extended.params.size)
    jac = extended.project_jacobians(points, half, free)
    ok = jac.status == Status.OK
    assert ok.sum() > 150
    extended = extended.with_config(fixed=frozenset())  # the projector differentiates all
    projector = extended.projector(np.full(n, int(half)))
    pixels, valid = projector.project(extended, points)
    np.testing.assert_array_equal(valid, ok)
    np.testing.assert_allclose(pixels[ok], jac.pixels[ok], atol=1e-9, rtol=0)
    dq_dparams, dq_dp = projector.jacobian(extended, points)
    for i, name in enumerate(extended.PARAM_NAMES):
        step = 1e-6 * max(1.0, abs(extended.params[i]))
        shifted = []
        for sign_ in (1.0, -1.0):
            p = extended.params.copy()
            p[i] += sign_ * step
            shifted.append(extended.with_params(p).project(points, half).pixels)
        numeric = (shifted[0] - shifted[1]) / (2 * step)
        scale = max(np.abs(numeric[ok]).max(), 1e-6)
        for analytic in (jac.dq_dparams[:, :, i], dq_dparams[:, :, i]):
            np.testing.assert_allclose(
                analytic[ok], numeric[ok], atol=JACOBIAN_REL_TOL * scale, rtol=0, err_msg=name
            )
    np.testing.assert_allclose(dq_dp[ok], jac.dq_dp[ok], atol=1e-9, rtol=0)


def test_a_model_stored_with_the_19_earlier_parameters_loads_fixed_at_zero(model_factory):
    raytrace_model = model_factory["raytrace"](**NEUTRAL)
    earlier = (
        "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "rear_a", "rear_b", "rear_d",
        "left_a", "left_b", "left_d", "right_a", "right_b", "right_d", "n_glass",
    )  # fmt: skip
    data = raytrace_model.to_dict()
    data["param_names"] = list(earlier)
    data["params"] = [raytrace_model.named_params()[n] for n in earlier]
    data["config"]["fixed"] = ["k3", "n_glass", "p1", "p2"]  # an earlier DEFAULT_FIXED
    loaded = model_from_dict(data)
    new = set(RaytraceModel.PARAM_NAMES) - set(earlier)
    assert new and all(getattr(loaded, n) == 0.0 for n in new)
    assert loaded.config.fixed == frozenset(data["config"]["fixed"]) | new
    np.testing.assert_array_equal(loaded.params, raytrace_model.params)
    # any other mismatch is still refused
    for names in (earlier[1:], (*earlier[:-1], "n_prism")):
        with pytest.raises(ValueError, match="parameter names"):
            model_from_dict(
                {**data, "param_names": list(names), "params": data["params"][: len(names)]}
            )


# ----- the edge of the field ---------------------------------------------------------


def test_every_traceable_pixel_of_a_steep_prism_projects(model_factory):
    """A dense flint with steep wedges: near the corners the start map lands beyond the
    critical angle although the corner's own ray traces. Each such point must still be
    aimed (the start is pulled back into the traceable field), up to the field edge."""
    steep = model_factory["raytrace"](
        **NEUTRAL, n_glass=1.85, left_a=-math.radians(30), right_a=math.radians(26),
        k1=0.25, k2=0.05, fx=200.0, fy=200.0, rear_a=0.02, left_d=2.2, right_d=2.3,
    )  # fmt: skip
    checked = 0
    for half in Half:
        q = _half_pixels(steep, half, 64, 48)
        rays = steep.rays(q, half)
        ok = rays.status == Status.OK
        assert 0.5 < ok.mean() < 1.0  # part of the half is beyond the critical angle
        for depth in (8.0, 30.0):
            proj = steep.project(_at_depth(rays, depth)[ok], half)
            assert np.all(proj.status == Status.OK), np.bincount(proj.status)
            assert np.abs(proj.pixels - q[ok]).max() < ROUND_TRIP_TOL_PX
            checked += ok.sum()
    assert checked > 4000


# ----- against optics the model does not share ------------------------------------------

NOISE_RMS_PX = 0.03
"""2-D RMS of the simulated detection noise, about the detector's on sharp renders."""
AT_FLOOR = 1.1  # the fit RMS over the noise floor that counts as fitting to the noise
FAR_ABOVE_FLOOR = 3.0


def _snell(d, normal, eta):
    """Refract unit rows ``d`` at a face of unit ``normal`` (either side) by ``eta = n1/n2``."""
    cos_i = d @ normal
    m = np.where(cos_i[:, None] < 0, normal, -normal)  # faces the incoming ray
    c = -np.sum(m * d, axis=1)
    k = 1.0 - eta**2 * (1.0 - c**2)
    return eta * d + (eta * c - np.sqrt(k))[:, None] * m  # NaN beyond the critical angle


class _IndependentProbe:
    """A probe no model shares: a lens defined from pixel to ray (radial to r_d^4 with
    decentering on the distorted point, 35 % barrel at the corners), an entrance pupil
    that moves as ``sin^2`` of the field angle (0.1 mm at the corner), a rear face tilted
    in both axes and front faces of unequal wedges meeting off axis, N-SF-like glass."""

    size, split = (640, 480), 320
    f, cx, cy = 240.0, 322.0, 236.5
    n_glass = 1.62

    def __init__(self):
        corner = math.hypot(self.cx + 0.5, self.cy + 0.5) / self.f  # distorted radius
        stretch = 1 / 0.65 - 1  # 35 % barrel: r_d = 0.65 r_u at the corner
        self.c = (0.6 * stretch / corner**2, 0.4 * stretch / corner**4)
        self.p = (2e-4, -1.5e-4)
        self.pupil_mm, self.theta_edge = 0.1, math.atan(corner * (1 + stretch))

        def plane(a_deg, b_deg, point):
            n = np.array([math.tan(math.radians(a_deg)), math.tan(math.radians(b_deg)), 1.0])
            n /= np.linalg.norm(n)
            return n, float(n @ point)

        apex = np.array([0.06, 0.0, 2.4])
        self.faces = {"rear": plane(1.0, -0.8, [0, 0, 1.0]), "left": plane(-20.0, 0.5, apex),
                      "right": plane(26.0, -0.4, apex + [0, 0, 0.02])}  # fmt: skip

    def ideal(self, q):
        xd, yd = (q[:, 0] - self.cx) / self.f, (q[:, 1] - self.cy) / self.f
        r2 = xd * xd + yd * yd
        radial = 1 + r2 * (self.c[0] + r2 * self.c[1])
        p1, p2 = self.p
        x = xd * radial + 2 * p1 * xd * yd + p2 * (r2 + 2 * xd * xd)
        y = yd * radial + p1 * (r2 + 2 * yd * yd) + 2 * p2 * xd * yd
        return x, y

    def rays(self, q, half):
        x, y = self.ideal(q)
        d = np.stack([x, y, np.ones_like(x)], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        theta = np.arccos(d[:, 2])
        o = np.zeros_like(d)
        o[:, 2] = self.pupil_mm * np.sin(theta) ** 2 / math.sin(self.theta_edge) ** 2
        for face, eta in (("rear", 1 / self.n_glass), (half.label, self.n_glass)):
            n, dist = self.faces[face]
            o = o + ((dist - o @ n) / (d @ n))[:, None] * d
            d = _snell(d, n, eta)
        return o, d


def _observations(probe, rng, per_half):
    points, halves, pixels = [], [], []
    for half in Half:
        lo, hi = (0.0, probe.split - 0.5) if half is Half.LEFT else (probe.split - 0.5, 639.0)
        q = np.stack([rng.uniform(lo, hi, per_half), rng.uniform(0, 479, per_half)], axis=1)
        o, d = probe.rays(q, half)
        ok = np.all(np.isfinite(d), axis=1)
        depth = rng.uniform(8.0, 40.0, ok.sum())
        points.append(o[ok] + ((depth - o[ok, 2]) / d[ok, 2])[:, None] * d[ok])
        halves.append(np.full(ok.sum(), int(half), dtype=np.int8))
        pixels.append(q[ok])
    return np.concatenate(points), np.concatenate(halves), np.concatenate(pixels)


def _start(probe, free):
    """The probe's own design values, its lens polynomial refitted in the model's form."""
    values = dict(fx=probe.f, fy=probe.f, cx=probe.cx, cy=probe.cy, n_glass=probe.n_glass)
    for face, (n, dist) in probe.faces.items():
        values.update({f"{face}_a": math.atan(n[0] / n[2]), f"{face}_b": math.atan(n[1] / n[2]),
                       f"{face}_d": dist})  # fmt: skip
    params = np.array([values.get(name, 0.0) for name in RaytraceModel.PARAM_NAMES])
    fixed = set(RaytraceModel.PARAM_NAMES) - set(free)
    model = RaytraceModel(params, ModelConfig(probe.size, probe.split, fixed))
    lens = [n for n in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "p1_image", "p2_image")
            if n in free]  # fmt: skip
    uu, vv = np.meshgrid(np.linspace(0, 639, 40), np.linspace(0, 479, 30))
    q = np.stack([uu.ravel(), vv.ravel()], axis=1)
    x, y = probe.ideal(q)

    def misfit(z):
        m = model.with_values(dict(zip(lens, z, strict=True)))
        xd, yd = distort(x, y, m._lens_coeffs())
        return np.concatenate([m.fx * xd + m.cx - q[:, 0], m.fy * yd + m.cy - q[:, 1]])

    fit = least_squares(misfit, np.zeros(len(lens)), method="lm")
    return model.with_values(dict(zip(lens, fit.x, strict=True)))


def _fit_rms(model, points, halves, observed) -> float:
    """RMS px of the model's best fit to the observations, its parameters and one rigid
    transform of the probe frame free (the model's frame need not be the probe's)."""
    free = np.flatnonzero(model.free_mask)
    projector = model.projector(halves)
    base = model.params.copy()

    def unpack(z):
        p = base.copy()
        p[free] = z[: free.size]
        return model.with_params(p), points @ rotation_matrix(z[-6:-3]).T + z[-3:]

    def residuals(z):
        m, P = unpack(z)
        pixels, ok = projector.project(m, P)
        return np.where(ok[:, None], pixels - observed, 0.0).ravel()

    def jacobian(z):
        m, P = unpack(z)
        projector.project(m, P)
        dq_dparams, dq_dp = projector.jacobian(m, P)
        RP = P - z[-3:]  # d(R P)/d w = -[R P]x for a small rotation applied before R
        skew = np.zeros((len(P), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -RP[:, 2], RP[:, 1], -RP[:, 0]
        skew -= np.swapaxes(skew, 1, 2)
        J = np.concatenate([dq_dparams, dq_dp @ -skew, dq_dp], axis=-1)
        return J.reshape(-1, J.shape[-1])

    fit = least_squares(residuals, np.concatenate([base[free], np.zeros(6)]), jac=jacobian,
                        method="trf", x_scale="jac", max_nfev=40)  # fmt: skip
    r = fit.fun.reshape(-1, 2)
    assert np.count_nonzero(np.all(r == 0.0, axis=1)) < 0.005 * len(r)  # nothing lost
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


PAPER = ("fx", "fy", "cx", "cy", "k1", "k2", "rear_a", "rear_b", "rear_d",
         "left_a", "left_b", "left_d", "right_a", "right_b", "right_d")  # fmt: skip
EXTENDED = PAPER + tuple(n for group in RaytraceModel.EXTENSIONS for n in group)


def _without(*names):
    return tuple(n for n in EXTENDED if n not in names)


@pytest.mark.parametrize(
    ("free", "bound"),
    [
        (PAPER, "far above"),
        (EXTENDED, "at"),
        (_without("k4", "k5", "k6"), "far above"),
        (_without("e1", "e2"), "above"),
        (_without("p1_image", "p2_image"), "above"),
    ],
    ids=["paper's lens", "every extension", "no rational factor", "a fixed pupil",
         "no image-side decentering"],
)  # fmt: skip
def test_the_extensions_fit_an_independent_probe_to_the_noise(free, bound):
    """Each extension is needed for this probe, and all of them fit it to the noise."""
    probe = _IndependentProbe()
    rng = np.random.default_rng(5)
    points, halves, pixels = _observations(probe, rng, 500)
    observed = pixels + rng.normal(0.0, NOISE_RMS_PX / math.sqrt(2), pixels.shape)
    model = _start(probe, free)
    dof = 1 - (model.free_mask.sum() + 6) / observed.size
    floor = NOISE_RMS_PX * math.sqrt(dof)
    rms = _fit_rms(model, points, halves, observed)
    limit = {"at": AT_FLOOR, "above": AT_FLOOR, "far above": FAR_ABOVE_FLOOR}[bound]
    assert (rms < limit * floor) if bound == "at" else (rms > limit * floor)
