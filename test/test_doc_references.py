"""
Every document that the code, the configuration and the docs cite is in the repository.

A reader who follows a citation must find the file. Three kinds of citation are checked in every
tracked text file:

* a document named in capitals, as README.md: a bare name must be the name of a tracked file,
  a path must exist from the repository root or from the citing file's directory;
* a path into ``docs/`` or ``bench/results/``: it must exist;
* a section sign after a capitalised document name, with or without ``.md``: that document
  must be tracked.

Lower-case bare names (``campaign.md``) are files that a command writes, and ``OUT.md`` a
placeholder of a command line, not citations. Tests
that read the shared practice recordings may cite them as ``../shared/...`` (they skip without
them).
"""

from pathlib import Path
import re
import subprocess

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
TEXT_SUFFIXES = {'.py', '.md', '.yaml', '.yml', '.xml', '.cfg', '.ini', '.sh', '.txt', '.in',
                 '.msg', '.srv', ''}
CAPITAL_DOC = re.compile(r'(?<![\w/.<-])((?:[\w.-]+/)*[A-Z][A-Z0-9_-]+\.md)\b')
DOCS_PATH = re.compile(r'(?<![\w/.<-])((?:docs|bench/results)/[\w.-]+\.md)\b')
SECTION = re.compile(r'\b([A-Z][A-Z_]{3,})(?:\.md)? ?§')
#: names of command-line placeholders (``--markdown OUT.md``, ``OUTDIR/campaign.md``)
PLACEHOLDERS = {'OUT', 'OUTDIR', 'FILE', 'PATH', 'NAME', 'DIR'}


def tracked_files():
    """Return the repository's tracked text files (git ls-files; a walk without git)."""
    try:
        names = subprocess.run(['git', 'ls-files'], cwd=REPO_ROOT, capture_output=True,
                               text=True, check=True, timeout=60).stdout.split()
    except (OSError, subprocess.SubprocessError):
        skip = {'.git', '.venv', 'build', 'install', 'log', '__pycache__'}
        names = [str(p.relative_to(REPO_ROOT)) for p in REPO_ROOT.rglob('*')
                 if p.is_file() and not skip & set(p.relative_to(REPO_ROOT).parts)]
    return sorted(n for n in names if Path(n).suffix in TEXT_SUFFIXES
                  and (REPO_ROOT / n).is_file())


TRACKED = tracked_files()
TRACKED_NAMES = {Path(n).name for n in TRACKED}


def unresolved_citations(relative, text):
    """Return the citations in ``text`` (of file ``relative``) that name no tracked file."""
    here = (REPO_ROOT / relative).parent
    bad = []
    for match in CAPITAL_DOC.finditer(text):
        cited = match.group(1)
        if re.split(r'[/.]', cited)[0] in PLACEHOLDERS:
            continue
        if '/' not in cited:
            ok = cited in TRACKED_NAMES
        else:
            ok = ((REPO_ROOT / cited).is_file() or (here / cited).is_file()
                  or (relative.startswith('test/') and cited.startswith('../shared/')))
        if not ok:
            bad.append(cited)
    for match in DOCS_PATH.finditer(text):
        if not (REPO_ROOT / match.group(1)).is_file() and match.group(1) not in bad:
            bad.append(match.group(1))
    for match in SECTION.finditer(text):
        if f'{match.group(1)}.md' not in TRACKED_NAMES:
            bad.append(match.group(0))
    return bad


@pytest.mark.parametrize('relative', TRACKED)
def test_cited_documents_are_in_the_repository(relative):
    text = (REPO_ROOT / relative).read_text(encoding='utf-8', errors='replace')
    bad = unresolved_citations(relative, text)
    assert not bad, f'{relative} cites what the repository does not hold: {sorted(set(bad))}'


def test_the_check_finds_what_it_must():
    missing = 'NO' + 'SUCH'            # spelled apart: this file names no missing document
    found = unresolved_citations('rotor_id/x.py', f'see {missing}.md, docs/{missing}.md and '
                                 f'{missing} §4; README.md and docs/models.md exist; '
                                 'campaign.md is an output')
    assert found == [f'{missing}.md', f'docs/{missing}.md', f'{missing} §']
    assert unresolved_citations('rotor_id/x.py', 'ok: README.md, docs/run_description.md') == []
