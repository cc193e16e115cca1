"""endomeasure sweep: the same results serially, on a local cluster and on a scheduler
started apart; an interrupted sweep resumes with the missing designs only."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import endomeasure
from endomeasure.pipeline.sweep import run_sweep
from endomeasure.study.evaluate import OK, WARNING

SPEC = {
    "preset": "default",
    "seed": 5,
    "designs": {
        "wedge_deg": {
            "set": {"prism.left_face.a_deg": -1, "prism.right_face.a_deg": 1},
            "grid": [33.0, 37.0],
        },
        "lens.fx": {"random": [295.0, 305.0]},
    },
    "random_designs": 1,
    "tolerances": {"draws": 1, "sigmas": {"prism.left_face.a_deg": 0.05}},
    "protocol": {"images_per_board": 2, "noise_px": 0.05, "start": "design"},
    "merit": {"depths_mm": [30.0], "grid": [6, 4], "sigmas": ["n_glass"]},
}
NOISE_RMS_PX = 0.05 * np.sqrt(2)  # the RMS length of the 2-D corner noise
RMS_TOLERANCE = 0.3
"""A calibration leaves an RMS within 30 % of the noise's (a few hundred corners)."""
SCHEDULER_WAIT_S = 40.0
CLOCK_S = 1e-3
"""Slack between the thread CPU clock and the wall clock (their resolutions)."""


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sweep") / "spec.json"
    path.write_text(json.dumps(SPEC))
    return path


@pytest.fixture(scope="module")
def serial(spec_file):
    return run_sweep(spec_file, spec_file.with_name("serial.h5"), workers=0)


def _assert_same(a, b):
    assert [r.index for r in a.results] == [r.index for r in b.results] == [0, 1]
    for x, y in zip(a.results, b.results, strict=True):
        assert x.same_as(y), (x, y)


def test_a_serial_sweep_evaluates_every_design_with_real_figures(serial):
    assert serial.mode == "serial"
    assert serial.computed == [0, 1]
    for r in serial.results:
        assert r.status.tolist() == [OK] or r.status.tolist() == [WARNING]
        assert abs(r.rms_px[0] / NOISE_RMS_PX - 1) < RMS_TOLERANCE
        assert r.n_points[0, 0, 0] > 10
        assert 0 < r.merit < 100  # % of a 1 mm segment at 30 mm
        assert 0 < r.sigmas[0, 0] < 0.05  # n_glass from 6 images
        assert 0 < r.cpu_seconds <= r.seconds + CLOCK_S  # one thread's CPU within its wall
    assert serial.results[0].values[0] == 33.0
    assert serial.results[1].values[0] == 37.0
    assert serial.results[0].values[1] != serial.results[1].values[1]
    assert serial.ranked[0].merit <= serial.ranked[1].merit


def test_a_two_worker_local_cluster_gives_identical_results(spec_file, serial):
    local = run_sweep(spec_file, spec_file.with_name("local.h5"), workers=2)
    assert local.mode == "local cluster of 2 worker processes"
    _assert_same(serial, local)


def test_local_workers_run_one_thread_with_the_quiet_dask_settings():
    import dask

    from endomeasure.pipeline.sweep import QUIET_CLUSTER, _client

    client, cluster, _ = _client(None, 1)
    try:
        seen = client.run(
            lambda dask_worker: (
                {key: dask.config.get(key) for key in QUIET_CLUSTER},
                dask_worker.state.nthreads,
            )
        )
    finally:
        client.close()
        cluster.close()
    assert list(seen.values()) == [(QUIET_CLUSTER, 1)]
    assert QUIET_CLUSTER["distributed.worker.profile.enabled"] is False


def _start(args, env, log: Path):
    with log.open("w") as out:
        return subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=env)


def _address(scheduler_file: Path, process) -> str:
    deadline = time.monotonic() + SCHEDULER_WAIT_S
    while time.monotonic() < deadline and process.poll() is None:
        if scheduler_file.exists():
            try:
                return json.loads(scheduler_file.read_text())["address"]
            except (ValueError, KeyError):
                pass
        time.sleep(0.2)
    pytest.fail("the dask scheduler did not start")


def test_a_scheduler_started_apart_gives_identical_results(spec_file, serial, tmp_path):
    from distributed import Client

    src = str(Path(endomeasure.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")])}
    scheduler_file = tmp_path / "scheduler.json"
    dask = [sys.executable, "-m", "dask"]
    procs = [_start([*dask, "scheduler", "--port", "0", "--no-dashboard", "--scheduler-file",
                     str(scheduler_file)], env, tmp_path / "scheduler.log")]  # fmt: skip
    try:
        address = _address(scheduler_file, procs[0])
        procs.append(_start([*dask, "worker", address, "--nworkers", "2", "--nthreads", "1",
                             "--no-dashboard"], env, tmp_path / "worker.log"))  # fmt: skip
        with Client(address, timeout="20s") as client:
            client.wait_for_workers(2, timeout=SCHEDULER_WAIT_S)
        remote = run_sweep(spec_file, tmp_path / "remote.h5", scheduler=address)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    assert remote.mode == f"scheduler {address}"
    _assert_same(serial, remote)


def test_an_interrupted_sweep_computes_only_the_missing_designs(spec_file, serial, tmp_path):
    out = tmp_path / "resumed.h5"
    first = run_sweep(spec_file, out, workers=0, max_designs=1)
    assert first.computed == [0]
    assert first.missing == 1
    # a write cut short: a group without its 'complete' mark is dropped on resume
    with h5py.File(out, "a") as f:
        f["designs"].create_group("000001").attrs["index"] = 1
    second = run_sweep(spec_file, out, workers=0)
    assert second.computed == [1]
    assert second.skipped == 1
    # read back, not redone
    assert second.results[0].seconds == first.results[0].seconds
    assert second.results[0].cpu_seconds == first.results[0].cpu_seconds
    _assert_same(serial, second)
    third = run_sweep(spec_file, out, workers=0)
    assert third.computed == []
    assert third.mode == "nothing to compute"


def test_a_results_file_of_another_spec_is_refused(spec_file, serial, tmp_path):
    from endomeasure.errors import BadInputError

    other = tmp_path / "other.json"
    other.write_text(json.dumps({**SPEC, "seed": 6}))
    with pytest.raises(BadInputError, match="holds the results of another sweep spec"):
        run_sweep(other, spec_file.with_name("serial.h5"), workers=0)


def test_a_design_exports_as_a_preset_and_a_model_file(spec_file, serial, tmp_path):
    from endomeasure.io.export import read_model_file
    from endomeasure.simulate.preset import load_preset

    report = run_sweep(spec_file, spec_file.with_name("serial.h5"), workers=0, export=1,
                       export_dir=tmp_path)  # fmt: skip
    preset_path, model_path = (Path(p) for p in report.exported)
    preset = load_preset(preset_path)
    assert preset.prism["right_face"]["a_deg"] == 37.0
    assert preset.lens["fx"] == serial.results[1].values[1]
    model = read_model_file(model_path)
    assert model.fx == pytest.approx(serial.results[1].values[1])
    assert np.degrees(model.params[model.PARAM_NAMES.index("right_a")]) == pytest.approx(37.0)
