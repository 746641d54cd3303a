# Two commands on a fresh Debian machine: `make demo` and `make test`.
# Each installs what it needs (Debian packages when missing, a venv, the package) and then runs.

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# open3d needs libusb at import time; libgomp for its OpenMP kernels.
DEB_PACKAGES := libusb-1.0-0 libgomp1
# The browser tests of `robonav view` drive Debian's chromium (Playwright cannot download its own offline).
e2e: DEB_PACKAGES += chromium

.PHONY: demo test e2e setup system-deps precompile clean

demo: setup
	mkdir -p out
	$(VENV)/bin/robonav demo --seed 0 --json out/demo-summary.json

# `make test` runs every test but the end-to-end ones (marked e2e: the whole stack, a browser,
# a campaign); `make e2e` runs those, and CI runs both (`.ci/run`). Plain `pytest` runs all.
test: setup
	$(VENV)/bin/ruff check pipeline services calibration tests examples
	$(PY) -m pytest -m "not e2e"

e2e: setup
	$(PY) -m pytest -m e2e

setup: system-deps $(STAMP) precompile

# Compiled kernels go to the compile cache (NUMBA_CACHE_DIR, default ~/.cache/robonav/numba, a folder per kernel sources),
# never into the source tree. Filled here, no service compiles at start-up; seconds when it is full.
precompile: $(STAMP)
	$(VENV)/bin/robonav precompile

system-deps:
	@missing=""; \
	for pkg in $(DEB_PACKAGES); do dpkg -s $$pkg >/dev/null 2>&1 || missing="$$missing $$pkg"; done; \
	$(PYTHON) -c "import venv, ensurepip" >/dev/null 2>&1 || missing="$$missing python3-venv"; \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:$$missing"; \
		sudo=""; [ "$$(id -u)" = 0 ] || sudo=sudo; \
		$$sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq $$missing; \
	fi

$(STAMP): pyproject.toml
	$(PYTHON) -c "import sys; assert sys.version_info >= (3, 11), 'Python >= 3.11 is required, found ' + sys.version"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

clean:
	rm -rf $(VENV) out .pytest_cache build *.egg-info
