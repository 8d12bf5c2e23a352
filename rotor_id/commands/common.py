"""
What every command shares: output paths checked before the work, warnings printed once.

* :func:`check_output_paths` is called by each command before it reads a bag or fits anything,
  so that ``--json`` naming a directory, a path under a regular file or a read-only file system
  is exit 2 with one line at once, not a traceback after the whole fit.
* :func:`print_warning` prints ``warning: ...`` on stderr, each text once per command.
  :func:`rotor_id.cli.main` routes Python's ``warnings`` through it too (:func:`capture_warnings`),
  so a warning that the library both issues and returns in a result is not printed twice, and
  every warning has the same one-line form.
"""

import contextlib
import errno
import os
from pathlib import Path
import sys
from typing import Iterable, Iterator, TextIO, TYPE_CHECKING
import warnings

if TYPE_CHECKING:
    from rotor_id.io.record import Record


class OutputPathError(ValueError):
    """An output path given on the command line cannot be written."""


_printed: set[str] = set()


def print_warning(text: object, stream: TextIO | None = None) -> None:
    """Print ``warning: text`` on stderr unless this text was already printed."""
    text = str(text).strip()
    if text.startswith('warning: '):
        text = text[len('warning: '):]
    if not text or text in _printed:
        return
    _printed.add(text)
    print(f'warning: {text}', file=stream or sys.stderr, flush=True)


def repairs_json(records: Iterable['Record']) -> list:
    """Every reading the records' reader replaced, as the commands' JSON ``repairs`` lists it."""
    return [repair.as_json() for record in records for repair in record.repairs]


def print_warnings(texts: Iterable[object], stream: TextIO | None = None) -> None:
    """Print each of ``texts`` with :func:`print_warning`."""
    for text in texts:
        print_warning(text, stream)


@contextlib.contextmanager
def capture_warnings() -> Iterator[None]:
    """
    Within the block, Python warnings are printed by :func:`print_warning` (once each).

    Deprecation notices (a library's, for its developers) are not printed.

    The input layer's warnings (:class:`~rotor_id.io.errors.BagWarning`,
    :class:`~rotor_id.io.errors.RunDescriptionWarning`) are also returned as values (a Record's
    and a RunDescription's ``warnings``), which the commands print item by item; the Python
    warning repeating them is not printed again.
    """
    from rotor_id.io.errors import BagWarning, RunDescriptionWarning
    _printed.clear()
    with warnings.catch_warnings():
        warnings.simplefilter('always')
        # a library's deprecation notices are for its developers, not for a test engineer
        # (a dependency importing a deprecated module printed 'warning: module ... is
        # deprecated' at every demo)
        warnings.simplefilter('ignore', DeprecationWarning)
        warnings.simplefilter('ignore', PendingDeprecationWarning)
        warnings.simplefilter('ignore', BagWarning)
        warnings.simplefilter('ignore', RunDescriptionWarning)

        def show(message, category, filename, lineno, file=None, line=None):
            print_warning(str(message))
        warnings.showwarning = show
        try:
            yield
        finally:
            _printed.clear()


def _reason(err):
    if err.errno == errno.EROFS:
        return 'the file system is read-only'
    if err.errno in (errno.EACCES, errno.EPERM):
        return 'permission denied'
    if err.errno == errno.ENOTDIR:
        return 'a part of the path is a regular file, not a directory'
    if err.errno == errno.EISDIR:
        return 'it is a directory'
    return err.strerror or str(err)


def check_output_path(option: str, path: str | os.PathLike | None,
                      directory: bool = False) -> None:
    """
    Check that ``path`` can be written (a file, or a directory when ``directory``).

    Missing parent directories are created (the command would create them anyway); a file
    that does not exist yet is created and removed again, so the check is the real one (a
    read-only file system or a full quota show up here, not after the fit).

    Raises
    ------
    OutputPathError
        One line naming the option, the path, the cause and what to do.

    """
    if path is None:
        return
    target = Path(path)
    what = 'a directory' if directory else 'a file'

    def fail(cause):
        raise OutputPathError(f'{option} {path}: cannot write {what} there ({cause}); give '
                              f'a writable {"directory" if directory else "file path"}')
    if str(path) == '':
        fail('the path is empty')
    if not directory and target.is_dir():
        fail('it is a directory; give a file name inside it, e.g. '
             f'{target / ("result.png" if option == "--figure" else "result.json")}')
    if directory and target.exists() and not target.is_dir():
        fail('a file of that name exists')
    for parent in target.parents:
        if parent.exists():
            if not parent.is_dir():
                fail(f'{parent} is a regular file, not a directory')
            break
    try:
        if directory:
            target.mkdir(parents=True, exist_ok=True)
            probe = target / f'.rotor_id_write_test_{os.getpid()}'
            probe.touch()
            probe.unlink()
            return
        target.parent.mkdir(parents=True, exist_ok=True)
        existed = target.exists()
        with open(target, 'a'):
            pass
        if not existed:
            target.unlink()
    except OSError as err:
        fail(_reason(err))


def check_output_paths(**paths: str | os.PathLike | None) -> None:
    """Check each ``--option=path`` given (keys: option names without dashes, e.g. json)."""
    for name, path in paths.items():
        directory = name.endswith('_dir')
        option = '--' + (name[:-4] if directory else name).replace('_', '-')
        check_output_path(option, path, directory=directory)
