"""The layering of the package, checked from the source with ``ast``.

Direction of imports (STYLE.md)::

    cli -> pipeline -> {io, features, simulate, measure, solvers} -> models
        -> {geometry, interpolation} -> conventions, errors

(``interpolation``: the cubic B-spline image interpolant that the corner refinement in
features and the correspondence search in measure share, numeric like geometry.)

A module may import from its own package, from any lower layer, and from the base
(``endomeasure``, ``conventions``, ``errors``). Imports between the middle-layer peers
need an entry in ``PEER_IMPORTS_ALLOWED`` with the reason.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "src" / "endomeasure"

LAYERS = {
    "conventions": 0,
    "errors": 0,
    "geometry": 1,
    "interpolation": 1,
    "models": 2,
    "io": 3,
    "features": 3,
    "simulate": 3,
    "measure": 3,
    "solvers": 3,
    "pipeline": 4,
    "cli": 5,
    "__main__": 6,
}
BASE = {"", "conventions", "errors"}  # "" is the package root (__version__)

PEER_IMPORTS_ALLOWED = {
    ("measure", "solvers"): "measurements triangulate their points with solvers.triangulate",
    ("simulate", "features"): "the simulator draws the boards features.boards parses, so one "
    "board-spec grammar serves both",
}

ONLY_IN = {
    "h5py": {"io"},
    "typer": {"cli"},
    "rich": {"cli"},
    "click": {"cli"},
}
"""Third-party packages only one part may import: storage in io, terminal UI in cli."""

HEAVY_MODULES = ("numpy", "cv2", "scipy", "h5py", "matplotlib")
"""Not to be loaded by ``endomeasure --help``: together they cost most of a second."""


def modules():
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        rel = path.relative_to(PACKAGE_DIR).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        yield ".".join(["endomeasure", *parts]).rstrip("."), path


def part_of(module: str) -> str:
    """The top-level part ('' for the package root) of an endomeasure module name."""
    pieces = module.split(".")
    return pieces[1] if len(pieces) > 1 else ""


def imports(path: Path, module: str):
    """(imported module, line, at_top_level) for every import in a file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    top_level = {id(node) for node in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno, id(node) in top_level
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield target, node.lineno, id(node) in top_level


def test_the_package_has_the_expected_parts():
    parts = {part_of(name) for name, _ in modules()}
    assert {"", "cli", "conventions", "errors", "io", "pipeline"} <= parts
    unknown = parts - set(LAYERS) - {""}
    assert not unknown, f"add {unknown} to LAYERS in this test"


def test_imports_point_down_the_layers():
    violations = []
    checked = 0
    for module, path in modules():
        part = part_of(module)
        for target, line, _ in imports(path, module):
            if target != "endomeasure" and not target.startswith("endomeasure."):
                continue
            checked += 1
            other = part_of(target)
            if other == part or other in BASE:
                continue
            if part in BASE:
                violations.append(f"{path.name}:{line} base module {module} imports {target}")
            elif LAYERS[other] > LAYERS[part] or (
                LAYERS[other] == LAYERS[part] and (part, other) not in PEER_IMPORTS_ALLOWED
            ):
                violations.append(f"{module}:{line} imports {target} ({part} -> {other})")
    assert checked > 20
    assert violations == []


def test_h5py_typer_and_rich_stay_in_their_parts():
    violations = []
    for module, path in modules():
        for target, line, _ in imports(path, module):
            root = target.split(".")[0]
            if root in ONLY_IN and part_of(module) not in ONLY_IN[root]:
                violations.append(f"{module}:{line} imports {target}")
    assert violations == []


def test_core_code_never_prints_or_exits():
    calls = []
    for module, path in modules():
        if part_of(module) in ("cli", "__main__"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Call):
                continue
            func = node.func
            name = func.id if isinstance(func, ast.Name) else None
            if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name):
                name = f"{func.value.id}.{func.attr}"
            if name in ("print", "exit", "quit", "sys.exit", "os._exit", "breakpoint"):
                calls.append(f"{module}:{node.lineno} calls {name}")
    assert calls == []


def test_cli_imports_pipeline_code_only_inside_commands():
    path = PACKAGE_DIR / "cli.py"
    top = sorted(
        target
        for target, _, at_top in imports(path, "endomeasure.cli")
        if at_top and target.startswith("endomeasure")
    )
    assert set(top) <= {"endomeasure", "endomeasure.errors"}, top


def test_importing_the_cli_loads_no_heavy_module():
    code = (
        "import json, sys; import endomeasure.cli; "
        f"print(json.dumps([m for m in {HEAVY_MODULES!r} if m in sys.modules]))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == []


@pytest.mark.parametrize("module", ["endomeasure.errors", "endomeasure"])
def test_base_modules_need_only_the_standard_library(module):
    code = (
        "import json, sys; before = set(sys.modules); "
        f"import {module}; "
        "print(json.dumps(sorted({m.split('.')[0] for m in set(sys.modules) - before})))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    third_party = set(json.loads(result.stdout)) - set(sys.stdlib_module_names) - {"endomeasure"}
    assert third_party == set()
