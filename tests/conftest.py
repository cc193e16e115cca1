"""Shared test fixtures and settings.

- ``rng``: a seeded NumPy generator per test (never a global seed).
- Hypothesis profiles: ``ci`` is derandomised (the same examples on every run, so CI is
  reproducible); ``dev`` draws fresh examples. ``CI=1`` or ``HYPOTHESIS_PROFILE=ci``
  selects the CI profile; ``.ci/run`` sets ``CI=1``. Deadlines are off in both because
  the machines these run on are shared and timing is not what the tests check.
"""

from __future__ import annotations

import os

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
