# endomeasure developer commands. Everything runs inside .venv, which `make install` creates.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR := out/demo

.PHONY: install test demo bench lint samples

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

bench: install
	@for script in bench/bench_*.py; do echo "== $$script"; $(PY) $$script || exit $$?; done

lint: install
	$(VENV)/bin/ruff check src tests bench scripts

# The committed sample set (calibration + test + scene, with ground truth): the default
# preset, seed 0. Deterministic: rerunning it reproduces the images byte for byte (the truth
# JSONs too, with the same ray-aiming code; see sample_sessions/README.md).
samples: install
	$(VENV)/bin/endomeasure simulate sample_sessions --preset default --set calib,test,scene --seed 0
