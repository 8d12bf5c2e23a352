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
(re)installs ros-* message wheels (tools/make_venv.sh runs it after every install).

Usage::

    .venv/bin/python tools/patch_cmake_exports.py            # patch, print a summary
    .venv/bin/python tools/patch_cmake_exports.py --check    # exit 1 if anything is left
"""

import argparse
import os
from pathlib import Path
import re
import sys
import sysconfig

# Any absolute Python or numpy include directory named in an export: the wheel builder's
# (/opt/python/cp3XX-cp3XX/...), or another venv's when a package cache handed us files that
# were patched for it (uv hard-links installed files to its cache). Absolute paths only: the
# ${_IMPORT_PREFIX}-relative entries of the exports are left alone.
NUMPY_INCLUDE_RE = re.compile(
    r'/[^;"\s$]*/lib/python3\.\d+/site-packages/numpy/(?:_core|core)/include')
PYTHON_INCLUDE_RE = re.compile(r'/[^;"\s$]*/include/python3\.\d+')


def target_paths():
    """Return (python_include, numpy_include) of the running interpreter."""
    import numpy  # imported here so that --help works without numpy
    return sysconfig.get_paths()['include'], numpy.get_include()


def export_files(prefix):
    """Yield the CMake files of all packages installed under ``prefix``."""
    yield from sorted(Path(prefix).glob('share/*/cmake/*.cmake'))


def patch_text(text, python_include, numpy_include):
    """Return ``text`` with foreign include paths replaced, and the count replaced."""
    numpy_include = numpy_include.replace('\\', '/')
    python_include = python_include.replace('\\', '/')
    count = 0

    def swap(target):
        def replace(match):
            nonlocal count
            if match.group(0) != target:
                count += 1
            return target
        return replace

    text = NUMPY_INCLUDE_RE.sub(swap(numpy_include), text)
    text = PYTHON_INCLUDE_RE.sub(swap(python_include), text)
    return text, count


def leftovers(text, python_include=None, numpy_include=None):
    """Return the include paths in ``text`` that are not this interpreter's."""
    if python_include is None:
        python_include, numpy_include = target_paths()
    return ([m for m in NUMPY_INCLUDE_RE.findall(text) if m != numpy_include]
            + [m for m in PYTHON_INCLUDE_RE.findall(text) if m != python_include])


def write_replacing(path, text):
    """
    Write ``text`` to a new file renamed over ``path``.

    Never in place: the installed file may be a hard link into a package cache (uv), and
    writing through it would change every other environment made from that cache.
    """
    tmp = path.with_name(path.name + '.patch-tmp')
    tmp.write_text(text, encoding='utf-8')
    os.replace(tmp, path)


def main(argv=None):
    """Patch (or, with --check, verify) the CMake exports under a prefix."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument(
        '--prefix', default=sys.prefix,
        help="install prefix holding share/<pkg>/cmake (default: this interpreter's "
             'sys.prefix, i.e. the venv)')
    parser.add_argument(
        '--check', action='store_true',
        help='change nothing; exit 1 if any file names a foreign include path')
    parser.add_argument('-q', '--quiet', action='store_true', help='print only problems')
    args = parser.parse_args(argv)

    files = list(export_files(args.prefix))
    if not files:
        print(f'patch_cmake_exports: no share/*/cmake/*.cmake under {args.prefix}; '
              'are the ros-* wheels installed there?', file=sys.stderr)
        return 1

    if args.check:
        python_include, numpy_include = target_paths()
        bad = [(f, leftovers(f.read_text(encoding='utf-8'), python_include, numpy_include))
               for f in files]
        bad = [(f, hits) for f, hits in bad if hits]
        for f, hits in bad:
            print(f'{f}: still names {sorted(set(hits))}', file=sys.stderr)
        if bad:
            print(f'patch_cmake_exports: {len(bad)} file(s) need patching; run without --check',
                  file=sys.stderr)
            return 1
        if not args.quiet:
            print(f'patch_cmake_exports: {len(files)} CMake files checked, all include paths '
                  "are this interpreter's")
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
            write_replacing(f, new_text)
            patched += 1
    if not args.quiet or patched:
        print(f'patch_cmake_exports: {patched} of {len(files)} CMake files patched '
              f'(python include -> {python_include}, numpy include -> {numpy_include})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
