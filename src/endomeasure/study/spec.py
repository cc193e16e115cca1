"""The sweep spec: design ranges, tolerance draws, calibration protocol, figures of merit.

A spec is a JSON document (``docs/sweep.md`` describes every key)::

    {"preset": "default", "seed": 0,
     "designs": {"wedge_deg": {"set": {"prism.left_face.a_deg": -1,
                                       "prism.right_face.a_deg": 1},
                               "grid": {"linspace": [30, 38, 5]}},
                 "lens.fx": {"random": [280, 320]}},
     "random_designs": 4,
     "tolerances": {"draws": 5, "sigmas": {"prism.left_face.a_deg": 0.05}},
     "protocol": {"images_per_board": 4, "noise_px": 0.05, "start": "design"},
     "merit": {"templates": [{"template": "x-segment", "size_mm": 1.0}],
               "depths_mm": [30], "target_pct": 1.0},
     "cost": "prism_thickness_mm"}

An axis of ``designs`` is named by a dotted path into the preset (list items by their
index, ``prism.apex_mm.2``), or by any name with ``set`` (path -> scale: the path is
``scale * value``) or ``add`` (path -> scale: the preset's value plus ``scale * value``).
Grid axes form a product; random axes (``[lo, hi]``, uniform) draw ``random_designs``
values per grid point from the design's seed. :func:`parse_spec` validates everything,
every design's nominal optics included (:func:`~endomeasure.simulate.design.check_optics`),
before any work: a bad spec is one :class:`~endomeasure.errors.BadInputError`.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError

__all__ = [
    "SPEC_VERSION",
    "DERIVED_COSTS",
    "Axis",
    "SweepSpec",
    "parse_spec",
    "read_spec",
    "get_path",
    "set_path",
]

SPEC_VERSION = 1
START_CHOICES = ("design", "images")
DERIVED_COSTS = {
    "prism_thickness_mm": "apex distance minus rear-face distance along the axis",
    "prism_length_mm": "apex distance from the lens (how far the adapter reaches forward)",
}
_TOP_KEYS = {
    "version",
    "preset",
    "seed",
    "designs",
    "random_designs",
    "tolerances",
    "protocol",
    "merit",
    "cost",
    "description",
}
_PROTOCOL_KEYS = {"images_per_board", "calib", "targets", "noise_px", "model", "start"}
_MERIT_KEYS = {"templates", "depths_mm", "grid", "field_quantile", "sigmas", "target_pct"}
MAX_DESIGNS = 100_000
"""More designs than a cluster would finish in a day at the measured throughput."""


def _bad(what: str, hint: str | None = None) -> BadInputError:
    return BadInputError(f"sweep spec: {what}", hint=hint)


def get_path(data: Any, path: str) -> Any:
    """The value at a dotted path (list items by index); KeyError naming the first
    missing part."""
    node = data
    for part in path.split("."):
        if isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            raise KeyError(part)
    return node


def set_path(data: Any, path: str, value: float) -> None:
    """Set the value at an existing dotted path, in place."""
    *head, last = path.split(".")
    parent = get_path(data, ".".join(head)) if head else data
    parent[int(last) if isinstance(parent, list) else last] = value


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _bad(f"{what} must be a finite number, not {json.dumps(value)}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class Axis:
    """One design variable: the preset paths it drives, and its grid or random range."""

    name: str
    mode: str  # "set" or "add"
    paths: tuple[tuple[str, float], ...]  # (dotted path, scale)
    grid: tuple[float, ...] | None
    bounds: tuple[float, float] | None

    def apply(self, data: dict, base: dict, value: float) -> None:
        for path, scale in self.paths:
            offset = float(get_path(base, path)) if self.mode == "add" else 0.0
            set_path(data, path, offset + scale * value)


def _grid(value: Any, name: str) -> tuple[float, ...]:
    if isinstance(value, dict) and set(value) == {"linspace"}:
        lo_hi_n = value["linspace"]
        if not (isinstance(lo_hi_n, list) and len(lo_hi_n) == 3):
            raise _bad(f"axis {name!r}: linspace is [first, last, count]")
        lo, hi = (_number(v, f"axis {name!r} linspace") for v in lo_hi_n[:2])
        n = lo_hi_n[2]
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise _bad(f"axis {name!r} has an empty range (linspace count {n!r})")
        return tuple(float(v) for v in np.linspace(lo, hi, n))
    if not isinstance(value, list):
        raise _bad(f'axis {name!r}: grid is a list of values or {{"linspace": [a, b, n]}}')
    if not value:
        raise _bad(f"axis {name!r} has an empty range (grid [])")
    return tuple(_number(v, f"axis {name!r} grid value") for v in value)


def _axis(name: str, entry: Any, preset: dict) -> Axis:
    if not isinstance(entry, dict):
        raise _bad(f"axis {name!r} must be an object with grid or random")
    unknown = set(entry) - {"set", "add", "grid", "random"}
    if unknown:
        raise _bad(
            f"axis {name!r} has unknown key(s) {', '.join(sorted(unknown))}",
            "use set or add, and grid or random",
        )
    modes = [m for m in ("set", "add") if m in entry]
    if len(modes) > 1:
        raise _bad(f"axis {name!r} has both set and add")
    mode = modes[0] if modes else "set"
    mapping = entry[mode] if modes else {name: 1.0}
    if not isinstance(mapping, dict) or not mapping:
        raise _bad(f"axis {name!r}: {mode} maps preset paths to scales")
    paths = []
    for path, scale in mapping.items():
        try:
            current = get_path(preset, path)
        except KeyError as exc:
            raise _bad(
                f"unknown field {path!r} (no {exc.args[0]!r} in the preset)",
                "name a numeric preset field by its dotted path",
            ) from None
        if isinstance(current, bool) or not isinstance(current, (int, float)):
            raise _bad(f"field {path!r} is not a number in the preset")
        paths.append((path, _number(scale, f"axis {name!r} scale of {path!r}")))
    kinds = [k for k in ("grid", "random") if k in entry]
    if len(kinds) != 1:
        raise _bad(f"axis {name!r} needs exactly one of grid or random")
    grid = bounds = None
    if kinds[0] == "grid":
        grid = _grid(entry["grid"], name)
    else:
        rng = entry["random"]
        if not (isinstance(rng, list) and len(rng) == 2):
            raise _bad(f"axis {name!r}: random is [low, high]")
        lo, hi = (_number(v, f"axis {name!r} random bound") for v in rng)
        if not lo < hi:
            raise _bad(f"axis {name!r} has an empty range (random [{lo:g}, {hi:g}])")
        bounds = (lo, hi)
    return Axis(name, mode, tuple(paths), grid, bounds)


@dataclasses.dataclass(frozen=True)
class Template:
    template: str
    size_mm: float

    @property
    def label(self) -> str:
        return f"{self.template} {self.size_mm:g} mm"


@dataclasses.dataclass(frozen=True, eq=False)
class SweepSpec:
    """A validated sweep spec (see the module docstring); ``document`` is the JSON as
    given, ``preset`` the base preset's data."""

    document: dict[str, Any]
    preset: dict[str, Any]
    seed: int
    axes: tuple[Axis, ...]
    random_designs: int
    draws: int
    tolerances: tuple[tuple[str, float], ...]
    images_per_board: int | None
    calib: dict[str, Any]
    targets: dict[str, Any]
    noise_px: float
    model: str
    start: str
    templates: tuple[Template, ...]
    depths_mm: tuple[float, ...]
    grid: tuple[int, int]
    field_quantile: float
    sigmas: tuple[str, ...]
    target_pct: float
    cost: str

    @property
    def digest(self) -> str:
        from endomeasure.simulate.preset import data_digest

        return data_digest({"spec": self.document, "preset": self.preset})

    @property
    def n_grid(self) -> int:
        return math.prod(len(a.grid) for a in self.axes if a.grid is not None)

    @property
    def n_designs(self) -> int:
        return self.n_grid * (self.random_designs if self.has_random else 1)

    @property
    def has_random(self) -> bool:
        return any(a.bounds is not None for a in self.axes)

    @property
    def axis_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.axes)

    def design_seed(self, index: int) -> int:
        """The seed of design ``index``: its random values, poses, noise and draws."""
        return int(np.random.SeedSequence([self.seed, int(index)]).generate_state(1)[0])

    def design_values(self, index: int) -> tuple[float, ...]:
        """The axes' values of design ``index`` (grid-major, then the random repeats)."""
        per_grid = self.random_designs if self.has_random else 1
        grid_index, _ = divmod(int(index), per_grid)
        grids = [a.grid for a in self.axes if a.grid is not None]
        point = next(itertools.islice(itertools.product(*grids), grid_index, None)) if grids else ()
        rng = np.random.default_rng([self.design_seed(index), 0x72616E64])
        values, k = [], 0
        for a in self.axes:
            if a.grid is not None:
                values.append(float(point[k]))
                k += 1
            else:
                values.append(float(rng.uniform(*a.bounds)))
        return tuple(values)

    def design_preset(self, index: int) -> dict[str, Any]:
        """The nominal preset document of design ``index`` (axes and protocol applied)."""
        data = copy.deepcopy(self.preset)
        for axis, value in zip(self.axes, self.design_values(index), strict=True):
            axis.apply(data, self.preset, value)
        data["name"] = f"sweep-design-{int(index)}"
        values = ", ".join(
            f"{n} {v:.6g}" for n, v in zip(self.axis_names, self.design_values(index), strict=True)
        )
        data["description"] = (
            f"design {int(index)} of a sweep of {self.preset.get('name')}: {values}"
        )
        return data

    def drawn_preset(self, index: int, draw: int) -> dict[str, Any]:
        """The design's preset with one workshop's tolerances drawn (Gaussian sigmas)."""
        data = self.design_preset(index)
        rng = np.random.default_rng([self.design_seed(index), int(draw), 0x746F6C])
        for path, sigma in self.tolerances:
            set_path(data, path, float(get_path(data, path)) + sigma * float(rng.standard_normal()))
        return data


