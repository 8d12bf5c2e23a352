#!/usr/bin/env python3
"""
Point the ros-* wheels' CMake exports at this interpreter's headers.

The ros-* message wheels were built in a manylinux container whose Python lived in
``/opt/python/cp3XX-cp3XX``. Their ``share/<pkg>/cmake/*.cmake`` export files carry that
container's absolute include paths (Python headers and numpy headers) in the
``INTERFACE_INCLUDE_DIRECTORIES`` of the ``<pkg>__rosidl_generator_py`` targets. Any package
that generates interfaces depending on those messages (our ``rotor_id_msgs`` depends on
std_msgs and builtin_interfaces) then fails at CMake generate time with::

    Imported target "std_msgs::std_msgs__rosidl_generator_py" includes non-existent path
      "/opt/python/cp311-cp311/include/python3.11"

This script rewrites those paths, in ``<prefix>/share/*/cmake/*.cmake`` only, to
``sysconfig.get_paths()['include']`` and ``numpy.get_include()`` of the interpreter that runs
it (run it with the venv's python). It is idempotent; re-run it after every install that
(re)installs ros-* message wheels. See TOOLCHAIN.md section 3.

Usage::

    .venv/bin/python tools/patch_cmake_exports.py            # patch, print a summary
    .venv/bin/python tools/patch_cmake_exports.py --check    # exit 1 if anything is left
"""

import argparse
from pathlib import Path
import re
import sys
import sysconfig

# The wheel builder's interpreter prefix, e.g. /opt/python/cp311-cp311.
_BUILDER_PREFIX = r'/opt/python/cp3\d+-cp3\d+'
# Its numpy headers; checked first because the Python pattern is not a prefix of it.
NUMPY_INCLUDE_RE = re.compile(
    _BUILDER_PREFIX + r'/lib/python3\.\d+/site-packages/numpy/(?:_core|core)/include')
PYTHON_INCLUDE_RE = re.compile(_BUILDER_PREFIX + r'/include/python3\.\d+')


def target_paths():
    """Return (python_include, numpy_include) of the running interpreter."""
    import numpy  # imported here so that --help works without numpy
    return sysconfig.get_paths()['include'], numpy.get_include()


def export_files(prefix):
    """Yield the CMake files of all packages installed under ``prefix``."""
    yield from sorted(Path(prefix).glob('share/*/cmake/*.cmake'))


def patch_text(text, python_include, numpy_include):
    """Return ``text`` with the builder's include paths replaced, and the count replaced."""
    text, n_numpy = NUMPY_INCLUDE_RE.subn(numpy_include.replace('\\', '/'), text)
    text, n_python = PYTHON_INCLUDE_RE.subn(python_include.replace('\\', '/'), text)
    return text, n_numpy + n_python


def leftovers(text):
    """Return the builder paths still present in ``text``."""
    return NUMPY_INCLUDE_RE.findall(text) + PYTHON_INCLUDE_RE.findall(text)


def main(argv=None):
    """Patch (or, with --check, verify) the CMake exports under a prefix."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument(
        '--prefix', default=sys.prefix,
        help="install prefix holding share/<pkg>/cmake (default: this interpreter's "
             'sys.prefix, i.e. the venv)')
    parser.add_argument(
        '--check', action='store_true',
        help="change nothing; exit 1 if any file still names the builder's paths")
    parser.add_argument('-q', '--quiet', action='store_true', help='print only problems')
    args = parser.parse_args(argv)

    files = list(export_files(args.prefix))
    if not files:
        print(f'patch_cmake_exports: no share/*/cmake/*.cmake under {args.prefix}; '
              'are the ros-* wheels installed there?', file=sys.stderr)
        return 1

    if args.check:
        bad = [(f, leftovers(f.read_text(encoding='utf-8'))) for f in files]
        bad = [(f, hits) for f, hits in bad if hits]
        for f, hits in bad:
            print(f'{f}: still names {sorted(set(hits))}', file=sys.stderr)
        if bad:
            print(f'patch_cmake_exports: {len(bad)} file(s) need patching; run without --check',
                  file=sys.stderr)
            return 1
        if not args.quiet:
            print(f'patch_cmake_exports: {len(files)} CMake files checked, none names '
                  '/opt/python')
        return 0

    python_include, numpy_include = target_paths()
    for path in (python_include, numpy_include):
        if not Path(path, 'Python.h' if path == python_include else 'numpy').exists():
            print(f'patch_cmake_exports: warning: {path} has no headers; install the '
                  'Python development headers (python3.11-dev)', file=sys.stderr)
    patched = 0
    for f in files:
        text = f.read_text(encoding='utf-8')
        new_text, count = patch_text(text, python_include, numpy_include)
        if count:
            f.write_text(new_text, encoding='utf-8')
            patched += 1
    if not args.quiet or patched:
        print(f'patch_cmake_exports: {patched} of {len(files)} CMake files patched '
              f'(python include -> {python_include}, numpy include -> {numpy_include})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
