"""Export a stored camera model: JSON for every model, files other tools read for ``pinhole``,
and a table of every pixel's ray for any model.

``docs/exports.md`` describes each format for the reader of the files; here each is
said once, for the writer.

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

The per-half formats (``ros-yaml`` and ``mrcal``, ``pinhole`` only) write one file per
half, each half as an image of its own (width: the half's columns; the right principal
point shifted left by ``split``): ``OUT`` = ``probe.yaml`` gives ``probe_left.yaml`` and
``probe_right.yaml`` beside it (:func:`export_files`).

ROS YAML (``--format ros-yaml``): a ``sensor_msgs/CameraInfo`` calibration file as ROS's
``camera_calibration_parsers`` writes it: ``image_width``, ``image_height``,
``camera_name``, ``camera_matrix`` (3x3), ``distortion_model: plumb_bob``,
``distortion_coefficients`` (1x5, ``k1 k2 p1 p2 k3``), ``rectification_matrix`` and
``projection_matrix`` (3x4) from ``cv2.stereoRectify`` of the pair (``alpha`` 0, zero
disparity at infinity, the left half's image size), as ROS's stereo calibrator makes
them: the right ``P[0, 3]`` is ``-fx' * baseline`` (mm).

mrcal (``--format mrcal``): a ``.cameramodel`` file, the Python-literal dict mrcal reads:
``lensmodel`` ``LENSMODEL_OPENCV5``, ``intrinsics`` ``fx fy cx cy k1 k2 p1 p2 k3``,
``extrinsics`` ``rt_cam_ref`` (Rodrigues vector, then translation, mm) with the left
camera as the reference (identity for the left file, ``T_right_left`` for the right),
``imagersize``.

Ray table (``--format ray-table``, any model, meant for the non-central ``raytrace``):
an HDF5 file with, per half, the ray (:meth:`CameraModel.rays`) through every pixel
centre of that half: ``origin`` and unit ``direction`` (H, W_half, 3) in the model frame
(mm), ``valid`` (H, W_half) 1 where the ray exists (else the ray is NaN and ``status``
says why), and the pixel coordinates ``pixel_x`` (W_half,) and ``pixel_y`` (H,) in
full-image pixels; attributes name the model, the units, the frame and the format
version (:data:`RAY_TABLE_VERSION`).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.errors import BadInputError
from endomeasure.io.outputs import atomic_write, file_kind, is_regular_file

__all__ = [
    "EXPORT_FORMATS",
    "RAY_TABLE_VERSION",
    "export_files",
    "export_model",
    "model_document",
    "read_model_document",
    "read_model_file",
    "read_opencv_yaml",
    "write_json_document",
    "write_map_csv",
]

EXPORT_FORMATS = ("json", "opencv-yaml", "ros-yaml", "mrcal", "ray-table")

_SUFFIXES = {
    "opencv-yaml": (".yml", ".yaml"),
    "ros-yaml": (".yml", ".yaml"),
    "mrcal": (".cameramodel",),
    "ray-table": (".h5", ".hdf5"),
}
"""Suffixes a format's file must end in (the readers of YAML and .cameramodel files, and
``cv2.FileStorage``, pick the format by it); json takes any name."""
_PER_HALF = ("ros-yaml", "mrcal")
"""Formats that describe one camera per file: one file per half."""
_HALVES = ("left", "right")

RAY_TABLE_VERSION = "1.0"
"""``format_version`` of the ray table (MAJOR.MINOR; a minor version only adds)."""


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


def write_json_document(document: dict[str, Any], path: str | Path) -> Path:
    """Write a JSON document atomically (a model file, a preset), indented."""
    path = Path(path)
    text = json.dumps(document, indent=1) + "\n"
    atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
    return path


def export_files(fmt: str, out: str | Path) -> tuple[Path, ...]:
    """The files :func:`export_model` writes for ``out`` in format ``fmt``: ``out`` itself,
    or for a per-half format ``<stem>_left<suffix>`` and ``<stem>_right<suffix>`` beside it.

    An unknown format or a suffix the format's readers would not take is a
    :class:`BadInputError`, before anything is computed.
    """
    out = Path(out)
    if fmt not in EXPORT_FORMATS:
        raise BadInputError(f"unknown export format {fmt!r}; choose {', '.join(EXPORT_FORMATS)}")
    allowed = _SUFFIXES.get(fmt)
    if allowed is not None and out.suffix.lower() not in allowed:
        what = {"opencv-yaml": "an OpenCV YAML", "ros-yaml": "a ROS YAML"}.get(fmt, f"a {fmt}")
        raise BadInputError(
            f"{what} file must end in {' or '.join(allowed)}",
            path=str(out),
            hint=f"give a name ending in {allowed[0]}",
        )
    if fmt not in _PER_HALF:
        return (out,)
    return tuple(out.with_name(f"{out.stem}_{half}{out.suffix}") for half in _HALVES)


def export_model(
    model,
    fmt: str,
    out: str | Path,
    extras: dict[str, Any] | None = None,
    files: tuple[Path, ...] | None = None,
) -> tuple[Path, ...]:
    """Write ``model`` to ``out`` in format ``fmt`` (see the module docstring).

    Parameters
    ----------
    model : CameraModel
    fmt : {'json', 'opencv-yaml', 'ros-yaml', 'mrcal', 'ray-table'}
    out : path
    extras : dict, optional
        Calibration figures to add to the JSON document.
    files : tuple of Path, optional
        The files to write, as :func:`export_files` names them and the output checks
        passed them (a symlink resolved to its target); default: those names.

    Returns
    -------
    tuple of Path
        The written files (each written atomically: a temporary file renamed into place).
    """
    out = Path(out)
    names = export_files(fmt, out)
    files = names if files is None else tuple(Path(f) for f in files)
    for folder in {f.parent for f in files}:
        if not folder.is_dir():
            raise BadInputError("the output folder does not exist", path=str(folder))
    if fmt == "json":
        text = json.dumps(model_document(model, extras), indent=2) + "\n"
        atomic_write(files[0], lambda p: p.write_text(text))
    elif fmt == "ray-table":
        _write_ray_table(model, files[0])
    else:
        stereo = _opencv_pair(model)
        if fmt == "opencv-yaml":
            _write_opencv_yaml(model, stereo, files[0])
        elif fmt == "ros-yaml":
            texts = _ros_yaml_texts(model, stereo, out.stem)
        else:
            texts = _mrcal_texts(model, stereo)
        if fmt in _PER_HALF:
            for path, text in zip(files, texts, strict=True):
                atomic_write(path, lambda p, text=text: p.write_text(text))
    return files


def _opencv_pair(model):
    """``model.opencv_stereo()``, or the one-line refusal of a model that has none."""
    stereo = model.opencv_stereo()
    if stereo is None:
        raise BadInputError(
            f"the {model.NAME} model has no OpenCV stereo equivalent (two pinhole cameras "
            "with Brown distortion)",
            hint="export it as json or ray-table",
        )
    return stereo


def _write_opencv_yaml(model, stereo, out: Path) -> None:
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

    atomic_write(out, write)


def _half_cameras(model, stereo) -> tuple[np.ndarray, np.ndarray, tuple[int, int], tuple[int, int]]:
    """The camera matrices of the two halves as images of their own (the right principal
    point shifted by ``split``) and the two halves' image sizes ``(width, height)``."""
    width, height = model.config.image_size
    split = model.config.split
    K2 = stereo.M2.copy()
    K2[0, 2] -= split
    return stereo.M1.copy(), K2, (split, height), (width - split, height)


