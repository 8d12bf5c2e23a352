"""
The five nodes started on rigs unlike the built-in plant, and the offline command on their bags.

Each rig is a run description a lab might write and the nodes have never been tuned to: 3 blades
with an unwrapped azimuth sampled at 2 kHz, or 5 blades at 500 Hz; joint names with spaces,
dashes, dots, slashes, '#', ':' and non-ASCII letters; the hub joint not named ``rotor``; every
topic in a sub-namespace of its own (sensors, encoder, commands, results) and the whole rig in a
namespace (one or two levels). The nodes are started as ``ros2 run`` would, with the demo's
parameter file and only ``run_description`` (and the plant's rate) changed. What it proves:
every node exits with 0 and no traceback; the identifier publishes one final estimate of test
point 1 on the rig's own result topic, converged exactly when its window is complete and then
within 3σ of the simulated rotor's truth (required unless the run had no core to spare:
the machine's CPU 90 % busy over it, or 1-minute load above 4 per core); the state
estimator publishes on the rig's state topic; ``rotor-id identify BAG --config RIG --test-point 1``
on the recorded bag starts the test point at the same flap sample and agrees with the live
estimate to 0.2σ (the 5-blade, 2 kHz, unwrapped rig's bag was refused as "two streams merged"
before the fix of rotor_id/io/streams.py). A run the machine starved so that the stirring node
stopped on a stale azimuth (test point 1 aborted) is run once more; no claim is dropped.
"""

import json
import os
import subprocess
import time

from live_helpers import (CpuUse, domain_id, REPO_ROOT, require_workspace, RosClient, starved,
                          within_sigma)
import pytest
import yaml

pytestmark = pytest.mark.slow
TRUTH = {'A': 0.5, 'AL_over_tau': 0.25, 'inv_tau': 0.125}     # nodes_wake.yaml's plant
RIGS = {
    # name: (blades, azimuth convention, namespace, sample rate)
    'three_blades_unwrapped_2khz': (3, 'unwrapped', '/stand7', 2000.0),
    'five_blades_500hz': (5, 'wrapped', '/lab/bay_2', 500.0),
}


def rig_description(blades, convention):
    """Return the run description (a dict) of an odd rig."""
    return {
        'rotor': {'blades': blades, 'advance_ratio': 0.0, 'flap_frequency': 1.2,
                  'tip_loss': 0.97},
        'topics': {'blade_pitch': 'stand/sensors/pitch', 'blade_flap': 'stand/sensors/flap',
                   'azimuth': 'stand/encoder/azimuth', 'pitch_command': 'stand/cmd/pitch',
                   'stirring': 'stand/cmd/stirring', 'estimate': 'results/estimate',
                   'progress': 'results/progress', 'state': 'results/state'},
        'joint_names': {'azimuth': 'hub shaft#0',
                        'blade_flap': [f'rotor {k}/flap-β' for k in range(1, blades + 1)],
                        'blade_pitch': [f'pitch.{k}:θ' for k in range(1, blades + 1)]},
        'azimuth_convention': convention,
        'model': 'multiblade_wake', 'unknowns': ['A', 'AL_over_tau', 'inv_tau'],
        'window_s': [0.80939, 0.93671],
        'initial_guess': {'A': 0.4, 'AL_over_tau': 0.2, 'inv_tau': 0.25},
    }


@pytest.fixture(scope='module', params=sorted(RIGS))
def rig(request, tmp_path_factory):
    """Start the five nodes on one odd rig until test point 1's final estimate; return all."""
    require_workspace()
    blades, convention, namespace, rate = RIGS[request.param]
    # A starved run: on a loaded CI machine the simulated plant (which waits for the pitch
    # commands) can fall 0.25 s behind the clock; the stirring node then stops on a stale
    # azimuth and the identifier aborts test point 1, the nodes' honest answer, but no test of
    # the rig. One more run in a fresh domain then, every claim below unchanged.
    for attempt in (1, 2):
        out = _run_rig(request.param, tmp_path_factory.mktemp(request.param), blades,
                       convention, namespace, rate)
        out['attempts'] = attempt
        if not _aborted(out['estimates']):
            break
    return out


def _aborted(estimates):
    from rotor_id_msgs.msg import ParameterEstimate
    return any(m.kind == ParameterEstimate.KIND_FINAL
               and m.status == ParameterEstimate.STATUS_ABORTED for m in estimates)


