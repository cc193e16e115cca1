"""Camera models by registry name, each with its calibration start, and their plain-data
round trip."""

from __future__ import annotations

from typing import Any

from endomeasure.models.base import CameraModel
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.pinhole_start import initial_pinhole
from endomeasure.models.raytrace import RaytraceModel
from endomeasure.models.raytrace_start import seed_raytrace
from endomeasure.models.start import Initialiser

__all__ = [
    "MODELS",
    "model_class",
    "model_from_dict",
    "model_start",
    "register_model",
    "unregister_model",
]

MODELS: dict[str, type[CameraModel]] = {}
"""Every known model class by ``NAME``, in registration order (a model seeded from
another is registered after it)."""
_STARTS: dict[str, Initialiser] = {}


def register_model(cls: type[CameraModel], start: Initialiser) -> type[CameraModel]:
    """Make a model class known by its ``NAME`` to every command.

    Parameters
    ----------
    cls : type of CameraModel
        Fulfils the contract of :class:`CameraModel` completely; its ``SEEDED_FROM``
        model, if any, is already registered.
    start : Initialiser
        ``start(ctx, base) -> Start``: the model's calibration start
        (:mod:`endomeasure.models.start`).
    """
    name = getattr(cls, "NAME", None)
    if not isinstance(name, str) or not name:
        raise ValueError(f"{cls.__name__} has no NAME")
    if MODELS.get(name, cls) is not cls:
        raise ValueError(f"another model is already registered as {name!r}")
    if cls.SEEDED_FROM is not None and cls.SEEDED_FROM not in MODELS:
        raise ValueError(f"{name} is seeded from {cls.SEEDED_FROM!r}, which is not registered")
    missing = set(cls.PARAM_NAMES) - set(getattr(cls, "PARAM_UNITS", {}))
    if missing:
        raise ValueError(f"{name} gives no unit for {sorted(missing)}")
    MODELS[name] = cls
    _STARTS[name] = start
    return cls


def unregister_model(name: str) -> None:
    """Forget a registered model (for tests that register one of their own)."""
    MODELS.pop(name, None)
    _STARTS.pop(name, None)


def model_start(name: str) -> Initialiser:
    """The calibration start registered with a model."""
    model_class(name)
    return _STARTS[name]


register_model(PinholeModel, initial_pinhole)
register_model(RaytraceModel, seed_raytrace)


def model_class(name: str) -> type[CameraModel]:
    """The model class registered under ``name`` (KeyError naming the known ones)."""
    try:
        return MODELS[name]
    except KeyError:
        raise KeyError(
            f"unknown camera model {name!r}; known: {', '.join(sorted(MODELS))}"
        ) from None


def model_from_dict(data: dict[str, Any]) -> CameraModel:
    """Rebuild a model from :meth:`CameraModel.to_dict` output."""
    return model_class(data["model"]).from_dict(data)
