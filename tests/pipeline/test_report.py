"""``endomeasure report``: the HTML page holds every section, with the session's numbers,
opens in a real browser without console errors, and says what is missing instead of
failing on sessions that hold less."""

from __future__ import annotations

import html.parser
import os
import shutil
import subprocess

import numpy as np
import pytest
from tests.pipeline.measure_data import board_points, build_session
from tests.solvers.calibration_data import perturbed_raytrace_truth, synthetic_views, write_session
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.io.records import BOARD_TEST_RECORD, MEASUREMENT_RECORD, PREDICTION_RECORD
from endomeasure.io.session import open_session

runner = CliRunner()
BROWSERS = ("chromium", "chromium-browser", "google-chrome")
REQUIRE_BROWSER = os.environ.get("ENDOMEASURE_REQUIRE_BROWSER") == "1"
"""Set by ``.ci/run``, which installs Chromium: there the browser test must not skip."""


class _Page(html.parser.HTMLParser):
    """What a test reads of a report: sections, ``data-field`` values, missing notes, images."""

    def __init__(self):
        super().__init__()
        self.sections: list[dict[str, str]] = []
        self.fields: dict[tuple[str | None, str], str] = {}
        self.missing: set[str] = set()
        self.images = 0
        self._model: str | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "section":
            self.sections.append(a)
            self._model = a.get("data-model")
        if "data-field" in a:
            self.fields[(self._model, a["data-field"])] = a.get("data-value", "")
        if "data-missing" in a:
            self.missing.add(a["data-missing"])
        if tag == "img":
            assert a["src"].startswith("data:image/png;base64,")  # embedded, no network
            self.images += 1


def _report(session, out, *extra):
    result = runner.invoke(cli.app, ["report", str(session), "-o", str(out), *extra])
    assert result.exit_code == 0, result.output
    page = _Page()
    page.feed(out.read_text(encoding="utf-8"))
    return page, result


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """Synthetic detections of a known probe, calibrated with both models."""
    folder = tmp_path_factory.mktemp("report")
    data = synthetic_views(perturbed_raytrace_truth(), np.random.default_rng(5), n_images=10,
                           noise_px=0.1)  # fmt: skip
    detections_only = write_session(folder / "detections.h5", data)
    session = folder / "calibrated.h5"
    shutil.copyfile(detections_only, session)
    result = runner.invoke(cli.app, ["calibrate", str(session), "--model", "all"])
    assert result.exit_code == 0, result.output
    return detections_only, session


def test_every_calibration_section_holds_the_sessions_numbers(calibrated, tmp_path):
    _, session = calibrated
    page, _ = _report(session, tmp_path / "r.html")
    models = {s.get("data-model") for s in page.sections if s.get("data-section") == "calibration"}
    assert models == {"pinhole", "raytrace"}
    with open_session(session) as s:
        for name in models:
            rec = s.model(name)
            assert page.fields[(name, "verdict")] == rec.attrs["verdict"]
            assert float(page.fields[(name, "rms")]) == pytest.approx(rec.attrs["rms"], rel=1e-12)
            assert float(page.fields[(name, "noise_floor")]) == pytest.approx(
                rec.attrs["noise_floor_px"], rel=1e-12
            )
            assert int(page.fields[(name, "n_inliers")]) == int(rec.arrays["inliers"].sum())
    text = (tmp_path / "r.html").read_text()
    for name in models:
        assert f'id="calibration-{name}"' in text and f'id="trust-{name}"' in text
    # the pinhole pair's baseline is the length of its stereo translation
    with open_session(session) as s:
        params = dict(zip(s.model("pinhole").param_names, s.model("pinhole").params, strict=True))
    t = np.array([params["tx"], params["ty"], params["tz"]])
    assert float(page.fields[("pinhole", "baseline")]) == pytest.approx(np.linalg.norm(t), 1e-9)
    # this session holds no test images, predictions or measurements: said, not failed
    assert {"board-test", "predicted", "measurements"} <= page.missing


def test_a_session_with_only_detections_says_what_is_missing(calibrated, tmp_path):
    detections_only, _ = calibrated
    before = detections_only.read_bytes()
    page, result = _report(detections_only, tmp_path / "d.html", "--json")
    assert {"calibration-pinhole", "calibration-raytrace", "board-test"} <= page.missing
    assert "calibrate" in result.stdout  # the JSON names the command to run
    assert detections_only.read_bytes() == before  # only read