def _run_rig(name, work, blades, convention, namespace, rate):
    """Start the five nodes on one odd rig until test point 1's final estimate; return all."""
    import rclpy
    from rotor_id.commands.demo import case_files
    from rotor_id.nodes.common import RESULT_QOS, STATE_QOS
    from rotor_id.nodes.processes import isolated_env, NodeProcesses
    from rotor_id.nodes.watch import call_trigger
    from rotor_id_msgs.msg import ParameterEstimate, StateEstimate

    config = work / 'rig.yaml'
    config.write_text(yaml.safe_dump(rig_description(blades, convention), allow_unicode=True),
                      encoding='utf-8')
    params_file = case_files('wake')[0]
    domain = domain_id()
    ros = RosClient(domain)
    out = {'config': config, 'bag': work / 'bag', 'estimates': [], 'states': [],
           'load': os.getloadavg()[0], 'name': name}
    cpu = CpuUse()
    ros.node.create_subscription(ParameterEstimate, f'{namespace}/results/estimate',
                                 out['estimates'].append, RESULT_QOS)
    # volatile, as the state estimator offers them: the states after discovery
    ros.node.create_subscription(StateEstimate, f'{namespace}/results/state',
                                 out['states'].append, STATE_QOS)
    procs = NodeProcesses(isolated_env(domain, work / 'ros_log'), work / 'logs')
    given = {'run_description': str(config)}
    try:
        procs.start('identifier', params_file, given, namespace=namespace)
        procs.start('state_estimator', params_file, given, namespace=namespace)
        procs.start('recorder', params_file, {**given, 'output': str(out['bag'])},
                    namespace=namespace)
        procs.start('stirring_input', params_file, given, namespace=namespace)
        started = call_trigger(ros.node, f'{namespace}/stirring_input/start', 60.0,
                               alive=lambda: not procs.dead())
        assert started is not None and started.success, (started, procs.dead())
        procs.start('rotor_plant', params_file, {**given, 'sample_rate_hz': rate,
                                                 'duration_s': 60.0}, namespace=namespace)
        deadline = time.monotonic() + 150.0
        while (time.monotonic() < deadline and not procs.dead()
               and not any(m.kind == ParameterEstimate.KIND_FINAL for m in out['estimates'])):
            rclpy.spin_once(ros.node, timeout_sec=0.1)
        settle = time.monotonic() + 2.0          # a few state estimates after the final one
        while time.monotonic() < settle:
            rclpy.spin_once(ros.node, timeout_sec=0.1)
        out['load'] = max(out['load'], os.getloadavg()[0])
        out['busy'] = cpu.busy_share()
    finally:
        out['codes'] = procs.stop_all()
        out['exits'] = procs.exit_summary()
        out['logs'] = {name: procs.log(name) for name in procs.procs}
        ros.close()
    return out


def test_nodes_run_and_exit_cleanly(rig):
    assert rig['codes'] == dict.fromkeys(rig['codes'], 0), rig['exits']
    for name, log in rig['logs'].items():
        assert 'Traceback' not in log and 'configuration error' not in log, f'{name}:\n{log}'
    assert rig['states'], "no state estimate on the rig's state topic"


def test_the_live_estimate_is_right_or_says_it_is_incomplete(rig):
    from rotor_id_msgs.msg import ParameterEstimate
    finals = [m for m in rig['estimates'] if m.kind == ParameterEstimate.KIND_FINAL]
    assert [m.test_point for m in finals] == [1], rig['logs']['identifier'][-3000:]
    final = finals[0]
    complete = final.time_base_consistent and not list(final.missing_channels)
    assert (final.status == ParameterEstimate.STATUS_CONVERGED) == complete, final.message
    if complete:
        ok, text = within_sigma(final.values, final.std, TRUTH, final.names)
        assert ok, f'{rig["name"]}: {text}'
    else:
        # samples lost, or the plant fell behind the clock so that the excitation ended before
        # the window (aborted): both said plainly, and only where the machine had no CPU to
        # spare for the nodes (measured over the run, not guessed from the load)
        assert final.status in (ParameterEstimate.STATUS_INCOMPLETE,
                                ParameterEstimate.STATUS_ABORTED), final.message
        assert starved(rig['load'], rig['busy']), (
            f'incomplete at load {rig["load"]:.1f}, CPU {100 * rig["busy"]:.0f} % busy: '
            f'{final.message}')


def test_offline_identification_of_the_bag_agrees(rig, tmp_path):
    from rotor_id_msgs.msg import ParameterEstimate
    final = next(m for m in rig['estimates'] if m.kind == ParameterEstimate.KIND_FINAL)
    out = tmp_path / 'offline.json'
    done = subprocess.run([str(REPO_ROOT / 'rotor-id'), 'identify', str(rig['bag']), '--config',
                           str(rig['config']), '--test-point', '1', '--json', str(out),
                           '--quiet'], capture_output=True, text=True, timeout=300)
    if final.status == ParameterEstimate.STATUS_ABORTED:
        # a test point the live identifier aborted is refused offline too, in one error line
        # naming why, before any fit
        last = done.stderr.strip().splitlines()[-1:] or ['']
        assert done.returncode == 2 and 'Traceback' not in done.stderr, done.stderr[-2000:]
        assert last[0].startswith('rotor-id identify: error: ') and 'aborted' in last[0], last
        return
    assert done.returncode == 0, done.stderr[-2000:]
    offline = json.loads(out.read_text())
    start = final.test_point_start.sec * 1_000_000_000 + final.test_point_start.nanosec
    if list(final.missing_channels) or not final.time_base_consistent:
        assert offline['test_point_start_ns'] <= start
        return
    assert offline['test_point_start_ns'] == start
    for name, value, std in zip(final.names, final.values, final.std):
        difference = offline['parameters'][name]['value'] - value
        assert abs(difference) < 0.2 * std, (name, value, std, offline['parameters'])
