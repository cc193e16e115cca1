"""Simulator presets: plain JSON files describing the ground-truth probe and the protocol.

A preset holds the physical description of the simulated probe (sensor, lens, biprism,
illumination), the render settings, the targets and the image sets (SPEC section 9).
Built-in presets live in ``endomeasure/simulate/presets/NAME.json`` and are read with
:mod:`importlib.resources`; any other JSON file of the same form can be given by path.
``docs/simulator.md`` explains every number of the default preset.

The ground-truth optics is a :class:`~endomeasure.models.raytrace.RaytraceModel` with
the terms the calibrated models lack switched on (``k3``, ``p1``, ``p2``), its faces
tilted off the nominal design and its apex off the optical axis. The prism is given
physically: the front faces both pass through the apex point, so their distances
``d = n . apex`` follow from the tilts; the split column is where the apex images.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.models.base import ModelConfig
from endomeasure.models.raytrace import RaytraceModel, plane_normal

__all__ = [
    "Preset",
    "load_preset",
    "builtin_presets",
    "data_digest",
    "restrict_to_sets",
    "PRESET_FORMAT",
]

PRESET_FORMAT = "endomeasure-simulator-preset"
PRESET_VERSION = 1

_REQUIRED = ("sensor", "lens", "prism", "illumination", "render", "targets", "sets")


def data_digest(data: dict[str, Any]) -> str:
    """SHA-256 of the canonical JSON (sorted keys, no spaces) of preset data."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _targets_named(value: Any) -> set[str]:
    """Every ``"target"`` value anywhere inside a set's protocol."""
    found: set[str] = set()
    if isinstance(value, dict):
        for key, item in value.items():
            if key == "target" and isinstance(item, str):
                found.add(item)
            else:
                found |= _targets_named(item)
    elif isinstance(value, list):
        for item in value:
            found |= _targets_named(item)
    return found


def restrict_to_sets(data: dict[str, Any], set_names) -> dict[str, Any]:
    """Preset data reduced to some image sets and their targets (see :meth:`Preset.for_sets`).

    Raises
    ------
    ValueError
        A set the data does not define.
    """
    names = set(set_names)
    sets = data.get("sets", {})
    missing = sorted(names - set(sets))
    if missing:
        raise ValueError(f"the preset defines no {', '.join(map(repr, missing))} set")
    used: set[str] = set()
    for name in names:
        used |= _targets_named(sets[name])
    out: dict[str, Any] = {}
    for key, value in data.items():
        if key == "targets":
            value = {k: v for k, v in value.items() if k in used}
        elif key == "sets":
            value = {k: v for k, v in value.items() if k in names}
        out[key] = copy.deepcopy(value)
    return out


def builtin_presets() -> list[str]:
    """Names of the presets shipped with the package."""
    folder = resources.files("endomeasure.simulate") / "presets"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".json"))


def load_preset(name_or_path: str | Path) -> Preset:
    """Load a built-in preset by name, or a preset JSON file by path.

    Raises
    ------
    BadInputError
        Unknown name, unreadable file, or a file that is not a valid preset.
    """
    text: str
    source: str
    candidate = Path(str(name_or_path))
    if candidate.suffix == ".json" or candidate.exists():
        if not candidate.is_file():
            names = ", ".join(builtin_presets())
            raise BadInputError(
                "simulator preset file not found",
                path=str(candidate),
                hint=f"give a JSON file or one of the built-in presets: {names}",
            )
        text, source = candidate.read_text(encoding="utf-8"), str(candidate)
    else:
        name = str(name_or_path)
        resource = resources.files("endomeasure.simulate") / "presets" / f"{name}.json"
        if not resource.is_file():
            raise BadInputError(
                f"unknown simulator preset {name!r}",
                hint=f"use one of {', '.join(builtin_presets())} or the path of a preset JSON file",
            )
        text, source = resource.read_text(encoding="utf-8"), f"builtin:{name}"
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BadInputError(
            f"simulator preset is not valid JSON ({exc.msg}, line {exc.lineno})", path=source,
            hint="fix the file or start from src/endomeasure/simulate/presets/default.json",
        ) from None  # fmt: skip
    return Preset.from_dict(data, source=source)


