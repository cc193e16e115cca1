"""The model misfit of a calibration's residuals (solvers/misfit.py).

Residuals are built with a known split (``tests/solvers/misfit_data.py``): seeded
Gaussian noise, independent from corner to corner, plus a smooth field of known variance
on square boards placed at random in both halves. The fit must return the field's
variance as misfit and the noise as noise, tell noise the two views of a corner share
from a misfit, and give a covariance that is one.
"""

from __future__ import annotations

import numpy as np
import pytest
from tests.solvers.misfit_data import AMPLITUDE, GRID, NOISE, SPACING, board_residuals

from endomeasure.measure.predict import ImageNoise, predict_measurement_error
from endomeasure.solvers.misfit import ModelMisfit, fit_misfit


def test_noise_only_has_no_misfit():
    m = fit_misfit(*board_residuals(np.random.default_rng(1), field_l=0.0, field_r=0.0))
    assert m is not None
    np.testing.assert_allclose(m.noise, NOISE, rtol=0.05)
    assert np.all(m.std < 0.3 * NOISE)  # sampling leaves at most a trace


def test_field_variance_is_the_misfit_and_noise_the_rest():
    m = fit_misfit(*board_residuals(np.random.default_rng(2)))
    field_std = AMPLITUDE / np.sqrt(2)
    np.testing.assert_allclose(m.std[0], field_std, rtol=0.12)
    np.testing.assert_allclose(m.std[1], 0.5 * field_std, rtol=0.15)
    np.testing.assert_allclose(m.noise, NOISE, rtol=0.15)
    # the right half's field is the left one's, negated: correlation -1
    assert np.all(m.rho_halves < -0.8)
    # the field decorrelates over a quarter wavelength, not over a corner spacing
    assert np.all(m.ring_px > SPACING)


def test_a_misfit_along_its_own_coordinate_stretches_the_kernel_across_it():
    """A radial-like misfit (the u error a function of u alone, the v error of v alone, as
    a scale or distortion error makes it) is shared by points above one another in u and
    side by side in v: the fitted kernels stretch across their coordinate, and the
    misfit of a vertical pair's u difference is predicted far below a horizontal pair's."""
    rng = np.random.default_rng(6)
    X, image, half, q, _ = board_residuals(rng, field_l=0.0, field_r=0.0)
    local = q - np.where(half[:, None] == 1, 320.0, 0.0)
    phase = rng.uniform(0, 2 * np.pi, (image.max() + 1, 2))[image]
    field = AMPLITUDE * np.sin(2 * np.pi * local / 80.0 + phase)  # u(u), v(v)
    r = field + rng.normal(0, NOISE, field.shape)
    m = fit_misfit(X, image, half, q, r)
    assert np.all(m.stretch >= 4)
    np.testing.assert_allclose(m.std, AMPLITUDE / np.sqrt(2), rtol=0.15)
    apart = 4 * SPACING
    for c in range(2):
        cov_along = m.covariance(np.array([[100.0, 100.0], [100.0, 100.0] + _axis(c) * apart]))
        cov_across = m.covariance(np.array([[100.0, 100.0], [100.0, 100.0] + _axis(1 - c) * apart]))
        var_along = cov_along[c, c] + cov_along[4 + c, 4 + c] - 2 * cov_along[c, 4 + c]
        var_across = cov_across[c, c] + cov_across[4 + c, 4 + c] - 2 * cov_across[c, 4 + c]
        assert var_across < 0.2 * var_along


def _axis(c: int) -> np.ndarray:
    return np.eye(2)[c]


def test_noise_the_two_views_share_is_not_a_misfit():
    data = board_residuals(np.random.default_rng(3), field_l=0.0, field_r=0.0, shared=NOISE)
    m = fit_misfit(*data)
    assert np.all(m.std < 0.3 * NOISE)


