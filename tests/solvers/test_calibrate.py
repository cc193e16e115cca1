"""Calibration of both models against synthetic detections with exact ground truth.

The truth is a known model (a perturbed test design); detections are its exact
projections of board corners at the paper's poses, plus seeded Gaussian noise where a
test says so. Every calibration starts from the initialisation chain (per-half OpenCV
-> pinhole -> raytrace seed), never from the truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from tests.conftest import make_pinhole_model, make_raytrace_model
from tests.solvers.calibration_data import (
    perturbed_raytrace_truth,
    synthetic_views,
    with_fresh_noise,
)

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError, CalibrationError
from endomeasure.models import PinholeModel, RaytraceModel
from endomeasure.models.raytrace_start import prism_tilt_for_deviation
from endomeasure.solvers.calibrate import (
    CalibrationOptions,
    ViewDetections,
    calibrate,
)
from endomeasure.solvers.covariance import marginal_covariance

SIZE = (640, 480)
SPLIT = 320
NOISE_PX = 0.1  # per axis, a good sub-pixel corner detector

# Exact detections: the fit can only be limited by the convergence tolerances and the
# ray-aiming precision (1e-9 px), so parameters come back to ~1e-9 of their scale.
EXACT_RMS_PX = 1e-6
EXACT_TOL = {"px": 1e-5, "rad": 1e-7, "mm": 1e-6, "1": 1e-7}
"""Per parameter unit (the model's ``PARAM_UNITS``)."""
NOISE_RMS_REL_TOL = 0.10  # the acceptance: residual at the noise floor within 10%
COVARIANCE_REL_TOL = 0.30  # the acceptance for empirical vs predicted std


@pytest.fixture(scope="module")
def truth():
    return perturbed_raytrace_truth()


@pytest.fixture(scope="module")
def exact_set(truth):
    return synthetic_views(truth, np.random.default_rng(11), n_images=12)


@pytest.fixture(scope="module")
def exact_raytrace(exact_set):
    return calibrate("raytrace", exact_set.views, exact_set.boards, SIZE, SPLIT)


@pytest.fixture(scope="module")
def noisy_set(truth):
    return synthetic_views(truth, np.random.default_rng(12), n_images=16, noise_px=NOISE_PX)


@pytest.fixture(scope="module")
def noisy_fits(noisy_set):
    pinhole = calibrate("pinhole", noisy_set.views, noisy_set.boards, SIZE, SPLIT)
    raytrace = calibrate("raytrace", noisy_set.views, noisy_set.boards, SIZE, SPLIT, start=pinhole)
    return pinhole, raytrace


def assert_params_close(fitted, truth_model, names):
    checked = 0
    for name in names:
        tol = EXACT_TOL[fitted.unit(name)]
        assert getattr(fitted, name) == pytest.approx(getattr(truth_model, name), abs=tol), name
        checked += 1
    assert checked >= 10


# ----- recovery of the truth ---------------------------------------------------------------


def test_raytrace_recovers_the_truth_from_exact_detections(exact_raytrace, truth):
    res = exact_raytrace
    assert res.converged
    assert res.rms < EXACT_RMS_PX
    assert res.outlier_count == 0
    assert set(res.free_names) == set(RaytraceModel.PARAM_NAMES) - RaytraceModel.DEFAULT_FIXED
    assert_params_close(res.model, truth, res.free_names)
    # the glass is estimated (to the exactness of the data); fixed terms keep their value
    assert res.model.n_glass == pytest.approx(truth.n_glass, abs=1e-9)
    assert res.model.k3 == 0.0


def test_raytrace_board_poses_match_the_truth(exact_raytrace, exact_set):
    for i, (R, t) in enumerate(exact_set.poses):
        from endomeasure.geometry.rotations import rotation_matrix

        np.testing.assert_allclose(rotation_matrix(exact_raytrace.rvecs[i]), R, atol=1e-8)
        np.testing.assert_allclose(exact_raytrace.tvecs[i], t, atol=1e-6)


def test_pinhole_recovers_a_pinhole_truth(rng):
    truth = make_pinhole_model(left_cx=170.0, right_cy=242.0, rz=0.004, ty=0.03)
    data = synthetic_views(truth, rng, n_images=10)
    res = calibrate("pinhole", data.views, data.boards, SIZE, SPLIT)
    assert res.rms < EXACT_RMS_PX
    assert set(res.free_names) == set(PinholeModel.PARAM_NAMES)
    # k3 and the tangential terms are weakly determined over a 55-degree field: looser
    for name in res.free_names:
        weak = name.endswith(("k3", "k2", "p1", "p2"))
        tol = EXACT_TOL[res.model.unit(name)] * (100 if weak else 1)
        assert getattr(res.model, name) == pytest.approx(getattr(truth, name), abs=tol), name


def test_residuals_are_the_models_own_projections(exact_raytrace, noisy_fits, noisy_set):
    """The stored residuals equal model.project minus the detections (no private path)."""
    for res in (*noisy_fits,):
        P = res.obs_points
        checked = 0
        for half in Half:
            sel = res.obs_half == half
            q = res.model.project(P[sel], half).pixels
            ok = np.all(np.isfinite(q), axis=-1)
            np.testing.assert_allclose(
                res.residuals[sel][ok], q[ok] - res.obs_pixels[sel][ok], atol=1e-7
            )
            checked += int(ok.sum())
        assert checked > 0.99 * res.obs_half.size


# ----- noise --------------------------------------------------------------------------------


def test_raytrace_residual_is_at_the_noise_floor(noisy_fits):
    _, raytrace = noisy_fits
    # s^2 estimates the per-axis noise variance without bias
    assert math.sqrt(raytrace.residual_variance) == pytest.approx(NOISE_PX, rel=NOISE_RMS_REL_TOL)
    m = 2 * raytrace.n_inliers
    n = len(raytrace.free_names) + 6 * len(raytrace.image_names)
    expected_rms = NOISE_PX * math.sqrt(2.0 * (m - n) / m)  # residual length per corner
    assert raytrace.rms == pytest.approx(expected_rms, rel=NOISE_RMS_REL_TOL)
    assert raytrace.outlier_count == 0


def test_pinhole_on_prism_data_leaves_a_systematic_residual(noisy_fits, exact_set):
    pinhole, raytrace = noisy_fits
    assert pinhole.rms > raytrace.rms
    exact = calibrate("pinhole", exact_set.views, exact_set.boards, SIZE, SPLIT)
    # exact prism data: whatever the pinhole pair leaves is model error, not noise
    assert exact.rms > 100 * EXACT_RMS_PX


def test_result_statistics_are_consistent(noisy_fits):
    for res in noisy_fits:
        r = res.residuals[res.inliers]
        assert res.rms == pytest.approx(math.sqrt(np.mean(np.sum(r * r, axis=1))))
        for h in (0, 1):
            rh = res.residuals[res.inliers & (res.obs_half == h)]
            assert res.rms_half[h] == pytest.approx(math.sqrt(np.mean(np.sum(rh * rh, axis=1))))
        assert res.rms_image.shape == (len(res.image_names),)
        assert res.worst_images(1)[0][1] == pytest.approx(np.nanmax(res.rms_image))
        cov = res.covariance
        np.testing.assert_allclose(cov, cov.T, rtol=1e-12, atol=0)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        np.testing.assert_allclose(np.diag(res.correlation), 1.0)
        a, b, c = res.strongest_correlations(1)[0]
        i, j = res.free_names.index(a), res.free_names.index(b)
        assert abs(c) == pytest.approx(np.max(np.abs(res.correlation - np.eye(len(cov)))))
        assert c == pytest.approx(res.correlation[i, j])
        with pytest.raises(ValueError):
            res.residuals[0, 0] = 1.0  # immutable


# ----- outliers ------------------------------------------------------------------------------


def test_gross_corner_errors_are_reported_and_dropped(noisy_set, noisy_fits):
    views = list(noisy_set.views)
    bad = [(2, Half.LEFT, 3), (5, Half.RIGHT, 7), (9, Half.LEFT, 0)]
    for i, half, k in bad:
        v = views[i]
        pix = [p.copy() for p in v.pixels]
        pix[half][k] += np.array([3.0, -2.5])  # a mis-detected corner, ~4 px off
        views[i] = ViewDetections(v.name, v.board, v.ids, tuple(pix))
    clean_pinhole, _ = noisy_fits
    res = calibrate("pinhole", views, noisy_set.boards, SIZE, SPLIT)
    flagged = {
        (int(res.obs_image[j]), int(res.obs_half[j]), int(res.obs_ids[j]))
        for j in np.flatnonzero(~res.inliers)
    }
    expected = {(i, int(h), int(views[i].ids[h][k])) for i, h, k in bad}
    assert expected <= flagged
    assert len(flagged) <= len(expected) + 2  # at most a couple of honest 5-sigma tails
    assert res.rms == pytest.approx(clean_pinhole.rms, rel=0.05)
    for name in ("left_fx", "right_fx", "left_cx", "right_cx"):
        assert getattr(res.model, name) == pytest.approx(
            getattr(clean_pinhole.model, name), abs=3 * clean_pinhole.named_std()[name]
        )


# ----- covariance -----------------------------------------------------------------------------

CAMERA_INTERNALS = {
    "pinhole": [f"{h}_{k}" for h in ("left", "right") for k in ("fx", "fy", "cx", "cy")],
    "raytrace": ["fx", "fy", "cx", "cy", "k1", "k2"],
}


def _fixed_model(model_name):
    """The parameters the covariance checks hold: the paper's models (the lens extensions
    and, for raytrace, the glass fixed), so that every re-calibration fits the same set."""
    cls = RaytraceModel if model_name == "raytrace" else PinholeModel
    extra = {"n_glass"} if model_name == "raytrace" else set()
    return CalibrationOptions(fixed=cls.DEFAULT_FIXED | extra)


def _monte_carlo(model_name, truth, data, first, runs, rng, noise_px):
    """Re-calibrate ``runs`` times with fresh noise, each warm-started from ``first``."""
    samples = []
    for _ in range(runs):
        views = with_fresh_noise(data, rng, noise_px, SPLIT, SIZE)
        res = calibrate(model_name, views, data.boards, SIZE, SPLIT, _fixed_model(model_name),
                        start=first)  # fmt: skip
        samples.append([getattr(res.model, n) for n in CAMERA_INTERNALS[model_name]])
    return np.std(np.array(samples), axis=0, ddof=1)


@pytest.mark.parametrize("model_name", ["pinhole", "raytrace"])
def test_predicted_std_matches_monte_carlo(model_name, rng):
    """The marginal covariance predicts the spread of re-calibrations (30 runs)."""
    truth = perturbed_raytrace_truth() if model_name == "raytrace" else make_pinhole_model()
    noise = 0.3
    data = synthetic_views(truth, rng, n_images=6, min_corners=20)
    first = calibrate(
        model_name, with_fresh_noise(data, rng, noise, SPLIT, SIZE), data.boards, SIZE, SPLIT,
        _fixed_model(model_name),
    )  # fmt: skip
    predicted = np.array([first.named_std()[n] for n in CAMERA_INTERNALS[model_name]])
    empirical = _monte_carlo(model_name, truth, data, first, 30, rng, noise)
    np.testing.assert_allclose(empirical, predicted, rtol=COVARIANCE_REL_TOL)


@pytest.mark.slow
@pytest.mark.parametrize("model_name", ["pinhole", "raytrace"])
def test_predicted_std_matches_monte_carlo_from_scratch(model_name, rng):
    """As above, but every run goes through the whole initialisation chain (60 runs)."""
    truth = perturbed_raytrace_truth() if model_name == "raytrace" else make_pinhole_model()
    data = synthetic_views(truth, rng, n_images=12)
    options = _fixed_model(model_name)
    first = calibrate(
        model_name, with_fresh_noise(data, rng, NOISE_PX, SPLIT, SIZE), data.boards, SIZE, SPLIT,
        options,
    )  # fmt: skip
    predicted = np.array([first.named_std()[n] for n in CAMERA_INTERNALS[model_name]])
    samples = []
    for _ in range(60):
        views = with_fresh_noise(data, rng, NOISE_PX, SPLIT, SIZE)
        res = calibrate(model_name, views, data.boards, SIZE, SPLIT, options)
        samples.append([getattr(res.model, n) for n in CAMERA_INTERNALS[model_name]])
    empirical = np.std(np.array(samples), axis=0, ddof=1)
    np.testing.assert_allclose(empirical, predicted, rtol=COVARIANCE_REL_TOL)


def test_marginal_covariance_names_an_undetermined_pair():
    """Two parameters that only enter as their sum make S singular; both are named."""
    rng = np.random.default_rng(3)
    m = 200
    J = rng.standard_normal((m, 4))
    J[:, 3] = J[:, 2]  # p2 and p3 enter only as p2 + p3
    Jq = rng.standard_normal((m, 6))
    mc = marginal_covariance(J, Jq, np.repeat(np.arange(4), m // 4), 4, 1.0)
    assert mc.covariance is None
    assert mc.undetermined == (2, 3)


def test_marginal_covariance_equals_the_full_inverse_block():
    """Schur complement == top-left block of the full (J^T J)^-1 (independent dense route)."""
    rng = np.random.default_rng(4)
    m, F, n_poses = 120, 3, 4
    Jp = rng.standard_normal((m, F))
    Jq = rng.standard_normal((m, 6))
    pose = np.repeat(np.arange(n_poses), m // n_poses)
    full = np.zeros((m, F + 6 * n_poses))
    full[:, :F] = Jp
    for i in range(m):
        full[i, F + 6 * pose[i] : F + 6 * pose[i] + 6] = Jq[i]
    expected = 2.5 * np.linalg.inv(full.T @ full)[:F, :F]
    mc = marginal_covariance(Jp, Jq, pose, n_poses, 2.5)
    np.testing.assert_allclose(mc.covariance, expected, rtol=1e-9)


# ----- seeds and the glass index ---------------------------------------------------------------


def test_a_seed_with_design_values_converges_to_the_truth(exact_set, truth):
    nominal = make_raytrace_model().to_dict()
    res = calibrate(
        "raytrace", exact_set.views, exact_set.boards, SIZE, SPLIT, CalibrationOptions(seed=nominal)
    )
    assert res.rms < EXACT_RMS_PX
    assert_params_close(res.model, truth, res.free_names)
    assert res.start.startswith("the seed model")


def test_a_seed_of_the_wrong_kind_is_bad_input(exact_set):
    with pytest.raises(BadInputError, match="not a raytrace model"):
        calibrate(
            "raytrace",
            exact_set.views,
            exact_set.boards,
            SIZE,
            SPLIT,
            CalibrationOptions(seed=make_pinhole_model().to_dict()),
        )


def test_glass_index_is_held_at_the_given_value(exact_set, exact_raytrace):
    res = calibrate(
        "raytrace",
        exact_set.views,
        exact_set.boards,
        SIZE,
        SPLIT,
        CalibrationOptions(values={"n_glass": 1.60}, hold=frozenset({"n_glass"})),
        start=exact_raytrace,
    )
    assert res.model.n_glass == 1.60
    assert "n_glass" not in res.free_names


def test_free_index_recovers_the_glass_index(exact_set, truth, exact_raytrace):
    start = calibrate(
        "raytrace",
        exact_set.views,
        exact_set.boards,
        SIZE,
        SPLIT,
        CalibrationOptions(values={"n_glass": 1.55}, hold=frozenset({"n_glass"})),
        start=exact_raytrace,
    )
    res = calibrate(
        "raytrace",
        exact_set.views,
        exact_set.boards,
        SIZE,
        SPLIT,
        CalibrationOptions(free=frozenset({"n_glass"})),
        start=start,
    )
    assert "n_glass" in res.free_names
    assert res.model.n_glass == pytest.approx(truth.n_glass, abs=1e-6)
    # the index trades against the face tilts: the correlation is reported, and strong
    corr = dict(((a, b), c) for a, b, c in res.strongest_correlations(len(res.free_names) ** 2))
    with_index = [abs(c) for (a, b), c in corr.items() if "n_glass" in (a, b)]
    assert max(with_index) > 0.9


# ----- refusals --------------------------------------------------------------------------------


def test_too_few_images_is_refused(exact_set):
    with pytest.raises(CalibrationError, match="too few usable calibration images: 3"):
        calibrate("pinhole", exact_set.views[:3], exact_set.boards, SIZE, SPLIT)


def test_one_half_only_is_refused(exact_set):
    views = [
        ViewDetections(v.name, v.board, (v.ids[0], v.ids[1][:0]), (v.pixels[0], v.pixels[1][:0]))
        for v in exact_set.views
    ]
    with pytest.raises(CalibrationError, match="right half"):
        calibrate("pinhole", views, exact_set.boards, SIZE, SPLIT)


def test_parallel_boards_are_refused(truth, rng):
    data = synthetic_views(truth, rng, n_images=8, max_tilt_deg=0.0)
    with pytest.raises(CalibrationError, match="all boards are parallel"):
        calibrate("raytrace", data.views, data.boards, SIZE, SPLIT)


def test_one_distance_is_refused(truth, rng):
    data = synthetic_views(truth, rng, n_images=8, near_mm=20.0, far_mm=21.0)
    with pytest.raises(CalibrationError, match="one distance"):
        calibrate("pinhole", data.views, data.boards, SIZE, SPLIT)


def test_no_convergence_is_refused(noisy_set):
    with pytest.raises(CalibrationError, match="did not converge"):
        calibrate(
            "pinhole",
            noisy_set.views,
            noisy_set.boards,
            SIZE,
            SPLIT,
            CalibrationOptions(max_nfev=2),
        )


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda v: ViewDetections(v.name, "nope", v.ids, v.pixels), "board 'nope'"),
        (
            lambda v: ViewDetections(v.name, v.board, (v.ids[0] + 1000, v.ids[1]), v.pixels),
            "out of range",
        ),
        (
            lambda v: ViewDetections(
                v.name, v.board, v.ids, (v.pixels[0] + [400.0, 0.0], v.pixels[1])
            ),
            "outside the left",
        ),
        (lambda v: ViewDetections(v.name, v.board, (v.ids[0][:-1], v.ids[1]), v.pixels), "ids but"),
    ],
)
def test_malformed_detections_are_bad_input(exact_set, change, match):
    views = list(exact_set.views)
    views[0] = change(views[0])
    with pytest.raises(BadInputError, match=match):
        calibrate("pinhole", views, exact_set.boards, SIZE, SPLIT)


# ----- the seeding formula ----------------------------------------------------------------------


@pytest.mark.parametrize("alpha_deg, tilt_deg", [(-30.0, -18.0), (25.0, 15.0), (0.0, -5.0)])
def test_prism_tilt_inverts_snell(alpha_deg, tilt_deg):
    """The tilt found for a deviation reproduces it through the 3-D model trace."""
    n = 1.5168
    tilt = math.radians(tilt_deg)
    model = make_raytrace_model(left_a=tilt, left_d=2.2 * math.cos(tilt))
    alpha = math.radians(alpha_deg)
    out = model.trace(np.array([math.tan(alpha)]), np.array([0.0]), Half.LEFT).directions[0]
    beta = math.atan2(out[0], out[2])
    assert prism_tilt_for_deviation(alpha, beta, n) == pytest.approx(tilt, abs=1e-10)
