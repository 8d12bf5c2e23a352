"""
An identifier that takes a whole test point in one burst still publishes a growing window first.

What it proves, through DDS in this process: when every sample of a test point's window arrives
before the identifier's next poll (a node starved of CPU catching up), the samples cross the
growing-window points and the window's end in one batch; the identifier then asks for the first
growing window itself, so a provisional estimate (KIND_PROVISIONAL, STATUS_ITERATING) of that
test point is published before its final one, which converges from the complete window.
"""

import math
import os
import time

import pytest
from ros_domains import next_domain

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
msgs = pytest.importorskip('rotor_id_msgs.msg', reason='rotor_id_msgs not built')

from test_test_points import _stream, LENGTH, OMEGA, WINDOW  # noqa: E402

BLADES = [f'blade_{k}' for k in range(1, 5)]


#: Seconds the burst is left to be delivered and queued before the one poll takes it; a
#: delivery that was still under way (a loaded machine) is retried with a longer wait.
QUEUE_WAITS_S = (0.5, 2.0, 8.0)


def test_a_burst_of_a_whole_window_still_gets_a_growing_window_first():
    from rotor_id_msgs.msg import ParameterEstimate

    for wait_s in QUEUE_WAITS_S:
        taken, estimates, min_window_rad = _burst(wait_s)
        if taken == 3 * LENGTH:
            break
    assert taken == 3 * LENGTH, \
        f'only {taken} of {3 * LENGTH} samples were queued even {wait_s} s after the burst'
    kinds = [(m.test_point, m.kind, m.status) for m in estimates]
    assert kinds[:2] == [(1, ParameterEstimate.KIND_PROVISIONAL,
                          ParameterEstimate.STATUS_ITERATING),
                         (1, ParameterEstimate.KIND_FINAL,
                          ParameterEstimate.STATUS_CONVERGED)], kinds
    provisional, final = estimates[:2]
    first = WINDOW[0] + min_window_rad / OMEGA
    assert provisional.window_requested_end_s == pytest.approx(first)
    assert final.window_requested_end_s == WINDOW[1]
    assert math.isfinite(final.values[0])


def _burst(wait_s):
    """Publish a whole test point at once, poll once after ``wait_s``; return what came of it."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.nodes.common import joint_state, RESULT_QOS, SENSOR_OFFER_QOS
    from rotor_id.nodes.identifier import Identifier
    from rotor_id_msgs.msg import ParameterEstimate
    from sensor_msgs.msg import JointState

    data = _stream(points=1)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=next_domain(),
               signal_handler_options=SignalHandlerOptions.NO)
    node = Identifier(context=context, parameter_overrides=[
        Parameter('run_description', value='demo_wake.yaml'),
        Parameter('auto_start', value='data'), Parameter('sensor_reliability', value='reliable'),
        Parameter('fit_process', value=False)])
    node.poller.stop()                    # taken here, in one poll: the node was starved
    test = rclpy.create_node('burst_test', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(test)
    estimates = []
    test.create_subscription(ParameterEstimate, '/rotor_id/estimate', estimates.append,
                             RESULT_QOS)
    pubs = {topic: test.create_publisher(JointState, f'/rotor/{topic}', SENSOR_OFFER_QOS)
            for topic in ('blade_flap', 'blade_pitch', 'azimuth')}
    taken = 0
    try:
        deadline = time.monotonic() + 30 + wait_s
        while (not all(p.get_subscription_count() for p in pubs.values())
               and time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.05)
        for i in range(LENGTH):
            stamp = int(data['stamps'][i])
            pubs['blade_flap'].publish(joint_state(stamp, BLADES, data['flap'][i]))
            pubs['blade_pitch'].publish(joint_state(stamp, BLADES, data['pitch'][i]))
            pubs['azimuth'].publish(joint_state(stamp, ['rotor'], [data['psi'][i]], [OMEGA]))
        time.sleep(wait_s)                 # all delivered and queued, then one poll takes them
        taken = node.poller.poll()
        while (taken == 3 * LENGTH
               and not any(m.kind == ParameterEstimate.KIND_FINAL for m in estimates)
               and time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.05)
        min_window_rad = node.d['min_window_rad']
    finally:
        node.close()
        executor.shutdown()
        node.destroy_node()
        test.destroy_node()
        rclpy.try_shutdown(context=context)
    return taken, estimates, min_window_rad
