"""
mypy over the library modules whose public API is annotated (the list is mypy.ini's).

The same check as ``make typecheck``, inside the suite so that CI runs it too.
"""

import os

import pytest

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.linter
def test_mypy_is_clean_on_the_annotated_modules(monkeypatch):
    api = pytest.importorskip('mypy.api', reason='mypy is not installed (make venv installs it)')
    monkeypatch.chdir(REPO_ROOT)
    out, err, status = api.run(['--config-file', 'mypy.ini', '--no-incremental'])
    assert status == 0, out + err