def _section(doc: dict, name: str, keys) -> dict[str, Any]:
    """The object ``doc[name]`` (empty when absent), refused unless it holds only ``keys``."""
    section = doc.get(name, {})
    if not isinstance(section, dict):
        raise _bad(f"{name} must be an object")
    unknown = set(section) - set(keys)
    if unknown:
        raise _bad(
            f"unknown {name} key(s) {', '.join(sorted(unknown))}",
            f"use {', '.join(sorted(keys))}",
        )
    return section


def _protocol(doc: dict) -> dict[str, Any]:
    protocol = _section(doc, "protocol", _PROTOCOL_KEYS)
    from endomeasure.models import MODELS

    n = protocol.get("images_per_board")
    if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 1):
        raise _bad(f"protocol.images_per_board must be a positive integer, not {n!r}")
    model = protocol.get("model", "raytrace")
    if model not in MODELS:
        raise _bad(f"unknown model {model!r}", f"use one of {', '.join(MODELS)}")
    start = protocol.get("start", "images")
    if start not in START_CHOICES:
        raise _bad(f"unknown start {start!r}", f"use one of {', '.join(START_CHOICES)}")
    noise = _number(protocol.get("noise_px", 0.05), "protocol.noise_px")
    if noise <= 0:
        raise _bad(f"protocol.noise_px must be positive, not {noise:g}")
    calib = protocol.get("calib", {})
    targets = protocol.get("targets", {})
    if not isinstance(calib, dict) or not isinstance(targets, dict):
        raise _bad("protocol.calib and protocol.targets are objects merged over the preset's")
    return {
        "images_per_board": n,
        "model": model,
        "start": start,
        "noise_px": noise,
        "calib": calib,
        "targets": targets,
    }


