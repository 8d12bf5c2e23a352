"""
`rotor-id` ends its process without the interpreter's teardown, and loses nothing by it.

:func:`rotor_id.cli.exit_with`: the exit code is the command's, what was printed (buffered,
to a pipe) arrives, the at-exit functions run; with another thread alive the exit waits for
it, as an ordinary exit does. Ctrl-C in the middle of a diagnosis (the terminal interrupts
the command and its worker processes alike) ends it at once with exit code 130 and no
process left behind: before, the command waited forever for the jobs its interrupted
workers had been running.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from practice import require_practice

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


def test_ctrl_c_during_a_diagnosis_ends_it_and_its_workers():
    recordings = require_practice()
    name = str(recordings / 'dx_sensor_lag')
    # Ctrl-C's disposition as in a terminal (make test runs this lane as a background job,
    # which ignores SIGINT, and a child inherits that)
    command = subprocess.Popen([str(REPO / 'rotor-id'), 'diagnose', name, '--config',
                                name + '.yaml'], stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True, start_new_session=True,
                               preexec_fn=_default_interrupt)
    try:
        for line in command.stderr:             # the first step's fits under way in the workers
            if line.startswith('    fitting '):
                break
        os.killpg(command.pid, signal.SIGINT)   # as Ctrl-C: the command and its workers
        interrupted = time.monotonic()
        rest = command.communicate(timeout=60)[1]
        assert time.monotonic() - interrupted < 10.0
    finally:
        if command.poll() is None:
            os.killpg(command.pid, signal.SIGKILL)
    assert command.returncode == 130, rest
    assert rest.strip().splitlines()[-1] == 'rotor-id diagnose: interrupted'
    time.sleep(0.5)
    left = subprocess.run(['pgrep', '-g', str(command.pid)], capture_output=True, text=True)
    assert not left.stdout.split(), 'processes of the command left behind'


def _default_interrupt():
    signal.signal(signal.SIGINT, signal.SIG_DFL)
