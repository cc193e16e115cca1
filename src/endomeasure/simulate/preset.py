"""Simulator presets: plain JSON files describing the ground-truth probe and the protocol.

A preset holds the physical description of the simulated probe (sensor, lens, biprism,
illumination), the render settings, the targets and the image sets (SPEC section 9).
Built-in presets live in ``endomeasure/simulate/presets/NAME.json`` and are read with
:mod:`importlib.resources`; any other JSON file of the same form can be given by path.
``docs/simulator.md`` explains every number of the default preset.

The ground-truth optics is :class:`~endomeasure.simulate.truth_optics.TruthOptics`, the
simulator's own tracer (not the calibrated models' code), with the effects the models lack
(``k3 k4 p1 p2``, distortion defined either way, a moving pupil, general faces). The
prism is given physically: a front face without ``d_mm`` passes through the apex point
(moved by ``offset_mm`` along its normal), so ``d = n . apex + offset``; the split
column is where the apex images. :attr:`Preset.truth_model` is the nearest
``raytrace`` model, the truth itself where that family can hold it.
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
from endomeasure.models.raytrace import RaytraceModel
from endomeasure.simulate.truth_optics import LensMap, Plane, TruthConfig, TruthLens, TruthOptics

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
                "simulator preset file not found"
                if not candidate.exists()
                else "the simulator preset is not a regular file",
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
            preset.truth_optics  # noqa: B018 - validates the optics now, not mid-render
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

    def _face(self, name: str) -> Plane:
        """A prism face from the preset: ``normal`` or tilts ``a_deg b_deg`` (normal
        ``(tan a, tan b, 1)``), and ``d_mm``, or for a front face without ``d_mm`` the
        plane through the apex point moved by ``offset_mm`` (default 0) along its normal."""
        face = self.prism[f"{name}_face"]
        if "normal" in face:
            normal = np.asarray(face["normal"], dtype=np.float64)
        else:
            normal = np.array(
                [np.tan(np.radians(face["a_deg"])), np.tan(np.radians(face["b_deg"])), 1.0]
            )
        normal = normal / np.linalg.norm(normal)
        if "d_mm" in face:
            d = float(face["d_mm"])
        elif name == "rear":
            raise KeyError("rear_face.d_mm")
        else:
            d = float(normal @ self.apex_point) + float(face.get("offset_mm", 0.0))
        return Plane.make(normal, d)

    def _truth_lens(self) -> TruthLens:
        lens = self.lens
        radial = tuple(float(lens.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4"))
        shift = float(lens.get("pupil_shift_mm", 0.0))
        return TruthLens(
            fx=float(lens["fx"]), fy=float(lens["fy"]), cx=float(lens["cx"]), cy=float(lens["cy"]),
            distortion=LensMap(radial, float(lens.get("p1", 0.0)), float(lens.get("p2", 0.0))),
            direction=str(lens.get("distortion_direction", "ray_to_pixel")),
            pupil_shift_mm=shift,
            pupil_edge_rad=np.radians(float(lens.get("pupil_edge_deg", 45.0))),
        )  # fmt: skip

    @cached_property
    def truth_optics(self) -> TruthOptics:
        """The ground-truth optics (:mod:`.truth_optics`), its split at the apex image."""
        width, height = self.image_size
        provisional = TruthOptics(
            self._truth_lens(), self._face("rear"), self._face("left"), self._face("right"),
            float(self.prism["n_glass"]), TruthConfig((width, height), width // 2),
        )  # fmt: skip
        return provisional.with_split(provisional.apex_split())

    @property
    def split(self) -> int:
        """First column of the right half: the column boundary nearest the apex image."""
        return self.truth_optics.config.split

    @cached_property
    def raytrace_representable(self) -> bool:
        """Whether the ``raytrace`` model family holds the truth exactly: distortion
        defined ray -> pixel without an ``r^8`` term, and an entrance pupil the model's
        ``e1 theta^2`` holds (any, where the model has ``e1``; else a fixed one)."""
        lens = self.truth_optics.lens
        pupil_ok = "e1" in RaytraceModel.PARAM_NAMES or lens.pupil_shift_mm == 0.0
        return lens.direction == "ray_to_pixel" and lens.distortion.radial[3] == 0.0 and pupil_ok

    def _truth_params(self) -> np.ndarray:
        optics = self.truth_optics
        lens = optics.lens
        values = {"fx": lens.fx, "fy": lens.fy, "cx": lens.cx, "cy": lens.cy}
        values.update(zip(("k1", "k2", "k3"), lens.distortion.radial[:3], strict=True))
        values.update(p1=lens.distortion.p1, p2=lens.distortion.p2)
        for name, plane in (("rear", optics.rear), ("left", optics.left), ("right", optics.right)):
            nx, ny, nz = plane.normal
            values[f"{name}_a"] = float(np.arctan(nx / nz))
            values[f"{name}_b"] = float(np.arctan(ny / nz))
            values[f"{name}_d"] = plane.d  # the same unit normal, so the same distance
        values["n_glass"] = optics.n_glass
        # the pupil law z = shift (theta / theta_edge)^2 is the model's e1 theta^2
        values["e1"] = lens.pupil_shift_mm / lens.pupil_edge_rad**2
        # every other term the model may have (a rational radial denominator, image-side
        # decentring, ...) is absent from the truth: 0
        return np.array([values.get(n, 0.0) for n in RaytraceModel.PARAM_NAMES], dtype=np.float64)

    @cached_property
    def truth_model(self) -> RaytraceModel:
        """The ``raytrace`` model nearest the truth: the truth itself when
        :attr:`raytrace_representable`, else the same numbers without the extra effects
        (an approximate seed for calibration, not the simulator's optics)."""
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