def _merit(doc: dict, model: str) -> dict[str, Any]:
    from endomeasure.measure.predict import TEMPLATES
    from endomeasure.models import model_class

    merit = _section(doc, "merit", _MERIT_KEYS)
    templates = []
    for t in merit.get("templates", [{"template": "x-segment", "size_mm": 1.0}]):
        name = t.get("template") if isinstance(t, dict) else None
        if name not in TEMPLATES:
            raise _bad(f"unknown template {name!r}", f"use one of {', '.join(TEMPLATES)}")
        if TEMPLATES[name][0] == "depth":
            raise _bad(
                f"template {name!r} measures a deviation of true value 0: it has no relative error",
                "use a segment or the area",
            )
        size = _number(t.get("size_mm", 1.0), f"template {name!r} size_mm")
        if size <= 0:
            raise _bad(f"template {name!r} size_mm must be positive")
        templates.append(Template(name, size))
    if not templates:
        raise _bad("merit.templates is empty")
    depths = merit.get("depths_mm", [30.0])
    if not isinstance(depths, list) or not depths:
        raise _bad("merit.depths_mm is an empty range", "give the depths, mm, of the maps")
    depths = [_number(d, "merit.depths_mm value") for d in depths]
    if min(depths) <= 0:
        raise _bad("merit.depths_mm must be positive")
    grid = merit.get("grid", [12, 9])
    if not (
        isinstance(grid, list)
        and len(grid) == 2
        and all(isinstance(g, int) and g >= 2 for g in grid)
    ):
        raise _bad(f"merit.grid is [NU, NV], at least 2 each, not {json.dumps(grid)}")
    quantile = _number(merit.get("field_quantile", 0.95), "merit.field_quantile")
    if not 0 < quantile <= 1:
        raise _bad("merit.field_quantile is in (0, 1]")
    sigmas = merit.get("sigmas", [])
    names = model_class(model).PARAM_NAMES
    for s in sigmas:
        if s not in names:
            raise _bad(f"unknown parameter {s!r} of the {model} model in merit.sigmas")
    target = _number(merit.get("target_pct", 1.0), "merit.target_pct")
    return {
        "templates": tuple(templates),
        "depths_mm": tuple(depths),
        "grid": tuple(grid),
        "field_quantile": quantile,
        "sigmas": tuple(sigmas),
        "target_pct": target,
    }


