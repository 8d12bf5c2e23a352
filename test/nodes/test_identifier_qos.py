"""
The identifier as shipped receives from a rig whose drivers publish best effort (REP-2003).

What it proves, through DDS in this process: the identifier with the identifier section of
config/nodes_wake.yaml subscribes to the sensors best effort, so a driver that publishes with
the sensor-data QoS (best effort, volatile, keep last) is matched and its samples arrive; one
test point sent that way is identified within 3σ of the truth from its complete window; the
estimate is stamped with the data time (the window's end) and its ``computed_at`` is the node's
clock, later.
"""

import math
import os
import time

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
msgs = pytest.importorskip('rotor_id_msgs.msg', reason='rotor_id_msgs not built')

from test_test_points import _stream, LENGTH, OMEGA, WAKE, WINDOW  # noqa: E402

BLADES = [f'blade_{k}' for k in range(1, 5)]
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def shipped_identifier_parameters():
    """Return the rclpy Parameters of config/nodes_wake.yaml's identifier section."""
    from rclpy.parameter import Parameter
    import yaml
    with open(os.path.join(REPO, 'config', 'nodes_wake.yaml'), encoding='utf-8') as handle:
        section = yaml.safe_load(handle)['/**/identifier']['ros__parameters']
    return [Parameter(name, value=value) for name, value in section.items()]


def _ns(t):
    return t.sec * 1_000_000_000 + t.nanosec


def test_a_best_effort_driver_delivers_to_the_shipped_identifier():
    from identifier_harness import InProcessIdentifier
    from rclpy.parameter import Parameter
    from rclpy.qos import ReliabilityPolicy
    from rotor_id.nodes.common import SENSOR_QOS
    from std_srvs.srv import Trigger

    assert SENSOR_QOS.reliability == ReliabilityPolicy.BEST_EFFORT
    data = _stream(points=1)
    params = shipped_identifier_parameters() + [
        Parameter('update_every_rad', value=0.0),       # the final estimate only
        Parameter('fit_process', value=False)]          # no child process to start here
    rig = InProcessIdentifier('test_identifier_qos', params, 171 + os.getpid() % 20,
                              sensor_qos=SENSOR_QOS)
    started = time.time_ns()
    try:
        assert rig.node.sensor_qos.reliability == ReliabilityPolicy.BEST_EFFORT
        start = rig.test.create_client(Trigger, '/identifier/start_test_point')
        # matched: a reliable subscription would never count a best-effort publisher
        assert rig.spin_until(lambda: all(p.get_subscription_count() for p in rig.pubs.values())
                              and start.service_is_ready()), 'best-effort publishers unmatched'
        future = start.call_async(Trigger.Request())
        assert rig.spin_until(future.done) and future.result().success
        for i in range(LENGTH):
            rig.send(data, i, OMEGA, BLADES)
            if i % 20 == 0:
                rig.drain()
        assert rig.spin_until(lambda: rig.final_of(1), 60.0), 'no final estimate'
        taken = rig.node.taken
    finally:
        rig.close()
    final = next(m for m in rig.estimates if m.kind == msgs.ParameterEstimate.KIND_FINAL)
    assert taken > 0
    assert final.status == msgs.ParameterEstimate.STATUS_CONVERGED, final.message
    assert list(final.missing_channels) == []
    for name, value, std in zip(final.names, final.values, final.std):
        assert abs(value - WAKE[name]) < 3 * std, (name, value, std)
    # data time: the window's last flap sample; computed_at: the node's clock, later
    last = math.floor(WINDOW[1] * 1000)
    assert _ns(final.header.stamp) == _ns(final.window_end) == data['stamps'][last]
    assert started <= _ns(final.computed_at) <= time.time_ns()
    assert _ns(final.computed_at) > _ns(final.header.stamp)
