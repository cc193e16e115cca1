# endomeasure developer commands. Everything runs inside .venv, which `make install` creates.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR := out/demo
DEMO_SESSION := $(DEMO_DIR)/demo.h5

.PHONY: install test demo bench lint samples

install: $(STAMP)

# Reinstall only when the package metadata changes; works on an existing venv too.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[dev]"
	touch $@

test: install
	$(PY) -m pytest -q -n 2

# Grows with every stage of the pipeline; for now: embed the sample images and summarise.
demo: install
	rm -rf $(DEMO_DIR) && mkdir -p $(DEMO_DIR)
	@found=0; \
	for set in calib test scene; do \
	  if [ -d sample_sessions/$$set ]; then \
	    $(VENV)/bin/endomeasure add-images $(DEMO_SESSION) sample_sessions/$$set --set $$set || exit $$?; found=1; \
	  fi; \
	done; \
	if [ $$found = 0 ] && ls sample_sessions/*.png >/dev/null 2>&1; then \
	  $(VENV)/bin/endomeasure add-images $(DEMO_SESSION) sample_sessions --set calib || exit $$?; found=1; \
	fi; \
	if [ $$found = 0 ]; then \
	  echo "no images in sample_sessions/; creating an empty session"; \
	  $(VENV)/bin/endomeasure add-images $(DEMO_SESSION) --set calib || exit $$?; \
	fi
	$(VENV)/bin/endomeasure info $(DEMO_SESSION)

bench: install
	@for script in bench/bench_*.py; do echo "== $$script"; $(PY) $$script || exit $$?; done

lint: install
	$(VENV)/bin/ruff check src tests bench

# The committed sample set (calibration + test + scene, with ground truth): the default
# preset, seed 0. Deterministic: rerunning it reproduces the files byte for byte.
samples: install
	$(VENV)/bin/endomeasure simulate sample_sessions --preset default --set calib,test,scene --seed 0
