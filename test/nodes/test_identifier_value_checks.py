"""
The live identifier checks each window's sensor values as the bag reader does (the same code).

One identifier node in this process (test/nodes/identifier_harness.py), growing-window fits on,
three test points of the wake plant (4 blades, 0.05° flap noise): the first with one blade-2
flap sample read as +0.2 rad (ten times the flap's travel in the window: a bit flip), the
second with blade 3's flap stuck at exactly 0.0 for the whole test point, the third clean. The
spike is replaced, counted once on /diagnostics however many growing windows saw it, named in
the final's message, and the final is within the truth's Bonferroni bound with residuals the
adequacy check finds white (left in, this spike moves the estimate by only 0.2-0.5 σ here, but
the final is 'inadequate', a WARN without a cause named); the dead sensor's
final is STATUS_FAILED naming blade_3 with no values, never CONVERGED, an ERROR on
/diagnostics that the clean third test point clears.
"""

import math
import os

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
msgs = pytest.importorskip('rotor_id_msgs.msg', reason='rotor_id_msgs not built')

from test_test_points import _stream, LENGTH, OMEGA, WAKE  # noqa: E402

BLADES = [f'blade_{k}' for k in range(1, 5)]
SPIKE_AT = 870                          # sample of test point 1, inside WINDOW (810..937)
SPIKE_RAD = 0.2
#: |value - truth| bound for three parameters at family-wise 0.1 % (as test_identifier_node)
BONFERRONI_SIGMAS = 3.59


@pytest.fixture(scope='module')
def run():
    """Three test points through one identifier node; what it published and reported."""
    from identifier_harness import InProcessIdentifier
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    data = _stream(points=3)
    truth_flap = data['flap'][SPIKE_AT, 1]
    data['flap'][SPIKE_AT, 1] = SPIKE_RAD
    data['flap'][LENGTH:2 * LENGTH, 2] = 0.0
    params = [Parameter('run_description', value='demo_wake.yaml'),
              Parameter('auto_start', value='none'), Parameter('sensor_queue_depth', value=100),
              Parameter('sensor_reliability', value='reliable'),
              Parameter('fit_process', value=False)]
    rig = InProcessIdentifier('test_identifier_value_checks', params, 201 + os.getpid() % 30)
    node = rig.node
    client = rig.test.create_client(Trigger, '/identifier/start_test_point')
    out = {'estimates': rig.estimates, 'truth_flap': truth_flap, 'diagnostics': {}}
    try:
        assert rig.spin_until(lambda: all(p.get_subscription_count() for p in rig.pubs.values())
                              and client.service_is_ready())
        for k in range(3):
            rig.drain()
            future = client.call_async(Trigger.Request())
            assert rig.spin_until(future.done) and future.result().success
            for i in range(k * LENGTH, (k + 1) * LENGTH):
                rig.send(data, i, OMEGA, BLADES)
                if i % 20 == 0:
                    rig.drain()
            assert rig.spin_until(lambda: rig.final_of(k + 1), 60.0), f'no final of {k + 1}'
            if k != 1:              # a fitted final's adequacy: checked after it is published
                rig.spin_until(lambda: node.diagnostics.values.get('adequacy_test_point')
                               == k + 1, 30.0)
            out['diagnostics'][k + 1] = (dict(node.diagnostics.values),
                                         node.diagnostics.problems.get('dead_flap_sensor'))
    finally:
        rig.close()
    return out


def _estimates(run, number, kind=None):
    return [m for m in run['estimates'] if m.test_point == number
            and (kind is None or m.kind == kind)]


def test_a_flap_spike_is_repaired_counted_once_and_named(run):
    from rotor_id_msgs.msg import ParameterEstimate
    finals = _estimates(run, 1, ParameterEstimate.KIND_FINAL)
    assert len(finals) == 1
    final = finals[0]
    assert final.status == ParameterEstimate.STATUS_CONVERGED, final.message
    for name, value, std in zip(final.names, final.values, final.std):
        assert abs(value - WAKE[name]) < BONFERRONI_SIGMAS * std, (name, value, std)
    assert 'value spike' in final.message and 'blade_2 flap: 1, e.g. 0.2 rad' in final.message
    values, dead = run['diagnostics'][1]
    assert dead is None
    # the spike left in, the residuals are not noise: 'inadequate' (measured, 0.05 and 0.2 rad)
    assert values['adequacy'] == 'adequate' and values['adequacy_test_point'] == 1
    # one sample replaced, however many growing windows (published or not) saw it
    assert values['value_spikes_repaired'] == 1
    last = values['value_spike_last']
    assert last.startswith('test point 1: blade_2 flap: 1, e.g. 0.2 rad among '), last
    # the interpolation between its neighbours, near the sample the plant produced
    among = float(last.split(' among ')[1].split(' at ')[0])
    assert abs(among - run['truth_flap']) < 0.003, (among, run['truth_flap'])
    assert float(last.split(' at ')[1].split(' s')[0]) == pytest.approx(SPIKE_AT / 1000, abs=1e-6)


def test_a_dead_flap_sensor_fails_the_final_naming_the_blade(run):
    from diagnostic_msgs.msg import DiagnosticStatus
    from rotor_id_msgs.msg import ParameterEstimate
    finals = _estimates(run, 2, ParameterEstimate.KIND_FINAL)
    assert len(finals) == 1
    final = finals[0]
    assert final.status == ParameterEstimate.STATUS_FAILED, final.message
    assert len(final.values) == 0
    assert 'the flap of blade_3 reads exactly 0 rad' in final.message, final.message
    assert not any(m.status == ParameterEstimate.STATUS_CONVERGED for m in _estimates(run, 2))
    values, dead = run['diagnostics'][2]
    assert dead[0] == DiagnosticStatus.ERROR
    assert dead[1].startswith('test point 2: the flap of blade_3 ')
    assert values['value_spikes_repaired'] == 1          # the stuck channel is no spike


def test_a_clean_test_point_clears_the_dead_sensor_error(run):
    from rotor_id_msgs.msg import ParameterEstimate
    final = _estimates(run, 3, ParameterEstimate.KIND_FINAL)[0]
    assert final.status == ParameterEstimate.STATUS_CONVERGED, final.message
    assert 'value spike' not in final.message
    values, dead = run['diagnostics'][3]
    assert dead is None and values['value_spikes_repaired'] == 1
    assert np.all(np.isfinite(final.values)) and math.isfinite(final.std[0])
