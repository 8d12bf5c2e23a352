"""Shared pytest fixtures: repository paths, the built workspace, ROS isolation."""

import os
from pathlib import Path
import sys

import pytest

import rotor_id  # noqa: F401 - before the tests import numpy: one BLAS thread (see there)

try:
    from hypothesis import settings
except ImportError:  # the pure tests still run without hypothesis
    settings = None

REPO_ROOT = Path(__file__).resolve().parents[1]

if settings is not None:
    # Timing on the 2-core CI machine is noisy: no per-example deadline.
    settings.register_profile('rotor_id', deadline=None, print_blob=True)
    # CI: the same examples on every run (a new random example that fails is found by a
    # developer's run, with its blob printed, not by a CI run of an unrelated change)
    settings.register_profile('ci', deadline=None, print_blob=True, derandomize=True,
                              database=None)
    settings.load_profile(os.environ.get('HYPOTHESIS_PROFILE',
                                         'ci' if os.environ.get('CI') else 'rotor_id'))


@pytest.fixture(scope='session', autouse=True)
def compiled_kernels():
    """
    Put this process's simulations on one kernel from the start (the compiled one).

    With ROTOR_ID_KERNELS=auto a process switches from numpy to the compiled kernel once its
    simulations have taken 0.5 s; results then differ in the last bits (1e-10 after a fit), so
    tests that compare two fits bit for bit must not straddle that switch. Commands run as
    subprocesses keep the default. test_kernels compares the two paths.
    """
    from rotor_id.estimation import kernels
    kernels.prefer()


@pytest.fixture(scope='session')
def repo_root():
    """Return the repository root (the rotor_id package's source directory)."""
    return REPO_ROOT


@pytest.fixture(scope='session')
def venv_prefix():
    """Return the prefix of the venv running the tests; skip if not run from a venv."""
    if sys.prefix == sys.base_prefix:
        pytest.skip('not running in a venv (run `make test`, which uses .venv)')
    return Path(sys.prefix)


@pytest.fixture(scope='session')
def install_prefix(repo_root):
    """Return <repo>/install of the colcon build; skip if the workspace is not built."""
    prefix = repo_root / 'install'
    if not (prefix / 'local_setup.sh').is_file():
        pytest.skip(f'no colcon install tree at {prefix} (run `make test`, which builds it)')
    return prefix


@pytest.fixture
def ros_domain_id():
    """Return a ROS_DOMAIN_ID that no other test of the run uses at the same time."""
    from ros_domains import next_domain
    return next_domain()


@pytest.fixture
def ros_env(ros_domain_id, tmp_path):
    """Return an environment for ROS subprocesses isolated to this test and to loopback."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(ros_domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_LOG_DIR'] = str(tmp_path / 'ros_log')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def pytest_collection_modifyitems(config, items):
    """
    Run the linters first; skip the long statistical studies unless ROTOR_ID_SLOW=1.

    The linters (marker ``linter``: flake8, mypy, pep257) are the longest single tests, each a
    whole-tree run of half a minute of CPU. pytest-xdist hands out tests in collection order,
    so where they are collected last (test/test_types.py sorts near the end) one worker runs
    mypy alone while the other has nothing left: the run's tail. First, they run beside the
    rest. The order within each group stays as collected (module fixtures keep their scope).
    """
    items.sort(key=lambda item: item.get_closest_marker('linter') is None)   # stable sort
    if os.environ.get('ROTOR_ID_SLOW'):
        return
    skip = pytest.mark.skip(reason='long statistical study: set ROTOR_ID_SLOW=1 to run it '
                                   '(CI runs a smaller variant)')
    for item in items:
        # the marker itself: keywords also hold the names of the directories above the test
        if item.get_closest_marker('study') is not None:
            item.add_marker(skip)


def pytest_terminal_summary(terminalreporter):
    """Count the tests skipped for want of the practice recordings, in a line of their own."""
    from practice import RECORDINGS, SKIP_REASON
    skipped = [r for r in terminalreporter.stats.get('skipped', [])
               if SKIP_REASON in str(getattr(r, 'longrepr', ''))]
    if skipped:
        terminalreporter.write_line(
            f'{len(skipped)} tests skipped: {SKIP_REASON} ({RECORDINGS}); their claims were '
            'not checked', yellow=True, bold=True)
