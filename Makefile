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
# sourced by both venv scripts
VENV_COMMON := tools/venv_common.sh
# uv (fast) or pip; uv falls back to pip by itself if uv cannot be installed.
INSTALLER ?= uv

# The venv is keyed on the content of the pins and of the install scripts, and on where the
# clone lives (the venv is not relocatable): a stamp with that key makes `make venv` a no-op.
VENV_KEY := $(shell { cat $(REQS) $(CONS) $(PATCH) $(MAKE_VENV) $(VENV_COMMON); \
              echo '$(CURDIR) $(PYTHON)'; } | sha256sum | cut -c1-16)
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

# The numba kernels are compiled now, not in a user's first study: ahead of time into two
# extension modules (two processes, about 2 min of CPU, once per change of the kernels), or
# where that fails just in time into numba's cache (rotor_id/estimation/kernels.py main). They
# need only the venv, so they compile while colcon builds the messages; their lines are printed
# after colcon's. They run in a session of their own, terminated on Ctrl-C with their compiler
# processes (a background job ignores SIGINT: it would compile on to its end).
KERNELS_LOG := log/kernels_build.log

build: venv | sysdeps
	@echo "== build: colcon build (rotor_id_msgs, rotor_id), the numba kernels beside it"
	@mkdir -p log
	@$(VENV_ENV) && { setsid -w python -m rotor_id.estimation.kernels > $(KERNELS_LOG) 2>&1 & \
	  kernels=$$!; trap 'kill -TERM -- -$$kernels 2> /dev/null' INT TERM; status=0; \
	  $(call locked,.build.lock) colcon build $(COLCON_PKG_ARGS) $(COLCON_BUILD_ARGS) \
	    || status=$$?; \
	  wait $$kernels || true; cat $(KERNELS_LOG); exit $$status; }
	@# byte-compile our sources and the generated message code once here, so that starting
	@# ./rotor-id reads .pyc even where PYTHONDONTWRITEBYTECODE is set (see tools/make_venv.sh)
	@$(VENV_ENV) && python -m compileall -q rotor_id install > /dev/null

# Both cores (pytest-xdist; tests take their ROS domains from test/ros_domains.py), and the
# 25 slowest tests listed at the end, so that a slow newcomer is seen in every CI log.
PYTEST_ARGS ?= -n 2 --durations=25
# The live tests (nodes on the clock: as processes on a DDS graph, or in the test process) run
# one at a time at normal priority, beside the rest, which run at the lowest; the source checks
# (linters, mypy, the package's import structure: they need only the venv) run beside the
# build. tools/test_lanes.sh arranges the lanes and says why.
LIVE_TESTS := test/integration test/nodes
SOURCE_TESTS := test/test_flake8.py test/test_pep257.py test/test_types.py \
                test/test_package_shape.py
LIVE_LOG := log/live_tests.log
SOURCE_LOG := log/source_checks.log
STOCK_LOG := log/test_stock.log

# The stock-stack venv (test-stock, below; mostly file copies) is installed while the main venv
# and the workspace are built; its lines are printed after theirs.
STOCK_VENV_LOG := log/venv_stock.log

test:
	@MAKE='$(MAKE)' PYTEST_ARGS='$(PYTEST_ARGS)' LIVE_TESTS='$(LIVE_TESTS)' \
	  SOURCE_TESTS='$(SOURCE_TESTS)' SOURCE_LOG=$(SOURCE_LOG) LIVE_LOG=$(LIVE_LOG) \
	  STOCK_LOG=$(STOCK_LOG) STOCK_VENV_LOG=$(STOCK_VENV_LOG) bash tools/test_lanes.sh

# The library's tests again on the stack of a stock Jazzy install (Ubuntu 24.04: Python 3.12,
# numpy 1.26, scipy 1.11; no ROS, no numba) in their own venv, .venv-stock (never the main
# .venv), keyed like the main venv. Only the library's fast tests: the ROS tests (marker ros)
# need rclpy, whose wheels exist for Python 3.11 only; the tests of the compiled kernels
# (marker numba) compare them with numpy, so they need numba.
PYTHON_STOCK ?= python3.12
VENV_STOCK := .venv-stock
REQS_STOCK := requirements-stock.txt
MAKE_VENV_STOCK := tools/make_stock_venv.sh
VENV_STOCK_KEY := $(shell { cat $(REQS_STOCK) $(MAKE_VENV_STOCK) $(VENV_COMMON); \
                    echo '$(CURDIR) $(PYTHON_STOCK)'; } | sha256sum | cut -c1-16)
VENV_STOCK_STAMP := $(VENV_STOCK)/.stamp-$(VENV_STOCK_KEY)
STOCK_TESTS := test/physics test/estimation test/io test/commands test/report \
               test/test_adequacy.py test/test_excitation.py test/test_planning.py
