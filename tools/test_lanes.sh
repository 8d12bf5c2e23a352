#!/usr/bin/env bash
# make test: install, build and run every test, in lanes that keep both cores busy.
#
# Called by the Makefile's test target with its settings in the environment: MAKE,
# PYTEST_ARGS, LIVE_TESTS, SOURCE_TESTS and the log files SOURCE_LOG, LIVE_LOG, STOCK_LOG,
# STOCK_VENV_LOG. On this 2-core VM `make test` is bound by CPU, so the lanes are arranged
# to leave no core idle:
#
#   venv          the main venv; the stock-stack venv (mostly file copies) beside it
#   source checks flake8, pep257, mypy and the package-shape test, which read the sources and
#                 need only the venv: from the moment it is ready, at the lowest priority, so
#                 they take what the build leaves (the larger half of the kernels compiles
#                 on alone for a while after colcon has finished)
#   build         colcon and the numba kernels (make build)
#   the rest      at the lowest priority on both cores (pytest-xdist), beside
#   live          the tests whose nodes run on the clock (LIVE_TESTS), one at a time at normal
#                 priority, then the library's tests on the stock stack (make test-stock)
#
# Why the priorities: side by side on this VM, CPU-bound tests starved the live ones (node
# processes fell behind the clock). Linux shares the CPU between sessions before it weighs
# nice values within one (autogroups), and every node process starts its own session: so each
# low-priority lane runs in a session of its own whose autogroup is lowered as well (raising
# either needs no privilege). The foreground lane takes Ctrl-C; the sessions in the background
# are then terminated (a background job ignores SIGINT). Each lane's lines are printed after
# the rest's; the exit status is not 0 if any lane failed.
set -uo pipefail
cd "$(dirname "$0")/.."
mkdir -p log

sessions=()
stop() {
  for session in "${sessions[@]}"; do kill -TERM -- "-$session" 2> /dev/null; done
  exit 130
}
trap stop INT TERM

# Run "$@" in a session of its own at the lowest CPU priority, in the background; its pid
# (also its session's id) is appended to sessions.
low_priority() {
  setsid -w bash -c 'echo 19 2> /dev/null > /proc/self/autogroup; exec nice -n 19 "$@"' \
    low_priority "$@" &
  sessions+=("$!")
}

status=0
"$MAKE" venv-stock > "$STOCK_VENV_LOG" 2>&1 &
stock_venv=$!
"$MAKE" venv || status=$?
if [ "$status" != 0 ]; then wait "$stock_venv"; exit "$status"; fi

# shellcheck source=tools/env.sh
source tools/env.sh --venv-only
low_priority python -m pytest -p no:cacheprovider --durations=5 $SOURCE_TESTS \
  > "$SOURCE_LOG" 2>&1
sources=$!

"$MAKE" build || status=$?
wait "$stock_venv" || status=1
cat "$STOCK_VENV_LOG"

if [ "$status" = 0 ]; then
  # shellcheck source=tools/env.sh
  source tools/env.sh
  echo "== test: pytest $PYTEST_ARGS at the lowest CPU priority, beside the live tests"
  ignored=()
  for path in $LIVE_TESTS $SOURCE_TESTS; do ignored+=("--ignore=$path"); done
  # shellcheck disable=SC2086 # PYTEST_ARGS is a list of options
  low_priority python -m pytest $PYTEST_ARGS "${ignored[@]}"
  rest=$!
  # shellcheck disable=SC2086 # LIVE_TESTS is a list of paths
  python -m pytest -p no:cacheprovider --durations=10 $LIVE_TESTS > "$LIVE_LOG" 2>&1 \
    || live=1
  "$MAKE" test-stock > "$STOCK_LOG" 2>&1 || stock=1
  wait "$rest" || status=1
  echo "== test: the live tests ($LIVE_TESTS), one at a time beside the rest"
  cat "$LIVE_LOG"
  echo "== test: the library's tests on the stock stack (make test-stock), after the live ones"
  cat "$STOCK_LOG"
  [ -z "${live:-}" ] && [ -z "${stock:-}" ] || status=1
fi

wait "$sources" || status=1
echo "== test: the source checks ($SOURCE_TESTS), beside the build"
cat "$SOURCE_LOG"
exit "$status"
