# The two user-facing targets, `make demo` and `make test`, each do the whole set-up on a fresh Debian machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stamp-installed
# Shared libraries the Open3D / pymeshlab / depthai wheels link against, and the Debian packages that provide them.
SYSTEM_LIBS := libusb-1.0.so.0:libusb-1.0-0 libGL.so.1:libgl1 libEGL.so.1:libegl1 libX11.so.6:libx11-6 libgomp.so.1:libgomp1

.PHONY: demo test test-slow bench lint system-deps clean peers

demo: $(STAMP)
	$(PY) -m fusion.cli demo --out out/demo

# The tests run side by side in one process per core (pytest-xdist), at most four: many of them start worker
# processes of their own, and each process holds its own copy of torch and Open3D.
TEST_PROCESSES := -n auto --maxprocesses 4

test: $(STAMP)
	$(PY) -m pytest -q $(TEST_PROCESSES)

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow $(TEST_PROCESSES)

bench: $(STAMP)
	$(PY) -m fusion.cli bench geometry --quick

lint: $(STAMP)
	$(VENV)/bin/ruff check perception tactile fusion benchmarks examples tests

peers:
	$(MAKE) -C benchmarks/peers pcl

# Missing shared libraries: install with apt-get when root, else print the exact command and stop.
system-deps:
	@missing=""; for pair in $(SYSTEM_LIBS); do lib=$${pair%%:*}; pkg=$${pair##*:}; \
	  ldconfig -p | grep -q "$$lib" || missing="$$missing $$pkg"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian packages:$$missing"; \
	    (apt-get update -qq || true) && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else \
	    echo "Missing system libraries. Run:  sudo apt-get install -y$$missing"; exit 1; \
	  fi; \
	fi

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)

# torch first, pinned: the CPU build; a plain `torch` would pull gigabytes of CUDA.
$(STAMP): setup.cfg pyproject.toml | system-deps $(VENV)/bin/python
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[camera,dist,dev]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) out *.egg-info
