"""
ament_flake8 over our Python sources, one test per file.

The ament_python template's test, scoped to the sources (never the venv or colcon's
build/install/log trees) and split per file so a failure names its file.
"""

from ament_flake8.main import main_with_errors
from lint_sources import REPO_ROOT, sources
import pytest


@pytest.mark.flake8
@pytest.mark.linter
@pytest.mark.parametrize('path', sources())
def test_flake8(path, monkeypatch, tmp_path):
    # ament_flake8 walks the current directory for AMENT_IGNORE markers: start it in an
    # empty one so it doesn't crawl the venv, and hand it an absolute path.
    monkeypatch.chdir(tmp_path)
    rc, errors = main_with_errors(argv=[str(REPO_ROOT / path)])
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors)