def _ros_rectification(model, stereo) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``R1, R2, P1, P2`` of the pair as ROS's stereo calibrator computes them:
    ``cv2.stereoRectify`` of the halves as their own images, ``alpha`` 0, zero disparity,
    the left half's image size."""
    import cv2

    K1, K2, size, _ = _half_cameras(model, stereo)
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        K1, stereo.D1, K2, stereo.D2, size, stereo.R, stereo.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0,
    )  # fmt: skip
    return R1, R2, P1, P2


def _number(x: float) -> str:
    """A float as YAML and Python both read it back exactly: the shortest round-trip
    form, with a decimal point before any exponent (YAML 1.1 reads ``1e-05`` as text)."""
    text = repr(float(x))
    mantissa, e, exponent = text.partition("e")
    if e and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


def _numbers(values) -> str:
    return ", ".join(_number(v) for v in np.asarray(values, dtype=np.float64).ravel())


def _ros_yaml_texts(model, stereo, stem: str) -> list[str]:
    """The ROS calibration YAML of each half (see the module docstring)."""
    from endomeasure import __version__

    K1, K2, size1, size2 = _half_cameras(model, stereo)
    R1, R2, P1, P2 = _ros_rectification(model, stereo)
    name = re.sub(r"[^A-Za-z0-9_]", "_", stem) or "endoscope"
    texts = []
    for half, K, D, size, R, P in (
        ("left", K1, stereo.D1, size1, R1, P1),
        ("right", K2, stereo.D2, size2, R2, P2),
    ):
        lines = [
            f"# endomeasure {__version__}: the {half} half of the {model.NAME} model as an image "
            f"of its own (columns {'0' if half == 'left' else model.config.split}.. of the "
            "sensor); lengths in mm",
            f"image_width: {size[0]}",
            f"image_height: {size[1]}",
            f"camera_name: {name}_{half}",
        ]
        for key, value, value_rows, value_cols in (
            ("camera_matrix", K, 3, 3),
            ("distortion_model", "plumb_bob", 0, 0),
            ("distortion_coefficients", D, 1, 5),
            ("rectification_matrix", R, 3, 3),
            ("projection_matrix", P, 3, 4),
        ):
            if isinstance(value, str):
                lines.append(f"{key}: {value}")
                continue
            lines += [f"{key}:", f"  rows: {value_rows}", f"  cols: {value_cols}",
                      f"  data: [{_numbers(value)}]"]  # fmt: skip
        texts.append("\n".join(lines) + "\n")
    return texts


