"""Camera models of the split-sensor probe: the contract, the two models, the registry."""

from endomeasure.models.base import (
    CameraModel,
    ModelConfig,
    OpenCVStereo,
    Projection,
    ProjectionJacobian,
    ProjectionJacobians,
    Rays,
)
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.raytrace import RaytraceModel
from endomeasure.models.registry import (
    MODELS,
    model_class,
    model_from_dict,
    model_start,
    register_model,
    unregister_model,
)

__all__ = [
    "CameraModel",
    "ModelConfig",
    "OpenCVStereo",
    "Projection",
    "ProjectionJacobian",
    "ProjectionJacobians",
    "Rays",
    "PinholeModel",
    "RaytraceModel",
    "MODELS",
    "model_class",
    "model_from_dict",
    "model_start",
    "register_model",
    "unregister_model",
]