@dataclasses.dataclass(frozen=True, eq=False)
class Preset:
    """A parsed simulator preset (see the module docstring).

    Attributes
    ----------
    data : dict
        The preset as plain data (a deep copy of the JSON document).
    source : str
        Where it came from (``builtin:NAME`` or a file path).
    """

    data: dict[str, Any]
    source: str = ""

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "") -> Preset:
        if not isinstance(data, dict) or data.get("format") != PRESET_FORMAT:
            raise BadInputError(
                f"not a simulator preset (format must be {PRESET_FORMAT!r})", path=source or None,
                hint="start from src/endomeasure/simulate/presets/default.json",
            )  # fmt: skip
        if int(data.get("version", 0)) != PRESET_VERSION:
            raise BadInputError(
                f"simulator preset version {data.get('version')!r} is not supported "
                f"(this version reads {PRESET_VERSION})",
                path=source or None,
            )
        missing = [k for k in _REQUIRED if k not in data]
        if missing:
            raise BadInputError(
                f"simulator preset lacks the section(s) {', '.join(missing)}", path=source or None
            )
        preset = cls(copy.deepcopy(data), source)
        try:
            preset.truth_model  # noqa: B018 - validates the optics now, not mid-render
            preset.supersampling  # noqa: B018
        except (KeyError, TypeError, ValueError) as exc:
            raise BadInputError(
                f"simulator preset has invalid optics ({type(exc).__name__}: {exc})",
                path=source or None,
            ) from None
        return preset

    # ----- identity ---------------------------------------------------------------------
    @property
    def name(self) -> str:
        return str(self.data.get("name", "unnamed"))

    @cached_property
    def digest(self) -> str:
        """SHA-256 of the canonical JSON of the preset: identifies its optics and protocol."""
        return data_digest(self.data)

    def for_sets(self, set_names) -> dict[str, Any]:
        """The preset's data as far as the given image sets depend on it.

        Everything but ``targets`` and ``sets``, plus the named sets and the targets they
        use, in the order of the preset (so the result does not depend on the order of
        ``set_names``). A simulated folder records this, so adding a set or a target to a
        preset does not change what the folders of its other sets say they were made of.

        Raises
        ------
        ValueError
            A set the preset does not define.
        """
        return restrict_to_sets(self.data, set_names)

    # ----- sections -----------------------------------------------------------------------
    @property
    def sensor(self) -> dict[str, Any]:
        return self.data["sensor"]

    @property
    def lens(self) -> dict[str, Any]:
        return self.data["lens"]

    @property
    def prism(self) -> dict[str, Any]:
        return self.data["prism"]

    @property
    def illumination(self) -> dict[str, Any]:
        return self.data["illumination"]

    @property
    def targets(self) -> dict[str, Any]:
        return self.data["targets"]

    @property
    def sets(self) -> dict[str, Any]:
        return self.data["sets"]

    @property
    def image_size(self) -> tuple[int, int]:
        width, height = self.sensor["image_size"]
        return int(width), int(height)

    @property
    def supersampling(self) -> int:
        n = int(self.data["render"]["supersampling"])
        if n < 1:
            raise ValueError("render.supersampling must be at least 1")
        return n

    @property
    def chunk_rays(self) -> int:
        return max(4096, int(self.data["render"].get("chunk_rays", 262144)))

    # ----- optics -------------------------------------------------------------------------
    @cached_property
    def apex_point(self) -> np.ndarray:
        """A point of the apex line (where the front faces meet), mm, camera frame."""
        return np.asarray(self.prism["apex_mm"], dtype=np.float64)

    def _truth_params(self) -> np.ndarray:
        lens, prism = self.lens, self.prism
        values = {k: float(lens[k]) for k in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2")}
        rear = prism["rear_face"]
        values.update(
            rear_a=np.radians(rear["a_deg"]), rear_b=np.radians(rear["b_deg"]), rear_d=rear["d_mm"]
        )
        for face in ("left", "right"):
            a = np.radians(prism[f"{face}_face"]["a_deg"])
            b = np.radians(prism[f"{face}_face"]["b_deg"])
            values[f"{face}_a"], values[f"{face}_b"] = a, b
            values[f"{face}_d"] = float(plane_normal(a, b) @ self.apex_point)
        values["n_glass"] = float(prism["n_glass"])
        return np.array([values[n] for n in RaytraceModel.PARAM_NAMES], dtype=np.float64)

    @cached_property
    def split(self) -> int:
        """First column of the right half: the column boundary nearest the apex image."""
        from endomeasure.simulate.optics import apex_columns

        width, height = self.image_size
        provisional = RaytraceModel(self._truth_params(), ModelConfig((width, height), width // 2))
        u = apex_columns(provisional, np.array([(height - 1) / 2.0]))[0]
        return int(np.floor(u + 1.0))  # the boundary u = split - 0.5 nearest the apex

    @cached_property
    def truth_model(self) -> RaytraceModel:
        """The ground-truth optics (every parameter free in its configuration)."""
        return RaytraceModel(self._truth_params(), ModelConfig(self.image_size, self.split))

    @property
    def aperture_mm(self) -> float:
        """Entrance-pupil diameter, mm: focal length / f-number (focal length = fx x pitch)."""
        focal_mm = float(self.lens["fx"]) * float(self.sensor["pixel_pitch_um"]) * 1e-3
        return focal_mm / float(self.lens["f_number"])

    def blur_diameter_px(self, distance_mm: np.ndarray) -> np.ndarray:
        """Geometric defocus blur-circle diameter on the sensor, px.

        ``c = A fx |1/z - 1/z_focus|`` for an object at distance ``z`` (thin-lens
        geometry: the pupil of diameter ``A`` seen from the object, scaled by ``fx``).
        """
        z = np.asarray(distance_mm, dtype=np.float64)
        with np.errstate(divide="ignore"):
            return (
                self.aperture_mm
                * float(self.lens["fx"])
                * np.abs(1.0 / z - 1.0 / float(self.lens["best_focus_mm"]))
            )

    def blur_sigma_px(self, distance_mm: np.ndarray) -> np.ndarray:
        """Gaussian sigma of the point-spread function at a distance, px.

        The blur disc of diameter ``c`` has standard deviation ``c / 4``; it adds in
        quadrature to the in-focus PSF (lens + pixel crosstalk) ``psf_sigma_px``.
        """
        c = self.blur_diameter_px(distance_mm)
        return np.sqrt(float(self.lens["psf_sigma_px"]) ** 2 + (c / 4.0) ** 2)

    @property
    def apex_band_sigma_px(self) -> float:
        """Width (sigma) of the dark band the out-of-focus apex casts, px."""
        return float(self.blur_diameter_px(self.apex_point[2]) / 4.0)

    def to_dict(self) -> dict[str, Any]:
        return copy.deepcopy(self.data)
