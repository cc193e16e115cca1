# endomeasure developer commands. Everything runs inside .venv, which `make install` creates.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR := out/demo

.PHONY: install test demo bench accuracy lint samples

install: $(STAMP)

# Reinstall only when the package metadata changes; works on an existing venv too.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[dev]"
	touch $@

test: install
	$(PY) -m pytest -q -n 2

# The whole pipeline on the bundled sample set: detect -> calibrate -> measure (board test
# and a distance on a scene image) -> predict-error -> info; see scripts/demo.py.
demo: install
	$(PY) scripts/demo.py $(DEMO_DIR)

# Speed: every bench/bench_*.py rewrites its section of docs/benchmarks.md. Accuracy: the
# long scripts (about an hour on 2 cores) rewrite theirs in docs/accuracy.md (the
# simulator's truth check: docs/simulator.md), in this order;
# corner_precision.py reads accuracy_report.py's work folder and only prints. Both run every
# script, then fail if one failed or missed its target (the script exits 3 and prints one
# line per miss; make then exits 1, naming the scripts).
# ARGS goes to every script: `make bench ARGS=--quick` (smoke run, docs untouched),
# `ARGS=--no-write` (figures printed only).
ARGS ?=
ACCURACY_WORK ?= out/accuracy
ACCURACY_RUNS := \
	"bench/bench_simulate.py --accuracy --noisy sample_sessions" \
	"bench/accuracy_detect.py" \
	"bench/accuracy_charuco.py --sweep" \
	"bench/accuracy_report.py sample_sessions --test-seeds 1,2,3 --work $(ACCURACY_WORK)" \
	"bench/corner_precision.py $(ACCURACY_WORK) --twins 8" \
	"bench/accuracy_scene.py" \
	"bench/match_precision.py" \
	"bench/accuracy_designs.py --work $(ACCURACY_WORK)/designs --jobs 2" \
	"bench/noise_designs.py $(ACCURACY_WORK)/designs" \
	"bench/zone_spread_designs.py $(ACCURACY_WORK)/designs" \
	"bench/misfit_designs.py $(ACCURACY_WORK)/designs --default $(ACCURACY_WORK)/accuracy.h5" \
	"bench/operator_designs.py $(ACCURACY_WORK)/designs" \
	"bench/calibration_origin.py --designs $(ACCURACY_WORK)/designs --session $(DEMO_DIR)/demo.h5" \
	"bench/accuracy_dense.py --session $(DEMO_DIR)/demo.h5 --designs $(ACCURACY_WORK)/designs" \
	"bench/accuracy_profile.py --session $(DEMO_DIR)/demo.h5" \
	"bench/accuracy_dense_sgbm.py --session $(DEMO_DIR)/demo.h5" \
	"bench/accuracy_plane.py" \
	"bench/figure5.py $(ACCURACY_WORK)/accuracy.h5 $(ACCURACY_WORK)/designs/design_005.h5" \
	"bench/accuracy_split.py --work $(ACCURACY_WORK)/split" \
	"bench/accuracy_compare.py --work $(ACCURACY_WORK)/compare" \
	"bench/accuracy_rotation.py --poses 24 --designs 10 --seed 0" \
	"bench/fault_bitflips.py $(ACCURACY_WORK)/accuracy.h5 --work $(ACCURACY_WORK)/bitflips" \
	"bench/fault_disk_full.py --work $(ACCURACY_WORK)/disk_full" \
	"bench/fault_limits.py --work $(ACCURACY_WORK)/limits" \
	"bench/fault_interrupts.py --work $(ACCURACY_WORK)/interrupts"

bench: install
	@failed=""; \
	for script in bench/bench_*.py; do \
		echo "== $$script $(ARGS)"; $(PY) $$script $(ARGS) || failed="$$failed $$script"; \
	done; \
	if [ -n "$$failed" ]; then echo "make bench: failed or missed a target:$$failed"; exit 1; fi

# accuracy_dense.py measures the scene images of the demo session: made first when missing
accuracy: install
	@test -f $(DEMO_DIR)/demo.h5 || $(PY) scripts/demo.py $(DEMO_DIR)
	@failed=""; \
	for run in $(ACCURACY_RUNS); do \
		echo "== $$run $(ARGS)"; $(PY) $$run $(ARGS) || failed="$$failed $${run%% *}"; \
	done; \
	if [ -n "$$failed" ]; then echo "make accuracy: failed or missed a target:$$failed"; exit 1; fi

lint: install
	$(VENV)/bin/ruff check src tests bench scripts

# accuracy_designs.py renders, detects and calibrates 40 random probe designs (hours on 2
# cores; resumable: finished designs are kept in its work folder).
# The committed sample set (calibration + test + scene, with ground truth): the default
# preset, seed 0. Deterministic: rerunning it reproduces the images byte for byte (the truth
# JSONs too, with the same ray-aiming code; see sample_sessions/README.md).
samples: install
	$(VENV)/bin/endomeasure simulate sample_sessions --preset default --set calib,test,scene --seed 0