def _tolerances(doc: dict, preset: dict) -> tuple[int, tuple[tuple[str, float], ...]]:
    tol = doc.get("tolerances", {"draws": 1, "sigmas": {}})
    if not isinstance(tol, dict) or set(tol) - {"draws", "sigmas"}:
        raise _bad('tolerances is {"draws": N, "sigmas": {path: sigma}}')
    draws = tol.get("draws", 1)
    if not isinstance(draws, int) or isinstance(draws, bool) or draws < 1:
        raise _bad(f"tolerances.draws must be a positive integer, not {draws!r}")
    out = []
    for path, sigma in tol.get("sigmas", {}).items():
        try:
            value = get_path(preset, path)
        except KeyError as exc:
            raise _bad(
                f"unknown field {path!r} in tolerances (no {exc.args[0]!r} in the preset)"
            ) from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _bad(f"tolerance field {path!r} is not a number in the preset")
        sigma = _number(sigma, f"tolerance sigma of {path!r}")
        if sigma < 0:
            raise _bad(f"tolerance sigma of {path!r} is negative")
        out.append((path, sigma))
    return draws, tuple(out)


def _base_preset(doc: dict, protocol: dict) -> dict[str, Any]:
    from endomeasure.simulate.preset import load_preset

    name = doc.get("preset", "default")
    if not isinstance(name, str):
        raise _bad("preset is a built-in name or a preset JSON path")
    try:
        data = load_preset(name).to_dict()
    except BadInputError as exc:
        raise _bad(exc.one_line()) from None
    data["targets"].update(copy.deepcopy(protocol["targets"]))
    data["sets"]["calib"] = {**data["sets"].get("calib", {}), **copy.deepcopy(protocol["calib"])}
    calib = data["sets"]["calib"]
    boards = calib.get("boards")
    if not isinstance(boards, list) or not boards:
        raise _bad("the calibration protocol has no boards")
    for board in boards:
        if not isinstance(board, dict) or board.get("target") not in data["targets"]:
            raise _bad(f"calibration board {json.dumps(board)} names no target of the preset")
        if protocol["images_per_board"] is not None:
            board["images"] = protocol["images_per_board"]
    return data


