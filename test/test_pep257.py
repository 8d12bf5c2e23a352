"""
ament_pep257 over our Python sources, in one run.

The ament_python template's test (ament convention: multi-line docstrings start their
summary on the second line), scoped to the sources. One run over every file: pydocstyle
prints each error with its file and line.
"""

from ament_pep257.main import main
from lint_sources import REPO_ROOT, sources
import pytest


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    rc = main(argv=[str(REPO_ROOT / path) for path in sources()])
    assert rc == 0, 'Found code style errors / warnings (listed above with file and line)'