def test_a_session_with_one_model_reports_it_and_names_the_other(calibrated, tmp_path):
    detections_only, _ = calibrated
    one = tmp_path / "one.h5"
    shutil.copyfile(detections_only, one)
    assert runner.invoke(cli.app, ["calibrate", str(one), "--model", "pinhole"]).exit_code == 0
    page, _ = _report(one, tmp_path / "one.html")
    assert [s.get("data-model") for s in page.sections if s.get("data-model")] == ["pinhole"]
    assert "calibration-raytrace" in page.missing


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """A session with a board test, its prediction and a length measurement."""
    path = tmp_path_factory.mktemp("measured") / "m.h5"
    build_session(path, np.random.default_rng(3), noise_px=0.05, offsets=((0, 0), (0, 0.5)))
    for args in (
        ["measure", str(path), "--board-test", "--model", "raytrace", "--zone-mm", "4"],
        ["predict-error", str(path), "--board-test", "--model", "raytrace"],
    ):
        result = runner.invoke(cli.app, args)
        assert result.exit_code == 0, result.output
    from tests.conftest import make_raytrace_model

    model = make_raytrace_model()
    ends = board_points(16.0)[[0, 6]]
    pixels = []
    for p in ends:
        left = model.project(p[None], "left").pixels[0]
        right = model.project(p[None], "right").pixels[0]
        pixels += ["--left", f"{left[0]:.17g},{left[1]:.17g}",
                   "--right", f"{right[0]:.17g},{right[1]:.17g}"]  # fmt: skip
    result = runner.invoke(cli.app, ["measure", str(path), "--model", "raytrace", "--image",
                                     "scene", "--kind", "length", *pixels])  # fmt: skip
    assert result.exit_code == 0, result.output
    return path


def test_board_test_prediction_and_measurements_match_the_records(measured, tmp_path):
    page, _ = _report(measured, tmp_path / "m.html")
    text = (tmp_path / "m.html").read_text()
    with open_session(measured) as s:
        bt = s.record(BOARD_TEST_RECORD, "raytrace")
        pred = s.record(PREDICTION_RECORD, "board-test-raytrace")
        (mid,) = s.record_names(MEASUREMENT_RECORD)
        m = s.record(MEASUREMENT_RECORD, mid)
    assert not {"board-test", "predicted", "measurements"} & page.missing
    assert float(page.fields[(None, "within_band")]) == pytest.approx(pred.attrs["within_band"])
    for mean in bt.arrays["zone_mean_error"][np.isfinite(bt.arrays["zone_mean_error"])]:
        assert f'data-value="{float(mean)!r}"' in text
    assert f'data-value="{float(m.attrs["value"])!r}"' in text
    assert float(m.attrs["value"]) == pytest.approx(3.0, abs=1e-6)  # six 0.5 mm squares
    # models stored without residuals: the calibration section says so
    assert "stored without its residuals" in text


def test_bad_bands_and_outputs_are_one_line(calibrated, tmp_path):
    _, session = calibrated
    for args, message in (
        (["--bands", "5,1"], "increasing"),
        (["--bands", "x"], "cannot read the bands"),
        (["-o", str(tmp_path / "r.png")], "report"),
        (["-o", str(session)], "report"),
    ):
        result = runner.invoke(cli.app, ["report", str(session), *args])
        assert result.exit_code == 2, result.output
        assert message in result.stderr and result.stderr.count("\n") == 1


def _browser() -> str | None:
    return next((b for b in map(shutil.which, BROWSERS) if b), None)


def test_the_report_opens_in_headless_chromium_without_console_errors(calibrated, tmp_path):
    browser = _browser()
    if browser is None:
        if REQUIRE_BROWSER:
            pytest.fail("ENDOMEASURE_REQUIRE_BROWSER=1 but no Chromium is installed")
        pytest.skip("no Chromium here (.ci/run installs it)")
    _, session = calibrated
    out = tmp_path / "r.html"
    page, _ = _report(session, out)
    done = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
         "--v=0", "--dump-dom", out.as_uri()],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    # the page's own script marks the body once every figure decoded
    assert f'data-images="ok:{page.images}"' in done.stdout
    console = [line for line in done.stderr.splitlines() if ":CONSOLE" in line]
    assert console == []
