"""``endomeasure simulate``: files, manifest, determinism, errors (on a small preset)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from endomeasure import cli
from endomeasure.errors import BadInputError
from endomeasure.pipeline.simulate import MANIFEST_NAME, checked_sets, simulate

runner = CliRunner()


def _files(folder):
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def test_writes_images_truth_and_manifest(tmp_path, small_preset_file, small_preset):
    out = tmp_path / "run"
    report = simulate(out, small_preset_file, ["calib", "test", "scene"], seed=4)
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    assert manifest["format"] == "endomeasure-simulation"
    assert manifest["split"] == small_preset.split == report.split
    assert manifest["truth_model"]["model"] == "raytrace"
    for name in ("calib", "test", "scene"):
        entries = manifest["sets"][name]["images"]
        assert len(entries) == report.sets[name]["images"] > 0
        for entry in entries:
            image = cv2.imread(str(out / entry["image"]), cv2.IMREAD_UNCHANGED)
            assert image.dtype == np.uint8
            assert image.shape == (small_preset.image_size[1], small_preset.image_size[0])
            truth = json.loads((out / entry["truth"]).read_text())
            assert truth["format"] == "endomeasure-simulated-truth"
            assert truth["image"] == entry["image"].split("/")[-1]
    assert report.sets["test"]["fully_visible"] == report.sets["test"]["images"]


def test_same_seed_same_bytes_other_seed_other_images(tmp_path, small_preset_file):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    simulate(a, small_preset_file, ["test"], seed=1)
    simulate(b, small_preset_file, ["test"], seed=1)
    simulate(c, small_preset_file, ["test"], seed=2)
    files_a, files_b, files_c = _files(a), _files(b), _files(c)
    assert files_a == files_b
    assert files_a["test/test_000.png"] != files_c["test/test_000.png"]


def test_noise_free_differs_only_by_the_noise(tmp_path, small_preset_file):
    simulate(tmp_path / "noisy", small_preset_file, ["test"], seed=1)
    simulate(tmp_path / "clean", small_preset_file, ["test"], seed=1, noise_free=True)
    noisy = cv2.imread(str(tmp_path / "noisy/test/test_000.png"), cv2.IMREAD_UNCHANGED)
    clean = cv2.imread(str(tmp_path / "clean/test/test_000.png"), cv2.IMREAD_UNCHANGED)
    diff = noisy.astype(float) - clean.astype(float)
    assert 0.5 < diff.std() < 10.0  # a few DN of shot and read noise, same scene
    truth_noisy = json.loads((tmp_path / "noisy/test/test_000.json").read_text())
    truth_clean = json.loads((tmp_path / "clean/test/test_000.json").read_text())
    assert truth_noisy["corners"] == truth_clean["corners"]
    assert truth_clean["render"]["noise_free"] is True


def test_rerun_replaces_stale_images(tmp_path, small_preset_file):
    out = tmp_path / "run"
    (out / "test").mkdir(parents=True)
    (out / "test" / "test_099.png").write_bytes(b"old")
    simulate(out, small_preset_file, ["test"], seed=1)
    assert not (out / "test" / "test_099.png").exists()


def test_bad_arguments_are_domain_errors(tmp_path, small_preset_file):
    with pytest.raises(BadInputError, match="unknown image set"):
        checked_sets(["calib", "nope"])
    with pytest.raises(BadInputError, match="seed"):
        simulate(tmp_path / "x", small_preset_file, ["test"], seed=-1)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(BadInputError, match="not a folder"):
        simulate(blocker, small_preset_file, ["test"], seed=1)


def test_cli_json_output_and_errors(tmp_path, small_preset_file):
    out = tmp_path / "cli"
    result = runner.invoke(
        cli.app,
        [
            "simulate",
            str(out),
            "--preset",
            str(small_preset_file),
            "--set",
            "scene",
            "--seed",
            "3",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["sets"]["scene"]["images"] == 1
    assert (out / report["sets"]["scene"]["files"][0]).is_file()
    bad = runner.invoke(cli.app, ["simulate", str(out), "--preset", "no-such-preset"])
    assert bad.exit_code == 2
    assert "unknown simulator preset" in bad.output
    assert "Traceback" not in bad.output


def test_random_preset_writes_the_drawn_design_and_labels_the_truth_model(tmp_path, monkeypatch):
    """The plumbing of ``--preset random --design-seed N`` (the draw itself: test_design)."""
    import copy

    from endomeasure.simulate import design

    from .conftest import small_preset_data

    drawn = small_preset_data()
    drawn["lens"].update(distortion_direction="pixel_to_ray", k1=0.1, pupil_shift_mm=0.05)
    drawn["design"] = {"seed": 9, "attempt": 0, "ranges_version": design.DESIGN_RANGES_VERSION}
    seeds = []
    monkeypatch.setattr(design, "draw_design", lambda n: seeds.append(n) or copy.deepcopy(drawn))
    out = tmp_path / "random"
    result = runner.invoke(
        cli.app,
        ["simulate", str(out), "--preset", "random", "--design-seed", "9", "--set", "scene",
         "--json"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert seeds == [9]
    assert json.loads(result.stdout)["design_seed"] == 9
    assert json.loads((out / "preset.json").read_text()) == drawn
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    assert manifest["design"]["seed"] == 9
    assert manifest["truth_optics"]["raytrace_representable"] is False
    assert manifest["truth_model_kind"] == "approximate-seed"
    assert manifest["truth_model"]["model"] == "raytrace"


def test_design_seed_goes_with_the_random_preset_only(tmp_path, small_preset_file):
    with pytest.raises(BadInputError, match="design-seed"):
        simulate(tmp_path / "a", "random", ["test"])
    with pytest.raises(BadInputError, match="design-seed"):
        simulate(tmp_path / "b", "random", ["test"], design_seed=-2)
    with pytest.raises(BadInputError, match="random"):
        simulate(tmp_path / "c", small_preset_file, ["test"], design_seed=3)


def test_default_manifest_says_its_truth_model_is_exact(tmp_path, small_preset_file):
    simulate(tmp_path / "d", small_preset_file, ["scene"], seed=0)
    manifest = json.loads((tmp_path / "d" / MANIFEST_NAME).read_text())
    assert manifest["truth_model_kind"] == "exact"
    assert manifest["truth_optics"]["raytrace_representable"] is True