# Left out there (--deselect takes node-id prefixes): the tests of more than ~2 s there (without
# numba its numpy reference path is several times slower). This run checks that every path
# runs on that stack, which the fast tests call; the heavier ones repeat those calls for their
# statistics. Each of their modules keeps its faster tests here, and the main run has them all.
STOCK_FE := test/estimation/test_filter_error.py
STOCK_EE := test/estimation/test_equation_error.py
STOCK_FEG := test/estimation/test_filter_error_gradient.py
STOCK_SIM := test/estimation/test_simulate.py
STOCK_ANY := test/physics/test_any_rotor_identification.py
STOCK_DESELECT := \
  $(STOCK_FE)::test_steady_state_gain_for_a_time_invariant_model \
  $(STOCK_FE)::test_system_noise_filter_error_beats_output_error_ci \
  $(STOCK_FE)::test_identify_recording_with_each_method \
  $(STOCK_FE)::test_no_process_noise_estimated_agrees_with_output_error \
  $(STOCK_FE)::test_marginal_bounds_stay_on_the_branch_of_optima \
  $(STOCK_FE)::test_residuals_are_the_innovations_at_the_estimate \
  $(STOCK_FE)::test_marginal_bounds_approach_the_bound_where_the_data_fix_sigma_v \
  $(STOCK_FEG)::test_analytic_gradient_matches_differences_of_the_likelihood \
  test/estimation/test_monte_carlo.py::test_estimates_scatter_as_the_cramer_rao_bound \
  test/estimation/test_monte_carlo.py::test_reference_is_truth_or_modelling_bias \
  test/estimation/test_monte_carlo.py::test_limits_reject_wrong_bounds \
  $(STOCK_EE)::test_iterated_equation_error_is_less_accurate_than_maximum_likelihood \
  $(STOCK_EE)::test_equation_error_covariance_is_not_a_confidence_measure \
  test/test_planning.py::test_predicted_sigma_matches_identify_spread \
  test/commands/test_campaign.py::test_campaign_identifies_every_bag_flags_the_outlier \
  test/io/test_io_fuzz.py::test_random_mappings_parse_or_raise_run_description_error \
  test/io/test_io_window.py::test_memory_and_reading_follow_the_window_not_the_bag \
  test/io/test_io_window.py::test_window_read_equals_the_full_read \
  test/io/test_io_window.py::test_small_bags_and_clock_trouble_are_read_whole \
  test/io/test_io_fuzz.py::test_mutated_valid_descriptions_parse_or_raise \
  $(STOCK_SIM)::test_lost_samples_cost_their_own_substeps_not_the_whole_records \
  $(STOCK_FEG)::test_analytic_gradient_with_output_offsets_and_two_runs \
  $(STOCK_FEG)::test_fit_with_analytic_gradients_lands_on_the_same_optimum \
  test/test_adequacy.py::test_false_alarms_and_whiteness_calibration_on_simulated_records \
  $(STOCK_ANY)::test_independent_blade_by_blade_rotors_identified_within_bounds \
  $(STOCK_ANY)::test_identify_command_on_a_five_bladed_bag \
  test/commands/test_identify_runs.py::test_joint_sigma_shrinks_as_the_information_of_the_runs_adds

.PHONY: venv-stock test-stock typecheck

venv-stock: $(VENV_STOCK_STAMP)

$(VENV_STOCK_STAMP):
	@$(call locked,.venv-stock.lock) bash $(MAKE_VENV_STOCK) $(PYTHON_STOCK) $(VENV_STOCK) $@ \
	  $(INSTALLER)

test-stock: venv-stock
	@echo "== test-stock: pytest on $$($(VENV_STOCK)/bin/python -c 'import sys, numpy, scipy; \
	  print(f"Python {sys.version.split()[0]}, numpy {numpy.__version__}, \
	  scipy {scipy.__version__}")')"
	@env -u PYTHONPATH -u AMENT_PREFIX_PATH PYTHONPATH=$(CURDIR) \
	  $(VENV_STOCK)/bin/python -m pytest -q -n 2 -m 'not slow and not ros and not numba' \
	    $(addprefix --deselect ,$(STOCK_DESELECT)) $(STOCK_TESTS)

# mypy over the annotated library modules (mypy.ini).
typecheck: venv
	@$(VENV_ENV) && python -m mypy

# The ament linters (flake8, pep257, one run each) and mypy, ~1 min: run before committing.
lint: venv
	@$(VENV_ENV) && python -m pytest -q -m linter test/test_flake8.py test/test_pep257.py
	@$(MAKE) typecheck

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
	rm -rf build install log .pytest_cache .hypothesis *.egg-info rotor_id/estimation/_kernels_aot_*
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
