"""
The identifier's ``window_s`` set at run time, as ``ros2 param set`` does it (SetParameters).

What it proves, through a parameter client of another node on DDS: a window that is not
0 <= start < end, longer than ``max_window_s`` or spanning fewer than ``min_window_samples``
at the measured rate is refused with the reason, and the node's window is unchanged; a valid
window set while test point 1 records is accepted, with a note (its log and a /diagnostics
value) saying that it applies from the next test point and that test point 1 keeps its own;
test point 1's final estimate is of its original window, test point 2's of the new one, with
the samples of that window (first and last flap stamps) used; a window (the run description's)
spanning fewer than ``min_window_samples`` is a WARN on /diagnostics while it records.
"""

import math
import os

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
msgs = pytest.importorskip('rotor_id_msgs.msg', reason='rotor_id_msgs not built')

from test_test_points import _stream, LENGTH, OMEGA, RATE, WINDOW  # noqa: E402

BLADES = [f'blade_{k}' for k in range(1, 5)]
NEW_WINDOW = [0.78, 0.95]     # also during the stirring: identifiable


@pytest.fixture(scope='module')
def run():
    """Two test points; window_s set while the first records; return answers and estimates."""
    from identifier_harness import InProcessIdentifier
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    from std_srvs.srv import Trigger

    data = _stream(points=2)
    params = [Parameter('run_description', value='demo_wake.yaml'),
              Parameter('auto_start', value='none'), Parameter('update_every_rad', value=0.0),
              Parameter('sensor_reliability', value='reliable'),
              Parameter('max_window_s', value=10.0),
              # the run description's window (127 samples) is short of it, the new one not
              Parameter('min_window_samples', value=130),
              Parameter('fit_process', value=False)]
    rig = InProcessIdentifier('test_identifier_parameters', params, 171 + os.getpid() % 29)
    node = rig.node
    start = rig.test.create_client(Trigger, '/identifier/start_test_point')
    parameters = AsyncParameterClient(rig.test, 'identifier')
    out = {'estimates': rig.estimates, 'data': data, 'answers': {}}

    def set_window(label, value, name='window_s'):
        future = parameters.set_parameters([Parameter(name, value=value)])
        assert rig.spin_until(future.done, 20.0), f'no answer to setting {name} {value}'
        result = future.result().results[0]
        out['answers'][label] = (result.successful, result.reason,
                                 node.get_parameter(name).value)

    def send(lo, hi):
        for i in range(lo, hi):
            rig.send(data, i, OMEGA, BLADES)
            if i % 20 == 0:
                rig.drain()
        rig.drain()

    def start_test_point():
        rig.drain()
        future = start.call_async(Trigger.Request())
        assert rig.spin_until(future.done), 'no answer from ~/start_test_point'
        return future.result().message

    try:
        assert rig.spin_until(lambda: all(p.get_subscription_count() for p in rig.pubs.values())
                              and start.service_is_ready() and parameters.services_are_ready())
        set_window('reversed', [0.6, 0.5])
        set_window('too long', [0.0, 20.0])
        out['started_1'] = start_test_point()
        send(0, 400)                             # test point 1 records
        out['problems_1'] = dict(node.diagnostics.problems)
        set_window('too few samples', [0.5, 0.52])
        set_window('during test point 1', NEW_WINDOW)
        out['diagnostics'] = dict(node.diagnostics.values)
        send(400, LENGTH)
        assert rig.spin_until(lambda: rig.final_of(1), 60.0), 'no final of test point 1'
        set_window('gap tolerance', 3.0, 'gap_tolerance_periods')
        set_window('gap tolerance below 1', 0.5, 'gap_tolerance_periods')
        set_window('slip tolerance', 0.05, 'azimuth_slip_tolerance_rad')
        out['tolerances'] = (node.points.gap_factor, node.points.slip_tolerance_rad)
        out['started_2'] = start_test_point()
        send(LENGTH, LENGTH + 400)
        out['problems_2'] = dict(node.diagnostics.problems)
        send(LENGTH + 400, 2 * LENGTH)
        assert rig.spin_until(lambda: rig.final_of(2), 60.0), 'no final of test point 2'
    finally:
        rig.close()
    return out


def _final(run, number):
    finals = [m for m in run['estimates'] if m.test_point == number and m.kind == 1]
    assert len(finals) == 1, [(m.test_point, m.kind, m.status) for m in run['estimates']]
    return finals[0]


def _ns(t):
    return t.sec * 1_000_000_000 + t.nanosec


@pytest.mark.parametrize('label, words', [
    ('reversed', '0 <= start < end'),
    ('too long', 'max_window_s 10'),
    ('too few samples', 'spans 20 flap samples at the measured 1000 Hz, fewer than '
                        'min_window_samples 130'),
])
def test_an_invalid_window_is_refused_with_the_reason(run, label, words):
    successful, reason, value = run['answers'][label]
    assert not successful and reason.startswith('window_s: ') and words in reason, reason
    assert list(value) == list(WINDOW)            # unchanged


def test_a_window_set_while_recording_applies_from_the_next_test_point(run):
    successful, reason, value = run['answers']['during test point 1']
    assert successful and list(value) == NEW_WINDOW
    # (rclpy answers a successful set without a reason: the node logs this and reports it)
    assert run['diagnostics']['window_s_change'] == (
        'window_s 0.7800-0.9500 s applies from the next test point armed; test point 1 '
        '(recording) keeps its window 0.8094-0.9367 s')
    assert run['diagnostics']['window_s_next'] == '0.7800-0.9500 s'
    assert '0.7800-0.9500 s' in run['started_2']
    assert '0.8094-0.9367 s' in run['started_1']


def test_each_test_point_is_fitted_over_its_own_window(run):
    from rotor_id_msgs.msg import ParameterEstimate
    stamps = run['data']['stamps']
    for k, window in ((1, WINDOW), (2, NEW_WINDOW)):
        final = _final(run, k)
        assert final.status == ParameterEstimate.STATUS_CONVERGED, final.message
        assert (final.window_requested_start_s, final.window_requested_end_s) == tuple(window)
        origin = (k - 1) * LENGTH
        assert _ns(final.test_point_start) == stamps[origin]
        assert _ns(final.window_start) == stamps[origin + math.ceil(window[0] * RATE - 1e-9)]
        assert _ns(final.window_end) == stamps[origin + math.floor(window[1] * RATE + 1e-9)]


def test_a_window_of_few_samples_is_a_warning_while_it_records(run):
    from diagnostic_msgs.msg import DiagnosticStatus
    level, text = run['problems_1']['window_too_short']
    assert level == DiagnosticStatus.WARN
    assert text.startswith('test point 1 (recording): window_s 0.80939-0.93671 s spans 127 flap '
                           'samples at the measured 1000 Hz, fewer than min_window_samples 130')
    assert 'window_too_short' not in run['problems_2']      # 170 samples: cleared


def test_window_check_tolerances_are_settable_within_their_ranges(run):
    assert run['answers']['gap tolerance'][:1] == (True,)
    assert run['answers']['slip tolerance'][:1] == (True,)
    successful, reason, value = run['answers']['gap tolerance below 1']
    assert not successful and value == 3.0                # refused by its range, unchanged
    assert run['tolerances'] == (3.0, 0.05)               # the next window check uses them
