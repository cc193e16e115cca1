"""Camera models by registry name, and their plain-data round trip."""

from __future__ import annotations

from typing import Any

from endomeasure.models.base import CameraModel
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.raytrace import RaytraceModel

__all__ = ["MODELS", "model_class", "model_from_dict"]

MODELS: dict[str, type[CameraModel]] = {cls.NAME: cls for cls in (PinholeModel, RaytraceModel)}


def model_class(name: str) -> type[CameraModel]:
    """The model class registered under ``name`` (``'pinhole'`` or ``'raytrace'``)."""
    try:
        return MODELS[name]
    except KeyError:
        raise KeyError(
            f"unknown camera model {name!r}; known: {', '.join(sorted(MODELS))}"
        ) from None


def model_from_dict(data: dict[str, Any]) -> CameraModel:
    """Rebuild a model from :meth:`CameraModel.to_dict` output."""
    return model_class(data["model"]).from_dict(data)
