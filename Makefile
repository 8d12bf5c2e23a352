# rotor_id: everything from a clean clone.
#
#   make test   venv + build + the tests         make demo   venv + build + ./rotor-id demo
#   make venv   .venv with the pinned wheels     make build  colcon build of both packages
#   make bench  python bench/run_all.py          make clean  build/install/log and caches
#   make lock   rewrite constraints-jazzy.txt    make distclean  clean + .venv
#   make lint   only flake8 + pep257 (before committing)
#
# Nothing has to be installed or sourced by hand: missing system tools (cmake, g++, Python
# 3.11 venv/headers) are installed with apt-get, the Python packages come from the pins in
# requirements-jazzy.in + constraints-jazzy.txt (installed with uv, pip as fallback).
# See docs/install.md for the why.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test
# Every target builds on the previous one (venv -> build -> test); never run them in parallel.
.NOTPARALLEL:
MAKEFLAGS += --no-print-directory

PYTHON ?= python3.11
VENV := .venv
VPY := $(VENV)/bin/python
REQS := requirements-jazzy.in
CONS := constraints-jazzy.txt
PATCH := tools/patch_cmake_exports.py
MAKE_VENV := tools/make_venv.sh
# uv (fast) or pip; uv falls back to pip by itself if uv cannot be installed.
INSTALLER ?= uv

# The venv is keyed on the content of the pins and of the install scripts, and on where the
# clone lives (the venv is not relocatable): a stamp with that key makes `make venv` a no-op.
VENV_KEY := $(shell { cat $(REQS) $(CONS) $(PATCH) $(MAKE_VENV); echo '$(CURDIR) $(PYTHON)'; } \
              | sha256sum | cut -c1-16)
VENV_STAMP := $(VENV)/.stamp-$(VENV_KEY)

COLCON_PKG_ARGS := --base-paths . msg_defs
# No live status line / desktop notification / terminal title: plain logs for CI.
COLCON_BUILD_ARGS := --event-handlers status- desktop_notification- terminal_title-

# Several people (and their make runs) share one work tree: serialise the venv install and
# the colcon build with flock so two runs never write the same tree at once.
FLOCK := $(shell command -v flock 2>/dev/null)
locked = $(if $(FLOCK),$(FLOCK) $(1))

# Sources the workspace environment (tools/env.sh) in a recipe.
WS_ENV := source tools/env.sh
VENV_ENV := source tools/env.sh --venv-only

.PHONY: all venv build test lint demo bench clean distclean lock sysdeps help

all: test

help:
	@sed -n '3,7p' Makefile | sed 's/^# \{0,1\}//'

sysdeps:
	@bash tools/ensure_system_deps.sh $(PYTHON)

venv: $(VENV_STAMP)

$(VENV_STAMP): | sysdeps
	@$(call locked,.venv.lock) bash $(MAKE_VENV) $(PYTHON) $(VENV) $@ $(INSTALLER)

build: venv | sysdeps
	@echo "== build: colcon build (rotor_id_msgs, rotor_id)"
	@$(VENV_ENV) && \
	  $(call locked,.build.lock) colcon build $(COLCON_PKG_ARGS) $(COLCON_BUILD_ARGS)
	@# byte-compile our sources and the generated message code once here, so that starting
	@# ./rotor-id reads .pyc even where PYTHONDONTWRITEBYTECODE is set (see tools/make_venv.sh)
	@$(VENV_ENV) && python -m compileall -q rotor_id install > /dev/null
	@# compile the numba kernel into its cache now (2-6 s once), not in a user's first study
	@$(WS_ENV) && python -m rotor_id.estimation.kernels

# Both cores (pytest-xdist; tests take their ROS domains from test/ros_domains.py), and the
# 25 slowest tests listed at the end, so that a slow newcomer is seen in every CI log.
PYTEST_ARGS ?= -n 2 --durations=25

test: build
	@echo "== test: pytest $(PYTEST_ARGS)"
	@$(WS_ENV) && python -m pytest $(PYTEST_ARGS)

# Only the ament linters (flake8, pep257), one run each, ~30 s: run before committing.
lint: venv
	@$(VENV_ENV) && python -m pytest -q -m linter test/test_flake8.py test/test_pep257.py

demo: build
	./rotor-id demo

bench: build
	@$(WS_ENV) && python bench/run_all.py

# Re-lock after editing requirements-jazzy.in: the new packages resolve freely, every
# existing pin is kept; then the venv is re-keyed on the new lock (a no-op install).
lock: venv
	@{ sed -n '/^#/p' $(CONS); $(VPY) -m pip freeze --all --disable-pip-version-check \
	    | grep -v -i '^pip=='; } > $(CONS).new && mv $(CONS).new $(CONS)
	@$(MAKE) venv
	@git diff --stat -- $(CONS) || true

clean:
	rm -rf build install log .pytest_cache .hypothesis *.egg-info
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
