"""Sweep specs: bad ones refused before any work, one line each; designs expanded."""

from __future__ import annotations

import copy
import json
import subprocess
import sys

import numpy as np
import pytest

from endomeasure.errors import BadInputError
from endomeasure.study.spec import parse_spec

WEDGE = {"set": {"prism.left_face.a_deg": -1, "prism.right_face.a_deg": 1}, "grid": [30, 34]}
GOOD = {
    "preset": "default",
    "designs": {"wedge_deg": WEDGE, "lens.fx": {"random": [290.0, 310.0]}},
    "random_designs": 3,
    "tolerances": {"draws": 2, "sigmas": {"prism.apex_mm.0": 0.01}},
    "protocol": {"images_per_board": 2, "start": "design"},
    "merit": {"depths_mm": [30], "sigmas": ["n_glass"]},
}


def with_(path: str, value):
    """GOOD with the value at a /-separated path (the keys themselves hold dots)."""
    doc = copy.deepcopy(GOOD)
    *head, last = path.split("/")
    node = doc
    for part in head:
        node = node[part]
    node[last] = value
    return doc


BAD = {
    "unknown field": (
        GOOD | {"designs": {"lens.fxx": {"grid": [300]}}},
        "unknown field 'lens.fxx'",
    ),
    "unknown field in a tolerance": (
        with_("tolerances/sigmas", {"prism.apex.0": 0.1}),
        "unknown field 'prism.apex.0' in tolerances",
    ),
    "empty grid": (with_("designs/wedge_deg/grid", []), "empty range (grid [])"),
    "empty linspace": (
        with_("designs/wedge_deg/grid", {"linspace": [30, 34, 0]}),
        "empty range (linspace count 0)",
    ),
    "empty random range": (
        with_("designs/lens.fx", {"random": [310.0, 290.0]}),
        "empty range (random [310, 290])",
    ),
    "total internal reflection": (
        with_("designs/wedge_deg/grid", [34, 60]),
        "design 3 (wedge_deg 60, lens.fx",
    ),
    "unknown key": (GOOD | {"desings": {}}, "unknown key(s) desings"),
    "no draws": (with_("tolerances/draws", 0), "tolerances.draws must be a positive integer"),
    "zero-valued template": (
        with_("merit/templates", [{"template": "point-plane"}]),
        "template 'point-plane' measures a deviation of true value 0",
    ),
    "unknown parameter sigma": (
        with_("merit/sigmas", ["n_glas"]),
        "unknown parameter 'n_glas'",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_specs_are_refused_with_one_line(case):
    doc, expected = BAD[case]
    with pytest.raises(BadInputError) as info:
        parse_spec(doc)
    line = info.value.one_line()
    assert expected in line
    assert "\n" not in line


def test_the_cli_refuses_a_bad_spec_before_any_work(tmp_path):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(BAD["total internal reflection"][0]))
    out = tmp_path / "results.h5"
    run = subprocess.run(
        [sys.executable, "-m", "endomeasure", "sweep", str(spec), "-o", str(out)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("error: sweep spec: design 3 (wedge_deg 60")
    assert "total internal reflection" in lines[0]
    assert not out.exists()


def test_designs_expand_grid_major_with_seeded_random_values():
    spec = parse_spec(GOOD)
    assert spec.n_designs == 2 * 3
    values = np.array([spec.design_values(i) for i in range(spec.n_designs)])
    np.testing.assert_array_equal(values[:, 0], [30, 30, 30, 34, 34, 34])
    assert np.all((values[:, 1] >= 290) & (values[:, 1] <= 310))
    assert len(set(values[:, 1])) == 6  # every design its own draw
    again = parse_spec(copy.deepcopy(GOOD))
    assert [again.design_values(i) for i in range(6)] == [tuple(v) for v in values]
    data = spec.design_preset(4)
    assert data["prism"]["left_face"]["a_deg"] == -34.0
    assert data["prism"]["right_face"]["a_deg"] == 34.0
    assert data["lens"]["fx"] == values[4, 1]
    assert all(b["images"] == 2 for b in data["sets"]["calib"]["boards"])


def test_add_axes_shift_from_the_preset_and_draws_perturb_only_the_tolerances():
    doc = GOOD | {
        "designs": {
            "shift": {"add": {"prism.rear_face.d_mm": 1, "prism.apex_mm.2": 1}, "grid": [0.5]}
        },  # fmt: skip
    }
    spec = parse_spec(doc)
    base = spec.preset["prism"]
    data = spec.design_preset(0)
    assert data["prism"]["rear_face"]["d_mm"] == pytest.approx(base["rear_face"]["d_mm"] + 0.5)
    assert data["prism"]["apex_mm"][2] == pytest.approx(base["apex_mm"][2] + 0.5)
    drawn = [spec.drawn_preset(0, d)["prism"]["apex_mm"] for d in range(2)]
    assert drawn[0][0] != drawn[1][0]
    assert abs(drawn[0][0] - data["prism"]["apex_mm"][0]) < 5 * 0.01
    assert drawn[0][1:] == data["prism"]["apex_mm"][1:]
