"""``endomeasure measure``: operator measurements and the board test, on sessions whose
truth is known (a model's exact projections of known points, seeded pixel noise)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tests.conftest import make_raytrace_model
from tests.pipeline.measure_data import (
    BOARD_COLS,
    BOARD_ROWS,
    DEPTHS_MM,
    SIGMA_RECORD_PX,
    SQUARE_MM,
    build_session,
)
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.defaults import WARN_PERCENT
from endomeasure.io.session import open_session
from endomeasure.pipeline.measure import board_test, measure_points

runner = CliRunner()

TRIANGULATION_TOL_MM = 1e-6
"""Noise-free pixels of known points: ML triangulation converges to 1e-9 px (issue 7
asks for 1e-6 mm)."""


@pytest.fixture(scope="module")
def exact_session(tmp_path_factory):
    path = tmp_path_factory.mktemp("measure") / "probe.h5"
    return build_session(path, models=("raytrace", "pinhole"))


def _pixels(points):
    model = make_raytrace_model()
    return model.project(points, "left").pixels, model.project(points, "right").pixels


def _args(ql, qr):
    out = []
    for a, b in zip(ql, qr, strict=True):
        out += ["--left", f"{a[0]:.17g},{a[1]:.17g}", "--right", f"{b[0]:.17g},{b[1]:.17g}"]
    return out


def _measure(session, points, kind, *extra):
    ql, qr = _pixels(np.asarray(points, dtype=float))
    return runner.invoke(
        cli.app,
        [
            "measure",
            str(session),
            "--model",
            "raytrace",
            "--image",
            "scene",
            "--kind",
            kind,
            *_args(ql, qr),
            *extra,
        ],
    )


@pytest.mark.parametrize(
    ("kind", "points", "expected"),
    [
        ("length", [[-2.0, 0.0, 15.0], [1.0, 1.0, 19.0]], np.sqrt(9 + 1 + 16)),
        ("point-line", [[-2.0, 0.0, 15.0], [2.0, 0.0, 15.0], [0.5, 1.5, 15.0]], 1.5),
        # plane z = 16 facing the probe, 4th point 0.8 mm nearer: +0.8 (towards the probe)
        ("depth", [[-1.5, -1, 16.0], [1.5, -1, 16.0], [0, 1.5, 16.0], [0.2, 0.1, 15.2]], 0.8),
        ("area", [[-1.0, -1.0, 18.0], [1.0, -1.0, 18.0], [1.0, 1.0, 18.0], [-1.0, 1.0, 18.0]], 4.0),
        ("polyline", [[-2.0, 0.0, 15.0], [0.0, 0.0, 15.0], [0.0, 1.5, 15.0]], 3.5),
    ],
)
def test_measurement_of_known_points(exact_session, kind, points, expected):
    session, _ = exact_session
    result = _measure(session, points, kind, "--json")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["value"] == pytest.approx(expected, abs=TRIANGULATION_TOL_MM)
    xyz = np.array([p["xyz_mm"] for p in doc["points"]])
    np.testing.assert_allclose(xyz, points, atol=TRIANGULATION_TOL_MM)
    assert max(p["ray_gap_mm"] for p in doc["points"]) < TRIANGULATION_TOL_MM
    assert doc["sigma_px"] == pytest.approx(SIGMA_RECORD_PX)
    assert doc["std"] > 0 and doc["ci95"] == pytest.approx(1.959964 * doc["std"], rel=1e-6)
    assert doc["std"] ** 2 == pytest.approx(
        doc["std_image"] ** 2 + doc["std_calibration"] ** 2, rel=0.02
    )
    assert doc["record"].startswith("m")


def test_image_noise_part_scales_with_sigma(exact_session):
    # first order, the image part of the std is linear in sigma: independent of the code
    session, _ = exact_session
    pts = [[-2.0, 0.0, 15.0], [2.0, 0.5, 15.5]]
    ql, qr = _pixels(np.array(pts))
    a = measure_points(session, "raytrace", "scene", ql, qr, "length", sigma=0.01, store=False)
    b = measure_points(session, "raytrace", "scene", ql, qr, "length", sigma=0.02, store=False)
    assert b.error.std_image == pytest.approx(2.0 * a.error.std_image, rel=0.01)
    assert a.error.std_calibration == pytest.approx(b.error.std_calibration, rel=1e-6)


def test_measurements_are_stored_and_numbered(tmp_path):
    session, _ = build_session(tmp_path / "s.h5")
    pts = [[-2.0, 0.0, 15.0], [2.0, 0.5, 15.5]]
    for _ in range(2):
        assert _measure(session, pts, "length").exit_code == 0
    with open_session(session) as s:
        assert s.record_names("measurement") == ["m001", "m002"]
        rec = s.record("measurement", "m002")
    assert rec.attrs["measurement_kind"] == "length"
    assert rec.attrs["value"] == pytest.approx(np.linalg.norm(np.subtract(*pts)), abs=1e-6)
    np.testing.assert_allclose(rec.arrays["points"], pts, atol=TRIANGULATION_TOL_MM)
    assert rec.units["value"] == "mm" and rec.attrs["std"] > 0


def test_warning_above_the_threshold(exact_session):
    session, _ = exact_session
    # a 0.3 mm segment at 25 mm: its predicted error is tens of percent
    pts = [[0.0, 0.0, 25.0], [0.3, 0.0, 25.0]]
    result = _measure(session, pts, "length")
    assert result.exit_code == 0, result.output
    assert "WARNING: not accurate enough" in result.stderr
    doc = json.loads(_measure(session, pts, "length", "--json").stdout)
    assert doc["warning"] and doc["relative_percent"] > WARN_PERCENT
    relaxed = _measure(session, pts, "length", "--warn-percent", str(2 * doc["relative_percent"]))
    assert "WARNING" not in relaxed.stderr and "accuracy index" in relaxed.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            [
                "--kind",
                "length",
                "--left",
                "700,10",
                "--left",
                "100,10",
                "--right",
                "400,10",
                "--right",
                "410,10",
            ],
            "outside the 640x480",
        ),
        (
            [
                "--kind",
                "length",
                "--left",
                "100,10",
                "--left",
                "400,10",
                "--right",
                "500,10",
                "--right",
                "410,10",
            ],
            "not in the left half",
        ),
        (
            [
                "--kind",
                "length",
                "--left",
                "100,10",
                "--left",
                "110,10",
                "--right",
                "400,10",
                "--right",
                "100,20",
            ],
            "not in the right half",
        ),
        (["--kind", "length", "--left", "100,10", "--right", "400,10"], "needs exactly 2 points"),
        (
            [
                "--kind",
                "area",
                "--left",
                "100,10",
                "--left",
                "110,10",
                "--right",
                "400,10",
                "--right",
                "410,10",
            ],
            "needs at least 3 points",
        ),
        (
            ["--kind", "length", "--left", "1x2", "--left", "1,1", "--right", "400,10"],
            "cannot read the pixel",
        ),
        (["--kind", "volume", "--left", "1,2", "--right", "400,10"], "unknown measurement kind"),
        (
            ["--kind", "length", "--left", "100,10", "--left", "110,10", "--right", "400,10"],
            "2 --left points but 1 --right",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_2(exact_session, args, message):
    session, _ = exact_session
    result = runner.invoke(cli.app, ["measure", str(session), "--image", "scene", *args])
    assert result.exit_code == 2
    assert message in result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


def test_collinear_depth_unknown_image_and_uncalibrated_model(exact_session, tmp_path):
    session, _ = exact_session
    line = [[-1.0, 0, 16.0], [0.0, 0, 16.0], [1.0, 0, 16.0], [0.2, 0.5, 15.0]]
    result = _measure(session, line, "depth")
    assert result.exit_code == 2 and "collinear" in result.stderr
    ql, qr = _pixels(np.array(line[:2]))
    result = runner.invoke(
        cli.app, ["measure", str(session), "--image", "nope", "--kind", "length", *_args(ql, qr)]
    )
    assert result.exit_code == 2 and "nope" in result.stderr
    only_ray, _ = build_session(tmp_path / "r.h5")
    result = runner.invoke(
        cli.app,
        [
            "measure",
            str(only_ray),
            "--model",
            "pinhole",
            "--image",
            "scene",
            "--kind",
            "length",
            *_args(ql, qr),
        ],
    )
    assert result.exit_code == 2
    assert "no calibrated 'pinhole' model" in result.stderr and "calibrate" in result.stderr


# ----- board test -------------------------------------------------------------------------------


def _stencil_counts():
    c, r = BOARD_COLS, BOARD_ROWS
    return {
        "x-segment": (c - 1) * r,
        "y-segment": c * (r - 1),
        "point-plane": (c - 1) * (r - 1),
        "area": (c - 1) * (r - 1),
    }


def test_board_test_on_exact_corners_has_zero_error(exact_session, tmp_path):
    session, truth = exact_session
    plot = tmp_path / "fig4.png"
    result = runner.invoke(
        cli.app,
        [
            "measure",
            str(session),
            "--board-test",
            "--model",
            "raytrace",
            "--json",
            "--plot",
            str(plot),
        ],
    )
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    images = doc["models"]["raytrace"]["images"]
    assert len(images) == len(DEPTHS_MM)
    counts = _stencil_counts()
    for image in images:
        xyz = np.array([c["xyz_mm"] for c in image["corners"]])
        ids = [c["id"] for c in image["corners"]]
        np.testing.assert_allclose(xyz, truth[image["image"]][ids], atol=TRIANGULATION_TOL_MM)
        kinds = [m["kind"] for m in image["measurements"]]
        assert {k: kinds.count(k) for k in counts} == counts
        for m in image["measurements"]:
            true = {"area": SQUARE_MM**2, "point-plane": 0.0}.get(m["kind"], SQUARE_MM)
            assert m["true"] == pytest.approx(true)
            assert abs(m["error"]) < 1e-5
    assert all(abs(r["mean_error"]) < 1e-6 for r in doc["summary"])
    assert sum(r["n"] for r in doc["summary"]) == len(DEPTHS_MM) * sum(counts.values())
    assert plot.stat().st_size > 10_000


def test_board_test_zones_match_a_direct_computation(tmp_path, rng):
    # noisy corners: the per-zone mean and std equal those computed here from the table
    session, _ = build_session(tmp_path / "n.h5", rng, noise_px=0.1)
    report = board_test(session, "raytrace", zone_mm=5.0)
    bt = report.models["raytrace"]
    t = bt.table
    for row in report.summary_rows():
        sel = (t.kind == row["kind"]) & (np.floor(t.z_mean / 5.0) * 5.0 == row["zone_start"])
        assert row["n"] == sel.sum()
        assert row["mean_error"] == pytest.approx(t.error[sel].mean(), abs=1e-12)
        assert row["std_error"] == pytest.approx(t.error[sel].std(ddof=1), rel=1e-9)
    assert {r["zone_start"] for r in report.summary_rows()} == {10.0, 15.0, 20.0, 25.0}
    with open_session(session) as s:
        rec = s.record("board_test", "raytrace")
    np.testing.assert_allclose(rec.arrays["row_error"], t.error)
    assert rec.attrs["zone_mm"] == 5.0


def test_board_test_all_models_table(exact_session):
    session, _ = exact_session
    result = runner.invoke(cli.app, ["measure", str(session), "--board-test", "--model", "all"])
    assert result.exit_code == 0, result.output
    assert f"pinhole {len(DEPTHS_MM)}, raytrace {len(DEPTHS_MM)}" in result.stderr
    with open_session(session) as s:
        assert {"pinhole", "raytrace"} <= set(s.record_names("board_test"))