def _mrcal_texts(model, stereo) -> list[str]:
    """The mrcal ``.cameramodel`` of each half (see the module docstring)."""
    from endomeasure import __version__

    K1, K2, size1, size2 = _half_cameras(model, stereo)
    rvec, tvec = _rvec_right_left(stereo.R), stereo.T
    texts = []
    for half, K, D, size, rt in (
        ("left", K1, stereo.D1, size1, np.zeros(6)),
        ("right", K2, stereo.D2, size2, np.concatenate([rvec, tvec])),
    ):
        intrinsics = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *D]
        texts.append(
            f"# endomeasure {__version__}: the {half} half of the {model.NAME} model as an "
            "image of its own\n"
            "# units: mm (mrcal keeps the units it is given; endomeasure's lengths are mm)\n"
            "{\n"
            "    'lensmodel': 'LENSMODEL_OPENCV5',\n"
            "    # intrinsics are fx,fy,cx,cy,k1,k2,p1,p2,k3 (px; cx of this half's own image)\n"
            f"    'intrinsics': [ {_numbers(intrinsics)} ],\n"
            "    # extrinsics are rt_cam_ref: Rodrigues r, then t (mm); the reference is the\n"
            "    # left camera\n"
            f"    'extrinsics': [ {_numbers(rt)} ],\n"
            f"    'imagersize': [ {int(size[0])}, {int(size[1])} ],\n"
            "}\n"
        )
    return texts


def _rvec_right_left(R: np.ndarray) -> np.ndarray:
    """The Rodrigues vector of the rotation matrix ``R`` (3,)."""
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


RAY_TABLE_FRAME = (
    "the model frame: x right, y down, z forward, origin at the lens projection centre "
    "(pinhole: the left virtual camera's centre and axes)"
)
RAY_TABLE_DESCRIPTION = """\
endomeasure ray table: the ray in space that each pixel centre of the sensor sees.
Groups 'left' and 'right', one per half of the split sensor, each with
  origin     (H, W_half, 3) float64, mm: a point of the ray, in the model frame;
  direction  (H, W_half, 3) float64: its unit direction (the ray goes to +z);
  valid      (H, W_half) uint8: 1 where the ray exists; 0: origin and direction NaN;
  status     (H, W_half) uint8: why not (status_codes attribute);
  pixel_x    (W_half,) float64 and pixel_y (H,): the pixel centre of each column and row
             in full-image pixels (the top-left pixel's centre is 0,0; the right half keeps
             its sensor columns), so element [i, j] is the ray of pixel (pixel_x[j], pixel_y[i]).
The frame is in the 'frame' attribute, the model in 'model' and 'model_document' (JSON);
endomeasure's docs/exports.md says more."""


def _write_ray_table(model, out: Path) -> None:
    """The ray table of ``model`` (see the module docstring) at ``out``."""
    import h5py

    from endomeasure import __version__

    width, height = model.config.image_size
    split = model.config.split
    tables = {}
    for half, columns in ((Half.LEFT, np.arange(split)), (Half.RIGHT, np.arange(split, width))):
        pixel_x = columns.astype(np.float64)
        pixel_y = np.arange(height, dtype=np.float64)
        grid = np.stack(np.meshgrid(pixel_x, pixel_y), axis=-1)  # (H, W_half, 2)
        tables[half.label] = (pixel_x, pixel_y, model.rays(grid, half))

    def write(path: Path) -> None:
        with h5py.File(path, "w") as f:
            f.attrs.update(
                {
                    "endomeasure_format": "ray-table",
                    "format_version": RAY_TABLE_VERSION,
                    "created_by": f"endomeasure {__version__}",
                    "model": model.NAME,
                    "model_document": json.dumps(model.to_dict()),
                    "units": "mm",
                    "frame": RAY_TABLE_FRAME,
                    "image_width": width,
                    "image_height": height,
                    "split": split,
                    "status_codes": json.dumps({s.name: int(s) for s in Status}),
                    "description": RAY_TABLE_DESCRIPTION,
                }
            )
            for label, (pixel_x, pixel_y, rays) in tables.items():
                g = f.create_group(label)
                options = {"compression": "gzip", "shuffle": True}
                g.create_dataset("origin", data=rays.origins, **options)
                g.create_dataset("direction", data=rays.directions, **options)
                g.create_dataset("valid", data=(rays.status == Status.OK).astype(np.uint8))
                g.create_dataset("status", data=rays.status)
                g.create_dataset("pixel_x", data=pixel_x)
                g.create_dataset("pixel_y", data=pixel_y)
                g["origin"].attrs["units"] = "mm"
                g["pixel_x"].attrs["units"] = g["pixel_y"].attrs["units"] = "px"

    atomic_write(out, write)


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
