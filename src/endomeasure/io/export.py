"""Export a stored camera model: JSON for every model, OpenCV FileStorage YAML for ``pinhole``.

JSON (``--format json``): the model's plain description (:meth:`CameraModel.to_dict`:
registry name, parameter names and values, configuration) plus, when the model is a
calibration result, its free parameters, their standard deviations and covariance, and
the RMS residuals. :func:`endomeasure.models.model_from_dict` reads it back (and
``endomeasure calibrate --seed`` accepts it as a seed).

OpenCV YAML (``--format opencv-yaml``, ``pinhole`` only), readable by
``cv2.FileStorage``: ``M1``, ``D1``, ``M2``, ``D2`` (camera matrices and distortion
``k1 k2 p1 p2 k3`` of the left and right virtual cameras), ``R``, ``T`` (right camera
from left, ``stereoCalibrate``'s convention, mm), ``image_width``, ``image_height``,
``split``. Both principal points are in full-image pixel coordinates, as everywhere in
endomeasure; for OpenCV functions that take the right half as its own image, subtract
``split`` from ``M2[0, 2]``.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.io.outputs import file_kind, is_regular_file

__all__ = [
    "EXPORT_FORMATS",
    "export_model",
    "model_document",
    "read_model_document",
    "read_model_file",
    "read_opencv_yaml",
    "write_map_csv",
]

EXPORT_FORMATS = ("json", "opencv-yaml")


def model_document(model, extras: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON document of a model (plus calibration extras such as covariance)."""
    doc = model.to_dict()
    if extras:
        doc["calibration"] = extras
    return doc


def read_model_document(path: str | Path, what: str = "model file") -> dict[str, Any]:
    """The JSON document of a model file (as :func:`export_model` writes it, or wrapped
    under ``camera_model`` as the simulator's truth files hold it)."""
    if os.path.exists(path) and not is_regular_file(path):  # a FIFO would block the read
        raise BadInputError(
            f"the {what} is a {file_kind(os.stat(path).st_mode)}, not a file", path=str(path)
        )
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise BadInputError(f"cannot read the {what} ({exc})", path=str(path)) from None
    if isinstance(data, dict) and "model" not in data and "camera_model" in data:
        data = data["camera_model"]
    if not isinstance(data, dict):
        raise BadInputError(f"the {what} is not a model document", path=str(path))
    return data


def read_model_file(path: str | Path):
    """The camera model of a model file (:func:`read_model_document`)."""
    from endomeasure.models import model_from_dict

    data = read_model_document(path)
    try:
        return model_from_dict(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise BadInputError(
            f"not a camera model ({exc})",
            path=str(path),
            hint="write it with `endomeasure export` or model.to_json()",
        ) from None


def write_map_csv(error_map, path: str | Path) -> Path:
    """An error map (:class:`~endomeasure.measure.predict.ErrorMap`) as CSV: one row per
    grid point, the centre (mm), whether the template is seen, the predicted value, bias,
    std and its image and calibration parts (the kind's unit)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    em = error_map
    data = np.column_stack([em.centres, em.visible, *em.errors])
    np.savetxt(
        path,
        data,
        delimiter=",",
        fmt="%.9g",
        header=",".join(("x_mm", "y_mm", "z_mm", "visible", *em.errors._fields)),
        comments="",
    )
    return path


def _atomic_write(path: Path, write) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it over ``path``.

    The temporary name keeps ``path``'s suffix (``cv2.FileStorage`` picks the format by it).
    """
    tmp = path.with_name(f".tmp{os.getpid()}-{path.name}")
    try:
        write(tmp)
        if path.exists():  # a replaced file keeps its permissions
            shutil.copymode(path, tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def export_model(model, fmt: str, out: str | Path, extras: dict[str, Any] | None = None) -> Path:
    """Write ``model`` to ``out`` in format ``fmt`` (see the module docstring).

    Parameters
    ----------
    model : CameraModel
    fmt : {'json', 'opencv-yaml'}
    out : path
    extras : dict, optional
        Calibration figures to add to the JSON document.

    Returns
    -------
    Path
        The written file (written atomically: a temporary file renamed into place).
    """
    out = Path(out)
    if fmt not in EXPORT_FORMATS:
        raise BadInputError(f"unknown export format {fmt!r}; choose {' or '.join(EXPORT_FORMATS)}")
    if not out.parent.is_dir():
        raise BadInputError("the output folder does not exist", path=str(out.parent))
    if fmt == "json":
        text = json.dumps(model_document(model, extras), indent=2) + "\n"
        _atomic_write(out, lambda p: p.write_text(text))
        return out
    stereo = model.opencv_stereo()
    if stereo is None:
        raise BadInputError(
            f"the {model.NAME} model has no OpenCV stereo equivalent (two pinhole cameras "
            "with Brown distortion)",
            hint="export it as json",
        )
    import cv2

    def write(path: Path) -> None:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        if not fs.isOpened():
            raise BadInputError("cannot write the YAML file", path=str(out))
        for tag in ("M1", "D1", "M2", "D2", "R"):
            value = getattr(stereo, tag)
            fs.write(tag, value.reshape(1, -1) if value.ndim == 1 else value)
        fs.write("T", stereo.T.reshape(3, 1))
        fs.write("image_width", int(model.config.image_size[0]))
        fs.write("image_height", int(model.config.image_size[1]))
        fs.write("split", int(model.config.split))
        fs.release()

    suffix_ok = out.suffix.lower() in (".yml", ".yaml")
    if not suffix_ok:
        raise BadInputError("an OpenCV YAML file must end in .yml or .yaml", path=str(out))
    _atomic_write(out, write)
    return out


def read_opencv_yaml(path: str | Path) -> dict[str, np.ndarray]:
    """Read back an exported pinhole YAML with ``cv2.FileStorage`` (arrays by tag)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise BadInputError("cannot read the OpenCV YAML file", path=str(path))
    try:
        out = {tag: fs.getNode(tag).mat() for tag in ("M1", "D1", "M2", "D2", "R", "T")}
        for tag in ("image_width", "image_height", "split"):
            out[tag] = int(fs.getNode(tag).real())
    finally:
        fs.release()
    return out
