"""
ament_pep257 over our Python sources, one test per file.

The ament_python template's test (ament convention: multi-line docstrings start their
summary on the second line), scoped to the sources and split per file.
"""

from pathlib import Path

from ament_pep257.main import main
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
LINTED_DIRS = ('rotor_id', 'test', 'tools')

# Files that failed pep257 when this test was introduced. Owners: fix the file, then
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


@pytest.mark.linter
@pytest.mark.pep257
@pytest.mark.parametrize('path', sources())
def test_pep257(path, request):
    if path in LINT_DEBT:
        request.applymarker(pytest.mark.xfail(reason='lint debt (LINT_DEBT)', strict=False))
    rc = main(argv=[str(REPO_ROOT / path)])
    assert rc == 0, 'Found code style errors / warnings'
