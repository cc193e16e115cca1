"""The layering of the package, checked from the source with ``ast``.

Direction of imports (STYLE.md)::

    cli -> pipeline -> study -> {io, features, simulate, measure, solvers} -> models
        -> {geometry, interpolation} -> conventions, errors

(``study``: the design studies of ``endomeasure sweep``, one probe design evaluated
from its spec through the simulator, the calibration and the error map, so it composes
three middle-layer peers and sits above them. ``interpolation``: the cubic B-spline
image interpolant that the corner refinement in features and the correspondence search
in measure share, numeric like geometry.)

A module may import from its own package, from any lower layer, and from the base
(``endomeasure``, ``conventions``, ``errors``). Imports between the middle-layer peers
need an entry in ``PEER_IMPORTS_ALLOWED`` with the reason.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "src" / "endomeasure"

LAYERS = {
    "conventions": 0,
    "errors": 0,
    "defaults": 0,
    "interrupts": 0,
    "geometry": 1,
    "interpolation": 1,
    "models": 2,
    "io": 3,
    "features": 3,
    "simulate": 3,
    "measure": 3,
    "solvers": 3,
    "study": 4,
    "pipeline": 5,
    "cli": 6,
    "__main__": 7,
}
BASE = {"", "conventions", "errors", "defaults", "interrupts"}
"""Importable from anywhere ("" is the package root: ``__version__``)."""

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
    "dask": {"pipeline"},
    "distributed": {"pipeline"},
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


DASK_MODULES = {"endomeasure.pipeline.sweep"}
"""Where the sweep's execution on Dask lives: the design evaluation it runs stays pure."""


def test_dask_stays_in_the_sweep_pipeline():
    found = {
        module
        for module, path in modules()
        for target, _, _ in imports(path, module)
        if target.split(".")[0] in ("dask", "distributed")
    }
    assert found == DASK_MODULES


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
    base = {"endomeasure", "endomeasure.errors", "endomeasure.defaults", "endomeasure.interrupts"}
    assert set(top) <= base, top


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


BASE_MODULES = [
    "endomeasure.errors",
    "endomeasure.defaults",
    "endomeasure.interrupts",
    "endomeasure",
]


@pytest.mark.parametrize("module", BASE_MODULES)
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


# ----- the shape of the code ----------------------------------------------------------------

MAX_FUNCTION_LINES = 120
"""Issue 14: a function longer than this is split into named steps."""
MODEL_BLIND_PARTS = ("solvers", "pipeline", "io", "measure", "features", "cli")
"""Parts that work for every registered model through the contract, never by its name
(the models themselves and the simulator, which builds its truth optics, do not)."""


def _runtime_imports(node):
    """Import nodes that run (not under ``if TYPE_CHECKING:``)."""
    if isinstance(node, ast.Import | ast.ImportFrom):
        yield node
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.dump(child.test):
            continue
        yield from _runtime_imports(child)


def module_graph() -> dict[str, set[str]]:
    """Every import between endomeasure modules that runs, lazy ones included; ``from
    package import submodule`` counts as importing the submodule."""
    names = {name for name, _ in modules()}
    graph: dict[str, set[str]] = {}
    for module, path in modules():
        edges = graph.setdefault(module, set())
        is_package = path.name == "__init__.py"
        for node in _runtime_imports(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {alias.name for alias in node.names if alias.name in names}
                continue
            base = node.module or ""
            if node.level:
                parts = module.split(".") if is_package else module.split(".")[:-1]
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                edges.add(sub if sub in names else base)
        graph[module] = {target for target in edges if target in names and target != module}
    return graph


def test_there_is_no_import_cycle():
    graph = module_graph()
    assert len(graph) > 40
    cycles = []
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(path[path.index(nxt) :] + [nxt]))
            elif nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for start in sorted(graph):
        if start not in state:
            visit(start, [start])
    assert cycles == []


PIPELINE_COMPOSERS = {
    "endomeasure.pipeline.report": {
        "endomeasure.pipeline.info": "the report's session overview is what `info` shows",
        "endomeasure.pipeline.predict": "its trust map is `predict-error --map` of each model",
    },
    "endomeasure.pipeline.profile": {
        "endomeasure.pipeline.measure": "a profile is a `measure` kind: its reference points are "
        "measure's operator points (the same checks, search, triangulation and refusal)",
    },
}
"""Pipeline modules that show what other commands compute, with the reason."""


def test_no_pipeline_module_imports_another():
    violations = [
        f"{module} imports {target}"
        for module, targets in module_graph().items()
        if part_of(module) == "pipeline"
        for target in targets
        if part_of(target) == "pipeline"
        and target != "endomeasure.pipeline"
        and target not in PIPELINE_COMPOSERS.get(module, {})
    ]
    assert violations == []


def _docstring_nodes(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                yield body[0].value


def test_no_part_but_the_models_names_a_model():
    from endomeasure.models import MODELS

    violations = []
    checked = 0
    for module, path in modules():
        if part_of(module) not in MODEL_BLIND_PARTS:
            continue
        tree = ast.parse(path.read_text())
        allowed = {id(node) for node in _docstring_nodes(tree)}
        for node in ast.walk(tree):
            if isinstance(node, ast.arguments):  # a default may name the usual model
                allowed |= {id(d) for d in (*node.defaults, *node.kw_defaults) if d is not None}
        for node in ast.walk(tree):
            checked += 1
            if isinstance(node, ast.Constant) and node.value in MODELS and id(node) not in allowed:
                violations.append(f"{module}:{node.lineno} names the {node.value} model")
            sides = (node.left, *node.comparators) if isinstance(node, ast.Compare) else ()
            if any(
                isinstance(side, ast.Attribute) and side.attr == "NAME" for side in sides
            ) and any(
                isinstance(side, ast.Constant) and isinstance(side.value, str) for side in sides
            ):
                violations.append(f"{module}:{node.lineno} compares a model's NAME with a name")
    assert checked > 1000
    assert violations == []


def test_no_function_is_longer_than_the_limit():
    long = []
    for module, path in modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{module}:{node.lineno} {node.name} has {lines} lines")
    assert long == []


DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
SEED_LIST = re.compile(r"\bseeds? \d+ ?(?:[,-]|to|and) ?\d+", re.I)


def test_docstrings_carry_no_dates_or_seed_lists():
    """Measured figures live in the generated docs, next to the command that makes them."""
    found = []
    for module, path in modules():
        for node in _docstring_nodes(ast.parse(path.read_text())):
            text = str(node.value)
            for pattern in (DATE, SEED_LIST):
                for match in pattern.finditer(text):
                    found.append(f"{module}:{node.lineno} {match.group(0)!r}")
    assert found == []