def test_too_few_runs_give_none():
    X, image, half, q, r = board_residuals(np.random.default_rng(4), n_images=1)
    keep = np.arange(X.shape[0]) % GRID < 2  # two columns: no run of three along a row
    keep &= (np.arange(X.shape[0]) // GRID) < 2  # and two rows
    assert fit_misfit(X[keep], image[keep], half[keep], q[keep], r[keep]) is None


def test_covariance_is_a_covariance_with_the_stated_diagonal():
    m = ModelMisfit([[0.2, 0.1], [0.15, 0.05]], [-0.7, 0.3], 15.0, 60.0, [[0.01] * 2] * 2)
    q = np.random.default_rng(5).uniform(0, 300, (50, 4, 2))
    cov = m.covariance(q)
    assert cov.shape == (50, 16, 16)
    assert np.linalg.eigvalsh(cov).min() > -1e-12
    diag = np.diagonal(cov, axis1=1, axis2=2).reshape(50, 4, 4)
    np.testing.assert_allclose(diag, np.broadcast_to([0.04, 0.01, 0.0225, 0.0025], (50, 4, 4)))
    # u_L with u_R of one point: rho s_L s_R
    np.testing.assert_allclose(cov[:, 0, 2], -0.7 * 0.2 * 0.15)
    # the same pixel twice: the two points share their misfit entirely
    same = m.covariance(np.array([[10.0, 20.0], [10.0, 20.0]]))
    np.testing.assert_allclose(same[:4, 4:], same[:4, :4])


@pytest.fixture(scope="module")
def raytrace_model():
    from tests.solvers.calibration_data import perturbed_raytrace_truth

    return perturbed_raytrace_truth()


def _pixels(model, points):
    return model.project(points, "left").pixels, model.project(points, "right").pixels


def test_misfit_is_its_own_budget_part_and_adds_in_quadrature(raytrace_model):
    points = np.array([[-1.5, 0.5, 25.0], [1.5, -0.5, 26.0]])
    ql, qr = _pixels(raytrace_model, points)
    misfit = ModelMisfit([[0.05, 0.03], [0.05, 0.03]], [-0.5, 0.0], 20.0, 80.0,
                         [[0.01] * 2] * 2)  # fmt: skip
    noise = ImageNoise(0.02)
    parts = {}
    for method in ("ut", "linear"):
        pred = predict_measurement_error(raytrace_model, "length", ql, qr, noise=noise,
                                         misfit=misfit, method=method)  # fmt: skip
        image, model = pred.parts["image"][1][0], pred.parts["model"][1][0]
        # the UT's parts leave out the bias cross term 2 (beta - alpha^2) b_image b_model
        np.testing.assert_allclose(pred.std[0] ** 2, image**2 + model**2,
                                   rtol=1e-6 if method == "linear" else 0.05)  # fmt: skip
        parts[method] = (image, model)
    alone = predict_measurement_error(raytrace_model, "length", ql, qr, noise=noise)
    assert "model" not in alone.parts
    # the image part does not change with the misfit beside it (the UT's spread grows
    # with the inputs: a few tenths of a percent)
    np.testing.assert_allclose(alone.std[0], parts["ut"][0], rtol=0.01)
    np.testing.assert_allclose(parts["ut"][1], parts["linear"][1], rtol=0.05)


def test_shared_misfit_cancels_in_a_short_length(raytrace_model):
    near = np.array([[0.0, 0.0, 25.0], [0.2, 0.0, 25.0]])
    far = np.array([[-3.0, 0.0, 25.0], [3.0, 0.0, 25.0]])
    misfit = ModelMisfit([[0.05, 0.05], [0.05, 0.05]], [0.0, 0.0], 30.0, 100.0,
                         [[0.01] * 2] * 2)  # fmt: skip
    rel = []
    for points in (near, far):
        ql, qr = _pixels(raytrace_model, points)
        pred = predict_measurement_error(raytrace_model, "length", ql, qr,
                                         noise=ImageNoise(0.0), misfit=misfit)  # fmt: skip
        shared = np.exp(-0.5 * (np.linalg.norm(ql[0] - ql[1]) / 100.0) ** 2)
        rel.append((pred.parts["model"][1][0], shared))
    # the short length's points share nearly all their misfit: a far smaller part
    assert rel[0][1] > 0.99 and rel[1][1] < 0.9
    assert rel[0][0] < 0.3 * rel[1][0]
