# ruff: noqa: I001  (endomeasure is imported before numpy on purpose, see below)
"""Shared test fixtures and settings.

- ``rng``: a seeded NumPy generator per test (never a global seed).
- Hypothesis profiles: ``ci`` is derandomised (the same examples on every run, so CI is
  reproducible); ``dev`` draws fresh examples. ``CI=1`` or ``HYPOTHESIS_PROFILE=ci``
  selects the CI profile; ``.ci/run`` sets ``CI=1``. Deadlines are off in both because
  the machines these run on are shared and timing is not what the tests check.
"""

from __future__ import annotations

import os

import endomeasure  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)
import numpy as np
import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("dev", deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))

RNG_SEED = 20240611
"""Seed of the per-test generator; any fixed value works, it only has to be fixed."""


@pytest.fixture
def rng() -> np.random.Generator:
    """A freshly seeded generator, so tests do not depend on each other's draws."""
    return np.random.default_rng(RNG_SEED)


# ----- camera-model designs shared by model, solver and measurement tests ---------------

NOMINAL_PRISM_TILT_DEG = 18.0
"""Front-face tilt of the nominal biprism used across the tests (see ``raytrace_model``)."""


def make_raytrace_model(**overrides):
    """A raytrace model of a plausible 6 mm probe: 640x480 sensor split at column 320,
    N-BK7 biprism with its apex 2.2 mm in front of the lens, faces tilted by 18 degrees.
    Keyword arguments override single parameters by name."""
    import math

    from endomeasure.models import ModelConfig, RaytraceModel

    tilt = math.radians(NOMINAL_PRISM_TILT_DEG)
    values = dict(
        fx=230.0, fy=230.0, cx=319.5, cy=239.5, k1=-0.12, k2=0.02, k3=0.0, p1=0.0, p2=0.0,
        rear_a=0.0, rear_b=0.0, rear_d=0.6,
        left_a=-tilt, left_b=0.0, left_d=2.2 * math.cos(tilt),
        right_a=tilt, right_b=0.0, right_d=2.2 * math.cos(tilt),
        n_glass=1.5168,
    )  # fmt: skip
    values.update(overrides)
    params = np.array([values.get(n, 0.0) for n in RaytraceModel.PARAM_NAMES])
    return RaytraceModel(params, ModelConfig((640, 480), 320, RaytraceModel.DEFAULT_FIXED))


def make_pinhole_model(**overrides):
    """A pinhole pair of similar geometry: two 230 px cameras 0.9 mm apart, toed in by 1 degree."""
    import math

    from endomeasure.models import ModelConfig, PinholeModel

    values = {}
    for half, cx in (("left", 160.0), ("right", 480.0)):
        values.update({f"{half}_{k}": v for k, v in dict(
            fx=230.0, fy=231.0, cx=cx, cy=239.5, k1=-0.1, k2=0.01, p1=1e-4, p2=-2e-4, k3=0.001
        ).items()})  # fmt: skip
    values.update(rx=0.0, ry=math.radians(-1.0), rz=0.002, tx=-0.9, ty=0.01, tz=0.0)
    values.update(overrides)
    params = np.array([values[n] for n in PinholeModel.PARAM_NAMES])
    return PinholeModel(params, ModelConfig((640, 480), 320))


@pytest.fixture
def raytrace_model():
    return make_raytrace_model()


@pytest.fixture
def pinhole_model():
    return make_pinhole_model()


@pytest.fixture(params=["pinhole", "raytrace"])
def any_model(request):
    """Each registered model in turn (the contract tests run on all of them)."""
    return {"pinhole": make_pinhole_model, "raytrace": make_raytrace_model}[request.param]()


@pytest.fixture
def model_factory():
    """The design factories themselves, for tests that perturb a design:
    ``model_factory['raytrace'](k3=0.01)``."""
    return {"pinhole": make_pinhole_model, "raytrace": make_raytrace_model}


def assert_snell(surfaces) -> None:
    """Snell's law at each surface: ``n_a sin(a) = n_b sin(b)`` and the two rays coplanar
    with the normal; ``surfaces`` holds (incident (N, 3), refracted (N, 3), normal (3,),
    n_a, n_b) with unit vectors."""
    for a, b, normal, n_a, n_b in surfaces:
        sin_a = np.linalg.norm(np.cross(a, normal), axis=1)
        sin_b = np.linalg.norm(np.cross(b, normal), axis=1)
        np.testing.assert_allclose(n_a * sin_a, n_b * sin_b, atol=1e-8)
        coplanar = np.einsum("ni,ni->n", np.cross(a, b), np.broadcast_to(normal, a.shape))
        np.testing.assert_allclose(coplanar, 0.0, atol=1e-8)


def scaled_world(model, factor: float):
    """``model`` in a world scaled by ``factor``: every length parameter (unit mm: the
    pinhole pair's stereo translation, the prism faces' distances) times ``factor``, so a
    point ``factor * p`` projects where ``p`` did and every length triangulates
    ``factor`` times larger (a baseline scaled by ``factor``)."""
    p = model.params.copy()
    for i, name in enumerate(model.PARAM_NAMES):
        if model.unit(name) == "mm":
            p[i] *= factor
    return model.with_params(p)
