# Two entry points for a fresh Debian machine (root, Python 3.11, no GPU):
#   make demo   — set everything up, then run `terraslam demo`
#   make test   — set everything up, then run the default test suite (with the import-layer contracts
#                 and ruff, tests/test_code_checks.py)
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: default setup demo test test-slow bench clean

default: setup

# Debian packages: libusb-1.0-0 (open3d's wheel links it), proj-data (EGM96 geoid grid for MSL heights).
$(STAMP): pyproject.toml
	@dpkg -s libusb-1.0-0 proj-data >/dev/null 2>&1 || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 proj-data >/dev/null; }
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# torch first, pinned to the CPU wheel that pip finds on this disk (no multi-GB CUDA download)
	$(BIN)/pip install -q "torch==2.13.0"
	$(BIN)/pip install -q -e ".[test]"
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(BIN)/terraslam demo

test: setup
	$(BIN)/python -m pytest -q

test-slow: setup
	$(BIN)/python -m pytest -q -m slow

bench: setup
	$(BIN)/terraslam bench --suite

clean:
	rm -rf $(VENV) build *.egg-info
