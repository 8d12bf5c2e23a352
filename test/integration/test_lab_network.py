"""
Lab network: plant and identifier on two "hosts" discover each other over DDS (pins #7).

Two network namespaces joined by a veth pair, an address on each end and a multicast route
224.0.0.0/4 on each side (discovery is multicast), made and deleted by this test. The plant
and the stirring input run in one namespace, the identifier and a listener in the other, with
default (subnet) discovery and UDP only (no shared-memory transport): nothing but the veth link
connects them. The listener must receive a final estimate within 3σ of the truth. Skipped, with
the reason, where namespaces cannot be made.
"""

import json
import os
import shutil
import subprocess
import sys

from live_helpers import require_workspace, within_sigma
import pytest

TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}
LISTENER = r"""
import json
import sys

import rclpy
from rotor_id.nodes.common import SENSOR_QOS
from rotor_id.nodes.watch import RunWatcher
from sensor_msgs.msg import JointState

rclpy.init()
node = rclpy.create_node('lab_listener')
watcher = RunWatcher(node)
# only then subscribe to the azimuth (the plant starts at 3 subscribers): the estimates must
# not be published before this listener has matched the identifier
watcher.spin_until(lambda: node.count_publishers('/rotor_id/estimate') > 0, 60.0)
watcher.spin_until(lambda: False, 1.0)
# the stirring input (on the rig) holds trim until asked: the test point starts with the rotor
watcher.trigger('/stirring_input/start', 60.0)
node.create_subscription(JointState, '/rotor/azimuth', lambda _: None, SENSOR_QOS)
ok = watcher.spin_until(lambda: watcher.final_estimate() is not None, float(sys.argv[1]))
final = watcher.final_estimate()
print(json.dumps(None if final is None else {
    'names': list(final.names), 'values': list(final.values), 'std': list(final.std),
    'status': int(final.status), 'message': final.message}), flush=True)
print(f'listener saw {len(watcher.messages["estimate"])} estimates, '
      f'{len(watcher.messages["diagnostics"])} diagnostics', file=sys.stderr, flush=True)
"""


def _ip(*args, check=True):
    return subprocess.run(['ip', *args], capture_output=True, text=True, check=check)


@pytest.fixture
def two_hosts():
    """(namespace of the rig, namespace of the identification host); deleted afterwards."""
    if shutil.which('ip') is None:
        pytest.skip('the ip command (iproute2) is not installed')
    if os.geteuid() != 0:
        pytest.skip('network namespaces need root (CAP_SYS_ADMIN)')
    tag = os.getpid() % 10000
    rig, lab = f'rid_rig_{tag}', f'rid_lab_{tag}'
    veth_rig, veth_lab = f'rid{tag}a', f'rid{tag}b'
    subnet = f'10.{200 + tag % 50}.{tag % 250}'
    made = []
    try:
        for ns in (rig, lab):
            result = _ip('netns', 'add', ns, check=False)
            if result.returncode != 0:
                pytest.skip(f'cannot create a network namespace: {result.stderr.strip()}')
            made.append(ns)
        _ip('link', 'add', veth_rig, 'netns', rig, 'type', 'veth', 'peer', 'name', veth_lab,
            'netns', lab)
        for ns, dev, host in ((rig, veth_rig, 1), (lab, veth_lab, 2)):
            _ip('-n', ns, 'addr', 'add', f'{subnet}.{host}/24', 'dev', dev)
            _ip('-n', ns, 'link', 'set', dev, 'up', 'multicast', 'on')
            _ip('-n', ns, 'link', 'set', 'lo', 'up')
            _ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)
        yield rig, lab
    except subprocess.CalledProcessError as exc:
        pytest.skip(f'cannot set up the veth link: {exc.stderr.strip()}')
    finally:
        for ns in made:
            _ip('netns', 'delete', ns, check=False)


def test_plant_and_identifier_on_two_hosts(two_hosts, tmp_path):
    require_workspace()
    from rotor_id.commands.demo import case_files
    from rotor_id.nodes.processes import NodeProcesses
    rig, lab = two_hosts
    params_file, description_path, _ = case_files('wake')
    env = dict(os.environ, ROS_DOMAIN_ID='42', ROS_LOG_DIR=str(tmp_path / 'ros_log'),
               PYTHONUNBUFFERED='1')
    env.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)         # default: the subnet (the veth)
    env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'    # no shared memory: data must cross the link
    rig_procs = NodeProcesses(env, tmp_path / 'rig', prefix=['ip', 'netns', 'exec', rig])
    lab_procs = NodeProcesses(env, tmp_path / 'lab', prefix=['ip', 'netns', 'exec', lab])
    listener = None
    try:
        lab_procs.start('identifier', params_file)
        listener = subprocess.Popen(['ip', 'netns', 'exec', lab, sys.executable, '-c', LISTENER,
                                     '150'], env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
        rig_procs.start('stirring_input', params_file)
        # azimuth subscribers: stirring input (rig), identifier and listener (lab)
        rig_procs.start('rotor_plant', params_file, {'duration_s': 0.99,
                                                     'wait_for_subscribers': 3})
        out, err = listener.communicate(timeout=200)
    finally:
        if listener is not None and listener.poll() is None:
            listener.kill()
        codes = {**rig_procs.stop_all(last=()), **lab_procs.stop_all(last=())}
        exits = rig_procs.exit_summary() + '\n' + lab_procs.exit_summary()
    final = json.loads(out.strip().splitlines()[-1]) if out.strip() else None
    assert final is not None, (f'no estimate crossed the veth link\nlistener (exit '
                               f'{listener.returncode}): {out[-500:]} {err[-2000:]}\n'
                               f'identifier: {lab_procs.log("identifier")[-2000:]}\n'
                               f'plant: {rig_procs.log("rotor_plant")[-2000:]}')
    assert final['status'] == 1, final['message']
    ok, text = within_sigma(final['values'], final['std'], TRUTH, final['names'])
    assert ok, text
    assert set(codes.values()) == {0}, exits
