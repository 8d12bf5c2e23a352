"""
The product carries no development history: it belongs in git log and the issue tracker.

Checked: README.md, docs/**, bench/results/**, bench/*.py and test/** in full; the comments and
string literals (docstrings, messages) of rotor_id/**. A user reads these; "the session that
measured it", "issue 15's target", a figure kept beside its predecessor or the commit a number
was taken on tells them nothing about the product and goes stale at the next change.

Found and reported per file:

* the word "session" (any case), except the Python and pytest names that mean something else
  (``start_new_session``, ``scope='session'``);
* a reference to an issue ("issue 16", "#16"), except in a test as the short tag ``pins #N``
  that marks a behaviour an issue defined;
* a commit hash (7 to 40 lowercase hex digits with at least one letter and one digit).

This file names what it looks for and is not checked itself.
"""

import functools
import io
from pathlib import Path
import re
import tokenize

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

SESSION = re.compile(r'session', re.I)
#: Names of Python and pytest that use the word in their own sense.
SESSION_API = re.compile(r"start_new_session|scope\s*=\s*['\"]session['\"]")
ISSUE = re.compile(r'\bissues?\s*#?\s*\d+', re.I)
#: "#16"; in Markdown not inside fenced code, where it is a program's output ("candidate #5")
ISSUE_HASH = re.compile(r'(?<![\w#&/])#\d+\b')
FENCED = re.compile(r'^```.*?^```', re.S | re.M)
TEST_TAG = re.compile(r'\bpins #\d+\b')
HEX_WORD = re.compile(r'(?<![\w.+-])[0-9a-f]{7,40}(?![\w.+-])')
_HASH_SCREEN = re.compile(r'(?<![\w.+-])(?=[0-9a-f]{0,39}[a-f])(?=[0-9a-f]{0,39}\d)'
                          r'[0-9a-f]{7,40}(?![\w.+-])')
TEXT_SUFFIXES = {'.md', '.py', '.json', '.yaml', '.yml', '.txt', '.csv', '.msg', '.srv', '.xml',
                 '.cfg', '.ini'}


def _files(pattern):
    return sorted(p for p in REPO_ROOT.glob(pattern)
                  if p.is_file() and p.suffix in TEXT_SUFFIXES and '__pycache__' not in p.parts)


def checked_files():
    """Return the files the rule applies to, as (path, whole file or code)."""
    paths = [REPO_ROOT / 'README.md'] + _files('docs/**/*') + _files('bench/results/**/*') \
        + _files('bench/*.py') + _files('test/**/*')
    paths = [p for p in paths if p.is_file() and p != Path(__file__).resolve()]
    return [(p, 'text') for p in paths] + \
        [(p, 'code') for p in _files('rotor_id/**/*.py')]


def prose_of_code(text):
    """Return the comments and string literals of Python source, one per line."""
    parts = []
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type in (tokenize.COMMENT, tokenize.STRING):
            parts.append(token.string)
        elif token.type == getattr(tokenize, 'FSTRING_MIDDLE', -1):
            parts.append(token.string)
    return '\n'.join(parts)


def findings(path, kind, in_tests=None):
    """Return the history found in one file: a list of short excerpts with their kind."""
    text = path.read_text(encoding='utf-8', errors='replace')
    if not _may_hold_history(text):
        return []
    if kind == 'code':
        text = prose_of_code(text)
    found = [f'session: {m.group(0)!r}' for m in SESSION.finditer(SESSION_API.sub('', text))]
    in_tests = _is_test(path) if in_tests is None else in_tests
    issue_text = TEST_TAG.sub('', text) if in_tests else text
    found += [f'issue reference: {m.group(0)!r}' for m in ISSUE.finditer(issue_text)]
    hash_text = FENCED.sub('', issue_text) if path.suffix == '.md' else issue_text
    found += [f'issue reference: {m.group(0)!r}' for m in ISSUE_HASH.finditer(hash_text)]
    found += [f'commit hash: {m.group(0)!r}' for m in HEX_WORD.finditer(text)
              if not m.group(0).isdigit() and not m.group(0).isalpha()]
    return found


def _may_hold_history(text):
    """Cheap screen before tokenizing: could any pattern match anywhere in the file."""
    lowered = text.lower()
    return ('session' in lowered or ('issue' in lowered and ISSUE.search(text) is not None)
            or ('#' in text and ISSUE_HASH.search(text) is not None)
            or _HASH_SCREEN.search(text) is not None)


def _is_test(path):
    try:
        path.relative_to(REPO_ROOT / 'test')
    except ValueError:
        return False
    return True


@functools.lru_cache(maxsize=1)
def scan():
    """Return {relative path: findings} for every checked file with history in it."""
    out = {}
    for path, kind in checked_files():
        found = findings(path, kind)
        if found:
            out[path.relative_to(REPO_ROOT).as_posix()] = found
    return out


def _report(offending):
    return '\n'.join(f'{path}: {len(found)} ({", ".join(sorted(set(found))[:4])}'
                     f'{", ..." if len(set(found)) > 4 else ""})'
                     for path, found in sorted(offending.items()))


def test_no_development_history_in_the_product():
    """Fail on any history in the product, listing each file with what was found."""
    offending = scan()
    assert not offending, 'development history in the product:\n' + _report(offending)


@pytest.mark.parametrize('text, expected', [
    ('measured in session 7 on 3f1279b', 2),
    ('see issue 16 and #15', 2),
    ('a JointState of 3 blades at 1.234567e-05 rad, seed 1234567', 0),
    ('the session bag', 1),
    ('```\nrecommended: #5 progressing\n```\n', 0),
    ('recommended: #5 progressing\n', 1),
])
def test_the_check_finds_what_it_should(tmp_path, text, expected):
    path = tmp_path / 'note.md'
    path.write_text(text)
    assert len(findings(path, 'text')) == expected


def test_a_test_may_carry_the_short_tag_only(tmp_path):
    path = tmp_path / 'test_x.py'
    path.write_text('"""The JSON keys (pins #3); issue 3 says why."""\n')
    assert findings(path, 'text', in_tests=True) == ["issue reference: 'issue 3'"]
    assert len(findings(path, 'text', in_tests=False)) == 2


def test_code_is_checked_in_its_comments_and_strings_only(tmp_path):
    path = tmp_path / 'module.py'
    path.write_text('"""Docstring (issue 4)."""\nsubprocess.Popen([], start_new_session=True)\n'
                    'x = 1  # as in session 3\nsession_like = 2\n')
    assert sorted(f.split(':')[0] for f in findings(path, 'code')) == \
        ['issue reference', 'session']
