"""Fixtures of the input-layer tests."""

from practice import require_practice
import pytest


@pytest.fixture(scope='session')
def recordings():
    """Return the directory of the shared test-stand recordings; skip if absent."""
    return require_practice()
