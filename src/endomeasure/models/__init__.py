"""Camera models of the split-sensor probe: the contract, ``pinhole`` and ``raytrace``."""

from endomeasure.models.base import CameraModel, ModelConfig, Projection, ProjectionJacobian, Rays
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.raytrace import RaytraceModel
from endomeasure.models.registry import MODELS, model_class, model_from_dict

__all__ = [
    "CameraModel",
    "ModelConfig",
    "Projection",
    "ProjectionJacobian",
    "Rays",
    "PinholeModel",
    "RaytraceModel",
    "MODELS",
    "model_class",
    "model_from_dict",
]
