"""
``rotor-id demo`` interrupted with Ctrl-C leaves nothing running and a readable bag.

The demo's full run is what test_live_system.py checks node by node; here the demo command
itself is started as a user would, interrupted (SIGINT, as a terminal's Ctrl-C) while the nodes
run, and must exit with 130 within seconds, with none of its node processes left and the bag it
had started finalised (read by the bag reader).
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from live_helpers import domain_id, require_workspace


def _processes_on_domain(domain):
    """Return the processes whose environment has ROS_DOMAIN_ID=<domain>."""
    found = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            environ = (entry / 'environ').read_bytes().split(b'\0')
        except OSError:
            continue
        if f'ROS_DOMAIN_ID={domain}'.encode() in environ:
            found.append(int(entry.name))
    return found


def test_ctrl_c_stops_every_node(tmp_path):
    require_workspace()
    domain = domain_id()
    out = tmp_path / 'demo'
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    demo = subprocess.Popen([sys.executable, '-m', 'rotor_id.cli', 'demo', '--out', str(out),
                             '--domain-id', str(domain)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines = []
    try:
        for line in demo.stdout:            # until the rotor runs (stirring is shown)
            lines.append(line)
            if 'stirring started' in line:
                break
        assert 'stirring started' in ''.join(lines), ''.join(lines)
        interrupted = time.monotonic()
        demo.send_signal(signal.SIGINT)
        output, _ = demo.communicate(timeout=60)
        took = time.monotonic() - interrupted
    finally:
        if demo.poll() is None:
            demo.kill()
    output = ''.join(lines) + output
    logs = '\n'.join(f'--- {p.name}\n{p.read_text()[-1500:]}'
                     for p in sorted((out / 'logs').glob('*.log')))
    report = f'exit {demo.returncode} after {took:.1f} s\n{output}\n{logs}'
    assert demo.returncode == 130, report
    assert 'interrupted' in output and 'Traceback' not in output, report
    assert took < 45, report
    left = _processes_on_domain(domain)
    assert not left, f'node processes left running: {left}\n{report}'
    from rotor_id.io.bag import read_record
    record = read_record(next(p for p in out.glob('bag_*') if p.is_dir()))
    assert len(record) > 100          # stirring starts 0.81 s (810 samples) after the first