def _check_designs(spec: SweepSpec) -> None:
    """Every design's nominal optics must be physical (checked on the nominal preset;
    tolerance draws that are not are recorded as infeasible, not refused)."""
    from endomeasure.simulate.design import DesignError, check_optics
    from endomeasure.simulate.preset import Preset

    for index in range(spec.n_designs):
        values = ", ".join(
            f"{n} {v:.4g}" for n, v in zip(spec.axis_names, spec.design_values(index), strict=True)
        )
        try:
            check_optics(Preset.from_dict(spec.design_preset(index)).truth_optics)
        except (BadInputError, DesignError) as exc:
            what = exc.what if isinstance(exc, BadInputError) else str(exc)
            raise _bad(
                f"design {index} ({values}) is impossible: {what}", "narrow the design ranges"
            ) from None


def _cost(doc: dict, axes: tuple[Axis, ...], preset: dict) -> str:
    cost = doc.get("cost", "prism_thickness_mm")
    if not isinstance(cost, str):
        raise _bad("cost is an axis name, a preset path or one of " + ", ".join(DERIVED_COSTS))
    if cost in DERIVED_COSTS or cost in {a.name for a in axes}:
        return cost
    try:
        get_path(preset, cost)
    except KeyError:
        raise _bad(
            f"unknown cost {cost!r}",
            "use an axis name, a preset path or one of " + ", ".join(DERIVED_COSTS),
        ) from None
    return cost


def parse_spec(doc: Any) -> SweepSpec:
    """Validate a spec document and return the :class:`SweepSpec` (BadInputError, one
    line, for the first problem found)."""
    if not isinstance(doc, dict):
        raise _bad("the spec is not a JSON object")
    unknown = set(doc) - _TOP_KEYS
    if unknown:
        raise _bad(
            f"unknown key(s) {', '.join(sorted(unknown))}", f"use {', '.join(sorted(_TOP_KEYS))}"
        )
    if doc.get("version", SPEC_VERSION) != SPEC_VERSION:
        raise _bad(f"version {doc.get('version')!r} is not supported (this reads {SPEC_VERSION})")
    seed = doc.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise _bad(f"seed must be a non-negative integer, not {seed!r}")
    protocol = _protocol(doc)
    preset = _base_preset(doc, protocol)
    designs = doc.get("designs")
    if not isinstance(designs, dict) or not designs:
        raise _bad("designs is empty", "give at least one design axis")
    axes = tuple(_axis(name, entry, preset) for name, entry in designs.items())
    n_random = doc.get("random_designs", 1 if any("random" in e for e in designs.values()) else 0)
    if any(a.bounds is not None for a in axes) and (not isinstance(n_random, int) or n_random < 1):
        raise _bad(f"random_designs must be a positive integer with random axes, not {n_random!r}")
    draws, tolerances = _tolerances(doc, preset)
    merit = _merit(doc, protocol["model"])
    spec = SweepSpec(
        document=copy.deepcopy(doc),
        preset=preset,
        seed=seed,
        axes=axes,
        random_designs=int(n_random),
        draws=draws,
        tolerances=tolerances,
        images_per_board=protocol["images_per_board"],
        calib=protocol["calib"],
        targets=protocol["targets"],
        noise_px=protocol["noise_px"],
        model=protocol["model"],
        start=protocol["start"],
        cost=_cost(doc, axes, preset),
        **merit,
    )
    if spec.n_designs > MAX_DESIGNS:
        raise _bad(f"{spec.n_designs} designs is more than {MAX_DESIGNS}", "split the sweep")
    if spec.start == "design":
        from endomeasure.simulate.preset import Preset

        truth = Preset.from_dict(preset).truth_model
        if truth.NAME != spec.model:
            raise _bad(
                f"start 'design' seeds with the design's {truth.NAME} model, not a "
                f"{spec.model} one",
                "use start 'images' for this model",
            )
    _check_designs(spec)
    return spec


def read_spec(path: str | Path) -> SweepSpec:
    """Read and validate a spec file (BadInputError naming the file)."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise BadInputError(
            f"cannot read the sweep spec ({exc.strerror})", path=str(path)
        ) from None
    except json.JSONDecodeError as exc:
        raise BadInputError(
            f"the sweep spec is not valid JSON ({exc.msg}, line {exc.lineno})", path=str(path)
        ) from None
    try:
        return parse_spec(doc)
    except BadInputError as exc:
        raise BadInputError(exc.what, path=str(path), hint=exc.hint) from None
