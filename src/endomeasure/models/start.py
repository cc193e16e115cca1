"""What a model's own calibration initialiser is given and gives back (the start contract).

Calibration (:mod:`endomeasure.solvers.calibrate`) is the same bundle adjustment for
every model; only the start is model-specific. A model class says where its start comes
from (:attr:`~endomeasure.models.base.CameraModel.SEEDED_FROM`), and the
:data:`Initialiser` registered with it (:func:`~endomeasure.models.registry.register_model`)
builds it from a :class:`StartContext`: the corner observations, the configuration, the
user's values, and a ``refine`` callable (the solver's bundle adjustment) for the small
fits a seeding may need. Nothing here depends on the solvers, so models stay below them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel, ModelConfig

__all__ = ["Observations", "Fit", "Start", "StartContext", "Initialiser"]


@dataclasses.dataclass(frozen=True)
class Observations:
    """Corner observations flattened to one row per corner, half and image (``M`` rows).

    Attributes
    ----------
    image_names, image_boards : tuple of str, length I
    image : ndarray of int, shape (M,)
        Index into ``image_names``.
    half : ndarray of int8, shape (M,)
        0 left, 1 right.
    ids : ndarray of int, shape (M,)
        Corner id on its board.
    board_points : ndarray, shape (M, 3), mm
        Corner in the board frame.
    pixels : ndarray, shape (M, 2), px
        Detected full-image pixel.
    skipped : tuple of str
        Images left out (too few corners in both halves).
    """

    image_names: tuple[str, ...]
    image_boards: tuple[str, ...]
    image: np.ndarray
    half: np.ndarray
    ids: np.ndarray
    board_points: np.ndarray
    pixels: np.ndarray
    skipped: tuple[str, ...] = ()

    @property
    def n_images(self) -> int:
        return len(self.image_names)

    def subset(self, image: int, half: int) -> np.ndarray:
        """Rows of one image and half."""
        return np.flatnonzero((self.image == image) & (self.half == half))

    def as_one_board(self, points: np.ndarray) -> Observations:
        """The same pixels seen as one rigid "board" whose corners are ``points`` (M, 3):
        fits one transform of already placed corners instead of a pose per image."""
        return dataclasses.replace(
            self,
            image_names=("all",),
            image_boards=("all",),
            image=np.zeros(self.image.size, dtype=np.int64),
            board_points=np.asarray(points, dtype=np.float64),
            skipped=(),
        )


class Fit(NamedTuple):
    """A bundle adjustment's outcome: the model, a board pose per image, the optimiser's
    verdict and the projector's warm-start state per observation (None if it keeps none)."""

    model: CameraModel
    rvecs: np.ndarray  # (I, 3) rad: T_model_board
    tvecs: np.ndarray  # (I, 3) mm
    status: int
    message: str
    nfev: int
    state: np.ndarray | None


class Start(NamedTuple):
    """A model and board poses to start a calibration (or a seeding) from."""

    model: CameraModel
    rvecs: np.ndarray  # (I, 3) rad: T_model_board
    tvecs: np.ndarray  # (I, 3) mm
    origin: str  # where it came from, for the report
    state: np.ndarray | None = None  # projector warm-start state per observation


Refine = Callable[..., Fit]
"""``refine(model, observations, rvecs, tvecs, state=None, max_nfev=None) -> Fit``: the
solver's bundle adjustment of the model's free parameters and the poses over all the given
observations, warm-started from a projector ``state`` over the same observations, with at
most ``max_nfev`` residual evaluations (default: the calibration's own limit)."""


@dataclasses.dataclass(frozen=True)
class StartContext:
    """What an initialiser may use.

    Attributes
    ----------
    obs : Observations
    config : ModelConfig
        The configuration of the model to build (image size, split, fixed parameters).
    values : mapping of str to float
        Parameter values the user set (e.g. a glass index); applied to the start.
    seed : CameraModel or None
        A model of this kind with nominal design values given by the user.
    refine : Refine
    """

    obs: Observations
    config: ModelConfig
    values: Mapping[str, float]
    seed: CameraModel | None
    refine: Refine


Initialiser = Callable[[StartContext, "Start | None"], Start]
"""``start(ctx, base) -> Start``: a model's calibration start. ``base`` is the refined
start of its ``SEEDED_FROM`` model over the same observations (None for a model started
from the detections alone). Raises CalibrationError when no start can be found."""
