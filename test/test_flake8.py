"""
ament_flake8 over our Python sources, one test per file.

The ament_python template's test, scoped to the sources (never the venv or colcon's
build/install/log trees) and split per file so a failure names its file.
"""

from pathlib import Path

from ament_flake8.main import main_with_errors
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
LINTED_DIRS = ('rotor_id', 'test', 'tools')

# Files that failed flake8 when this test was introduced. Owners: fix the file, then
# delete its entry (an XPASS in the summary means it is clean now). Don't add entries.
LINT_DEBT = {
}


def sources():
    """Return the linted Python files, relative to the repository root."""
    files = [REPO_ROOT / 'setup.py']
    for directory in LINTED_DIRS:
        files += sorted((REPO_ROOT / directory).rglob('*.py'))
    # like ament_flake8/ament_pep257: skip directories starting with '.' or '_'
    return [f.relative_to(REPO_ROOT).as_posix() for f in files
            if not any(d.startswith(('.', '_')) for d in f.relative_to(REPO_ROOT).parts[:-1])]


@pytest.mark.flake8
@pytest.mark.linter
@pytest.mark.parametrize('path', sources())
def test_flake8(path, monkeypatch, tmp_path, request):
    if path in LINT_DEBT:
        request.applymarker(pytest.mark.xfail(reason='lint debt (LINT_DEBT)', strict=False))
    # ament_flake8 walks the current directory for AMENT_IGNORE markers: start it in an
    # empty one so it doesn't crawl the venv, and hand it an absolute path.
    monkeypatch.chdir(tmp_path)
    rc, errors = main_with_errors(argv=[str(REPO_ROOT / path)])
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors)
