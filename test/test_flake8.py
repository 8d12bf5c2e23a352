"""
ament_flake8 over our Python sources, in one run.

The ament_python template's test, scoped to the sources (never the venv or colcon's
build/install/log trees). One flake8 run over every file: each error line names its file,
so nothing is lost against a test per file, and the suite pays one start-up instead of one
per file.
"""

from ament_flake8.main import main_with_errors
from lint_sources import REPO_ROOT, sources
import pytest


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch, tmp_path):
    # ament_flake8 walks the current directory for AMENT_IGNORE markers: start it in an
    # empty one so it doesn't crawl the venv, and hand it absolute paths.
    monkeypatch.chdir(tmp_path)
    rc, errors = main_with_errors(argv=[str(REPO_ROOT / path) for path in sources()])
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors)
