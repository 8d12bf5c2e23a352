"""
`rotor-id` ends its process without the interpreter's teardown, and loses nothing by it.

:func:`rotor_id.cli.exit_with`: the exit code is the command's, what was printed (buffered,
to a pipe) arrives, the at-exit functions run; with another thread alive the exit waits for
it, as an ordinary exit does.
"""

import os
from pathlib import Path
import subprocess
import sys

REPO = Path(__file__).resolve().parents[2]


def _child(code):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          env=env, timeout=60)


def test_exit_keeps_the_code_the_output_and_the_exit_functions():
    out = _child('import atexit, sys\n'
                 'from rotor_id.cli import exit_with\n'
                 'atexit.register(print, "at exit")\n'
                 'print("printed", end="")\n'
                 'sys.stderr.write("said")\n'
                 'exit_with(3)\n'
                 'print("never")\n')
    assert out.returncode == 3
    assert out.stdout == 'printedat exit\n'
    assert out.stderr == 'said'


def test_exit_waits_for_a_live_thread():
    out = _child('import threading, time\n'
                 'from rotor_id.cli import exit_with\n'
                 'def late():\n'
                 '    time.sleep(0.3)\n'
                 '    print("thread done", flush=True)\n'
                 'threading.Thread(target=late).start()\n'
                 'exit_with(4)\n')
    assert out.returncode == 4
    assert out.stdout == 'thread done\n'


def test_the_command_line_exits_with_its_code():
    out = subprocess.run([str(REPO / 'rotor-id'), 'diagnose', '/nonexistent/bag', '--config',
                          '/nonexistent.yaml'], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert out.stderr.count('\n') == 1 and 'error' in out.stderr
