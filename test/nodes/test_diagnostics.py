"""
The one diagnostics helper of every node: staleness, rate, levels, names, run-time settings.

A node that never receives data is never OK (WARN after ``stale_warn_s``, ERROR after
``stale_error_s``); an input that stops is WARN, then ERROR; an idle node's quiet inputs are
STALE; an input slower than ``min_rate_hz`` is WARN; rejected messages are WARN for one period;
the name and hardware_id carry the node's namespace; the thresholds are settable at run time and
an ERROR threshold below the WARN one is refused with the reason.
"""


import pytest
from ros_domains import next_domain

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
pytest.importorskip('diagnostic_msgs.msg', reason='diagnostic_msgs not importable')

S = 1_000_000_000


@pytest.fixture()
def diag():
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.nodes.common import Diagnostics
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=next_domain(),
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('probe', namespace='/rig4', context=context, parameter_overrides=[
        Parameter('stale_warn_s', value=2.0), Parameter('stale_error_s', value=10.0),
        Parameter('min_rate_hz', value=50.0)])
    diagnostics = Diagnostics(node, 'probing')
    diagnostics.watch('flap', 'rotor/blade_flap')
    yield diagnostics
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def levels(diagnostics, at_ns):
    findings, values = diagnostics.stream_findings(at_ns)
    return [level for level, _ in findings], [text for _, text in findings], values


def test_no_data_at_all_is_never_ok(diag):
    from diagnostic_msgs.msg import DiagnosticStatus as D
    t0 = diag.started_ns
    assert levels(diag, t0 + 1 * S)[0] == []
    found, texts, _ = levels(diag, t0 + 3 * S)
    assert found == [D.WARN] and 'no data on rotor/blade_flap since the start' in texts[0]
    found, texts, _ = levels(diag, t0 + 11 * S)
    assert found == [D.ERROR] and 'namespace' in texts[0]
    diag.idle = True                      # idle, but it never had data: still an ERROR
    assert levels(diag, t0 + 11 * S)[0] == [D.ERROR]


def test_an_input_that_stops_is_warn_then_error_or_stale_when_idle(diag, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticStatus as D
    now = [diag.started_ns]
    monkeypatch.setattr(diag, '_now', lambda: now[0])
    for _ in range(200):                  # 200 Hz for 1 s
        now[0] += S // 200
        diag.received('flap')
    last = now[0]
    assert levels(diag, last + S)[0] == []
    assert levels(diag, last + 3 * S)[0] == [D.WARN]
    found, texts, values = levels(diag, last + 11 * S)
    assert found == [D.ERROR] and 'for 11.0 s' in texts[0]
    assert values['flap_messages'] == 200
    diag.idle = True
    assert levels(diag, last + 11 * S)[0] == [D.STALE]


def test_a_slow_input_is_warn(diag, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticStatus as D
    now = [diag.started_ns]
    monkeypatch.setattr(diag, '_now', lambda: now[0])
    diag.publisher.publish = lambda _msg: None
    diag.received('flap')
    now[0] += 1
    diag.publish()                        # a period starts: the rate counts from here
    for _ in range(20):                   # 20 Hz over the next second
        now[0] += S // 20
        diag.received('flap')
    found, texts, values = levels(diag, now[0])
    assert found == [D.WARN] and 'below min_rate_hz 50' in texts[0]
    assert float(values['flap_rate_hz']) == pytest.approx(20.0, rel=0.01)


def test_published_status_levels_names_and_rejections(diag):
    from diagnostic_msgs.msg import DiagnosticStatus as D
    published = []
    diag.publisher.publish = published.append
    diag.settings['min_rate_hz'] = 0.0    # one message per period is enough here
    diag.received('flap')
    diag.publish()
    status = published[-1].status[0]
    assert (status.level, status.message) == (D.OK, 'ok')
    assert status.name == 'rig4/probe: probing' and status.hardware_id == '/rig4/probe'
    diag.count('degrees', 'angle 45 rad')
    diag.publish()
    status = published[-1].status[0]
    assert status.level == D.WARN and 'degrees: angle 45 rad' in status.message
    diag.publish()                        # the next period: nothing new rejected
    assert published[-1].status[0].level == D.OK
    diag.problem('fit', D.ERROR, 'the fit process died')
    diag.publish()
    assert published[-1].status[0].level == D.ERROR
    assert published[-1].status[0].message == 'the fit process died'


def test_thresholds_settable_at_run_time_with_validation(diag):
    from rclpy.parameter import Parameter
    node = diag.node
    result = node.set_parameters([Parameter('stale_warn_s', value=0.5)])[0]
    assert result.successful and diag.settings['stale_warn_s'] == 0.5
    result = node.set_parameters([Parameter('stale_error_s', value=0.1)])[0]
    assert not result.successful and 'stale_error_s 0.1 is below stale_warn_s 0.5' in \
        result.reason
    assert diag.settings['stale_error_s'] == 10.0
    result = node.set_parameters([Parameter('min_rate_hz', value=-1.0)])[0]
    assert not result.successful                    # outside the descriptor's range
