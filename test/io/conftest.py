"""Fixtures of the input-layer tests."""

from io_helpers import RECORDINGS
import pytest


@pytest.fixture(scope='session')
def recordings():
    """Return the directory of the shared test-stand recordings; skip if absent."""
    if not (RECORDINGS / 'README.md').is_file():
        pytest.skip(f'shared recordings not found at {RECORDINGS}')
    return RECORDINGS
