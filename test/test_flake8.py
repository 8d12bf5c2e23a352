"""
ament_flake8 over our Python sources, in one run.

The ament_python template's test, scoped to the sources (never the venv or colcon's
build/install/log trees). One flake8 run over every file: each error line names its file,
so nothing is lost against a test per file, and the suite pays one start-up instead of one
per file. flake8 checks files in a pool of forked processes, so it runs in a fresh process of
its own: a fork of a test process that already holds threads (rclpy's, a pytest-xdist
worker's) can deadlock.
"""

import subprocess
import sys

from lint_sources import REPO_ROOT, sources
import pytest

_RUN = ('import sys\n'
        'from ament_flake8.main import main_with_errors\n'
        'rc, errors = main_with_errors(argv=sys.argv[1:])\n'
        'print("\\n".join(errors))\n'
        'sys.exit(rc)\n')


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(tmp_path):
    # ament_flake8 walks the current directory for AMENT_IGNORE markers: start it in an
    # empty one so it doesn't crawl the venv, and hand it absolute paths.
    done = subprocess.run([sys.executable, '-c', _RUN]
                          + [str(REPO_ROOT / path) for path in sources()],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, 'code style errors / warnings:\n' + done.stdout + done.stderr
