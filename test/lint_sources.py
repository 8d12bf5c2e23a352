"""The Python files the ament linters check (shared by test_flake8 and test_pep257)."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
LINTED_DIRS = ('rotor_id', 'test', 'tools', 'bench')


def sources():
    """Return the linted Python files, relative to the repository root."""
    files = [REPO_ROOT / 'setup.py']
    for directory in LINTED_DIRS:
        files += sorted((REPO_ROOT / directory).rglob('*.py'))
    # like ament_flake8/ament_pep257: skip directories starting with '.' or '_'
    return [f.relative_to(REPO_ROOT).as_posix() for f in files
            if not any(d.startswith(('.', '_')) for d in f.relative_to(REPO_ROOT).parts[:-1])]
