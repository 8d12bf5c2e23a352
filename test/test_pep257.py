"""
ament_pep257 over our Python sources, one test per file.

The ament_python template's test (ament convention: multi-line docstrings start their
summary on the second line), scoped to the sources and split per file.
"""

from ament_pep257.main import main
from lint_sources import REPO_ROOT, sources
import pytest


@pytest.mark.linter
@pytest.mark.pep257
@pytest.mark.parametrize('path', sources())
def test_pep257(path):
    rc = main(argv=[str(REPO_ROOT / path)])
    assert rc == 0, 'Found code style errors / warnings'
