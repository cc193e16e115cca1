"""Projection of a fixed set of observations under many trial models, for the solvers.

A bundle adjustment projects the same corners (each a point in the model frame and the
half it is seen in) under every trial parameter vector, and differentiates the
projection with respect to the free parameters and the points. A :class:`Projector`
does this for one model kind; a model gets its own through
:meth:`~endomeasure.models.base.CameraModel.projector`. The default here uses the
model's public projection and :meth:`~endomeasure.models.base.CameraModel.project_jacobians`,
so it follows the same validity rules as :meth:`~endomeasure.models.base.CameraModel.project`;
a model subclasses it only to keep state between calls (warm starts).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from endomeasure.conventions import Half

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel

__all__ = ["Projector", "zero_lost_rows"]


class Projector:
    """Projects a fixed set of observations and differentiates the projection.

    Parameters
    ----------
    template : CameraModel
        Its ``free_mask`` fixes which parameters are differentiated.
    halves : ndarray of int, shape (N,)
        Half (0 left, 1 right) of each observation.
    state : ndarray, shape (N, k), optional
        A previous projector's :meth:`state` over the same observations.

    Notes
    -----
    :meth:`jacobian` may rely on the last :meth:`project` call, which the solver always
    makes with the same model and points first.
    """

    def __init__(self, template: CameraModel, halves: np.ndarray, state: np.ndarray | None = None):
        self.halves = np.asarray(halves, dtype=np.int8)
        self.free = np.flatnonzero(template.free_mask)
        self.groups = [
            (half, np.flatnonzero(self.halves == half))
            for half in (Half.LEFT, Half.RIGHT)
            if np.any(self.halves == half)
        ]

    def state(self) -> np.ndarray | None:
        """Per-observation state worth carrying to a next problem over the same
        observations (warm starts), shape (N, k), or None."""
        return None

    def project(self, model: CameraModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of the observations' points (N, 3), mm, in the model frame.

        Returns
        -------
        pixels : ndarray, shape (N, 2), px
            NaN where the projection is not valid.
        ok : ndarray of bool, shape (N,)
            Status OK by the model's rules (:meth:`CameraModel.project`).
        """
        pixels = np.full((points.shape[0], 2), np.nan)
        for half, idx in self.groups:
            pixels[idx] = model.project(points[idx], half).pixels
        return pixels, np.all(np.isfinite(pixels), axis=-1)

    def jacobian(self, model: CameraModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of the pixels of the observations' points.

        Returns
        -------
        dq_dparams : ndarray, shape (N, 2, F)
            With respect to the free parameters, px per parameter unit.
        dq_dp : ndarray, shape (N, 2, 3), px / mm
            With respect to the points. Both are zero where the projection or its
            derivative fails (such a corner then does not steer the step).
        """
        dq_dparams = np.zeros((points.shape[0], 2, self.free.size))
        dq_dp = np.zeros((points.shape[0], 2, 3))
        for half, idx in self.groups:
            jac = model.project_jacobians(points[idx], half, self.free)
            dq_dparams[idx], dq_dp[idx] = jac.dq_dparams, jac.dq_dp
        return zero_lost_rows(dq_dparams, dq_dp)


def zero_lost_rows(dq_dparams: np.ndarray, dq_dp: np.ndarray):
    """Both Jacobians with the rows zeroed where either is not finite."""
    lost = ~(np.isfinite(dq_dparams).all(axis=(1, 2)) & np.isfinite(dq_dp).all(axis=(1, 2)))
    dq_dparams[lost] = 0.0
    dq_dp[lost] = 0.0
    return dq_dparams, dq_dp
