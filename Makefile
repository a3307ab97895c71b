# Two entry points for a fresh Debian/Ubuntu machine with Python 3.10+:
#   make demo   -- set everything up, run the demo on built-in synthetic data, results in ./out/
#   make test   -- set everything up, run the whole test suite
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
STAMP := $(VENV)/.octofactor-installed
DEBIAN_PACKAGES := libusb-1.0-0 libgl1 libegl1 libx11-6 octomap-tools gcc python3-dev
PYTEST_ARGS ?=
# The suite runs in two pytest-xdist workers (12-13 min -> 8.5-9.5 min on two cores); a file's tests
# stay on one worker, in order (the README's blocks build on each other). TEST_WORKERS=0 runs
# it in this process.
TEST_WORKERS ?= 2

.PHONY: setup system-deps kernels demo test lint clean

setup: system-deps $(STAMP) kernels

# Open3D needs libusb/libGL/libEGL/libX11 to import; octomap-tools (graph2tree) is the
# reference implementation the compatibility tests compare against; gcc and the Python headers
# link the numba kernels compiled ahead of time (kernels, below).
system-deps:
	@missing=""; \
	for pkg in $(DEBIAN_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$pkg 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$pkg"; \
	done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ]; then \
	    echo "Installing Debian packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else \
	    echo "Missing Debian packages:$$missing"; \
	    echo "Install them with:  sudo apt-get install -y$$missing"; \
	    exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 10))' || \
	  { echo "octofactor needs Python >= 3.10 ($(PYTHON) is older)"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

# The numba kernels compiled ahead of time into extension modules (estimation/aot.py): a
# process then starts without numba (octofactor map on a small graph in ~0.15 s instead of
# ~0.8 s). Rebuilt only when a kernel, its signature table or the CPU changed; written under
# a temporary name and renamed, so an interrupted build leaves the JIT fallback, never half
# a module. The package's bytecode is compiled too, as pip does for a regular install (an
# editable one leaves it to the first import, which cannot write it where
# PYTHONDONTWRITEBYTECODE is set: every run then compiles our modules again, ~25 ms of
# `octofactor map`'s start). A stale .pyc is never used: Python checks the source's mtime.
kernels: $(STAMP)
	$(PY) -m estimation.aot build --if-stale
	$(PY) -m compileall -q estimation mapping perception pipelines

demo: setup
	$(VENV)/bin/octofactor demo -o out

test: setup
	$(PY) -m pytest -q --nbmake -n $(TEST_WORKERS) --dist loadfile tests notebooks $(PYTEST_ARGS)

lint: setup
	$(VENV)/bin/ruff check .

clean:
	rm -rf out .pytest_cache mapping/_kernels_aot_*.so estimation/registration/_kernels_aot_*.so
	find estimation mapping perception pipelines -name "*.pyc" -delete
