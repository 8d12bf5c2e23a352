"""
The practice recordings beside the repository (``../shared/recordings``), and their skip.

Tests that read them call :func:`require_practice`; where the directory is absent (a clone
without ``../shared``) they skip with :data:`SKIP_REASON`, and the conftest's summary counts
those skips in a line of their own, so that a run without them is never taken for a full one.
"""

from pathlib import Path

import pytest

RECORDINGS = Path(__file__).resolve().parents[2] / 'shared' / 'recordings'
SKIP_REASON = 'practice recordings absent'


def practice_available() -> bool:
    """Return whether the practice recordings (with their answers) are beside the repository."""
    return (RECORDINGS / 'answers.json').is_file()


def require_practice() -> Path:
    """Return the practice recordings' directory; skip the calling test where it is absent."""
    if not practice_available():
        pytest.skip(f'{SKIP_REASON}: {RECORDINGS} not found (clone with ../shared beside it)')
    return RECORDINGS
