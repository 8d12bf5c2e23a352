"""
The stirring_input node itself, in this process, on a rig unlike the built-in plant.

What it proves, on a 3-bladed rig with its own topic and joint names, hub joint ``hub`` and an
unwrapped azimuth, fed through DDS by a test publisher at the clock's pace: until ``~/start`` is
called the node commands trim only (collective on every blade, PHASE_DONE); a test point runs
trim, cyclic step, stirring, then ends by itself (its duration) with a ramp back to trim and
PHASE_DONE, and holds trim after; ``~/start`` runs a second one and ``~/abort`` ends it the same
way, the answer naming the test point; after either the pitch commands are collective only.
(The process-level contract, signals, deactivate and a stale azimuth: test_actuator_live.py.)
Settings are checked at run time (an amplitude above the limit is refused with the reason, a
read-only limit cannot be changed), and the pitch commands are offered keep-last with a small
depth and a lifespan: no stale backlog.
"""

import math
import os
import time
import warnings

from cpu_use import CpuUse, starved
import numpy as np
import pytest
from ros_domains import next_domain

rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
msgs = pytest.importorskip('rotor_id_msgs.msg', reason='rotor_id_msgs not built')

OMEGA = 2 * math.pi * 15
COLLECTIVE = math.radians(2.0)
RIG = """\
rotor: {blades: 3, advance_ratio: 0.0, flap_frequency: 1.2, tip_loss: 0.97}
topics: {blade_pitch: stand/pitch, blade_flap: stand/flap, azimuth: stand/shaft,
         pitch_command: stand/pitch_setpoint, stirring: stand/excitation}
joint_names: {azimuth: hub, blade_pitch: [p1, p2, p3], blade_flap: [f1, f2, f3]}
azimuth_convention: unwrapped
model: multiblade_wake
unknowns: [A, AL_over_tau, inv_tau]
window_s: [0.8, 0.9]
"""


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    """Two test points (one ends by itself, one is aborted); return what the node did."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from rcl_interfaces.srv import SetParameters
    from rotor_id.nodes.common import joint_state, SENSOR_OFFER_QOS, SENSOR_QOS
    from rotor_id.nodes.stirring_input import EXCITATION_QOS, StirringInput
    from rotor_id_msgs.msg import StirringCommand
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    description = tmp_path_factory.mktemp('rig') / 'rig.yaml'
    description.write_text(RIG)
    domain = next_domain()
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    params = [Parameter('run_description', value=str(description)),
              Parameter('t0', value=10.0), Parameter('step_after_rad', value=2.0),
              Parameter('duration_rad', value=8.0), Parameter('ramp_s', value=0.05),
              Parameter('omegadot', value=-1.0),
              Parameter('max_stirring_rate_rad_s', value=1e4)]
    node = StirringInput(parameter_overrides=params, context=context, namespace='/rig7')
    test = rclpy.create_node('test_stirring_node', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(test)
    shaft = test.create_publisher(JointState, '/rig7/stand/shaft', SENSOR_OFFER_QOS)
    phases, commands = [], []
    test.create_subscription(StirringCommand, '/rig7/stand/excitation',
                             lambda m: phases.append((m.phase, m.header.stamp)), EXCITATION_QOS)
    test.create_subscription(JointState, '/rig7/stand/pitch_setpoint', commands.append,
                             SENSOR_QOS)
    clients = {name: test.create_client(Trigger, f'/rig7/stirring_input/{name}')
               for name in ('start', 'abort')}
    set_params = test.create_client(SetParameters, '/rig7/stirring_input/set_parameters')
    start_ns = test.get_clock().now().nanoseconds
    turns = 1000 * 2 * math.pi                           # an encoder that has run for a while

    def publish_shaft():
        now = test.get_clock().now().nanoseconds
        psi = turns + OMEGA * (now - start_ns) / 1e9
        shaft.publish(joint_state(now, ['hub'], [psi], [OMEGA]))
    test.create_timer(0.002, publish_shaft)

    def spin(seconds, until=None):
        end = test.get_clock().now().nanoseconds + seconds * 1e9
        while test.get_clock().now().nanoseconds < end:
            executor.spin_once(timeout_sec=0.01)
            if until is not None and until():
                return True
        return False

    def call(client, request):
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        return future.result()

    def done_count():
        # PHASE_DONE after a test point (the first is the trim held before any start)
        return _sequence(phases)[1:].count(StirringCommand.PHASE_DONE)

    out = {'phases': phases, 'commands': commands, 'answers': {}}
    try:
        # nobody asked for a test point: trim only, for 1 s of commands
        cpu, load = CpuUse(), os.getloadavg()[0]
        spin(1.0)
        out['before_start'] = (list(commands), list(phases))
        out['before_start_use'] = (max(load, os.getloadavg()[0]), cpu.busy_share())
        out['answers']['first_start'] = call(clients['start'], Trigger.Request())
        # test point 1: t0 + duration = 2 + 10 + 8 = 20 rad after the start: 0.21 s, ramp 0.05 s
        out['first_done'] = spin(10.0, lambda: done_count() > 0)
        spin(0.2)
        out['n_first'] = len(phases)
        out['commands_first'] = len(commands)
        # run-time settings: refused with a reason, or accepted for the next test point
        out['too_big'] = call(set_params, SetParameters.Request(parameters=[
            Parameter('amplitude_rad', value=0.2).to_parameter_msg()])).results[0]
        out['read_only'] = call(set_params, SetParameters.Request(parameters=[
            Parameter('max_amplitude_rad', value=0.5).to_parameter_msg()])).results[0]
        out['accepted'] = call(set_params, SetParameters.Request(parameters=[
            Parameter('duration_rad', value=500.0).to_parameter_msg()])).results[0]
        out['answers']['abort_idle'] = call(clients['abort'], Trigger.Request())
        cpu, load = CpuUse(), os.getloadavg()[0]
        out['answers']['start'] = call(clients['start'], Trigger.Request())
        out['answers']['start_again'] = call(clients['start'], Trigger.Request())
        spin(10.0, lambda: any(p == StirringCommand.PHASE_STIRRING
                               for p, _ in phases[out['n_first']:]))
        spin(0.1)
        out['answers']['abort'] = call(clients['abort'], Trigger.Request())
        out['second_done'] = spin(10.0, lambda: done_count() > 1)
        out['second_use'] = (max(load, os.getloadavg()[0]), cpu.busy_share())
        out['last_end'] = str(node.diagnostics.values.get('last_end', ''))
        spin(0.2)
        out['offers'] = test.get_publishers_info_by_topic('/rig7/stand/pitch_setpoint')
        out['qos'] = node.pub_command.qos_profile
    finally:
        executor.shutdown()
        node.destroy_node()
        test.destroy_node()
        rclpy.try_shutdown(context=context)
    return out


def _stamped_from(commands, seconds):
    """Return the pitch commands whose header stamp is at or after ``seconds`` (clock time)."""
    return [c for c in commands if c.header.stamp.sec + c.header.stamp.nanosec * 1e-9 >= seconds]


def _sequence(phases):
    seq = []
    for phase, _ in phases:
        if not seq or seq[-1] != phase:
            seq.append(phase)
    return seq


def test_only_trim_until_a_start_is_asked_for(run):
    from rotor_id_msgs.msg import StirringCommand as S
    commands, phases = run['before_start']
    # 200 Hz for 1 s: at least a quarter of them where the cores had room, some where the
    # machine was measured saturated (its single-threaded executor then spins seldom)
    load, busy = run['before_start_use']
    measured = f'{len(commands)} commands in 1 s; load {load:.1f}, CPU {100 * busy:.0f} % busy'
    assert len(commands) >= (10 if starved(load, busy) else 50), measured
    if len(commands) < 50:
        warnings.warn(f'{measured} (no CPU to spare)')
    np.testing.assert_allclose([c.position for c in commands], COLLECTIVE, atol=1e-12)
    assert phases and {p for p, _ in phases} == {S.PHASE_DONE}
    assert run['answers']['first_start'].success, run['answers']['first_start'].message
    assert 'test point 1' in run['answers']['first_start'].message


def test_a_test_point_ends_by_itself_and_holds_trim(run):
    from rotor_id_msgs.msg import StirringCommand as S
    assert run['first_done']
    first = run['phases'][:run['n_first']]
    while first and first[0][0] == S.PHASE_DONE:      # holding trim before the start
        first = first[1:]
    assert _sequence(first) == [S.PHASE_TRIM, S.PHASE_CYCLIC_STEP, S.PHASE_STIRRING,
                                S.PHASE_RAMP_DOWN, S.PHASE_DONE]
    stamp = {p: s.sec + s.nanosec * 1e-9 for p, s in reversed(first)}   # first stamp of each
    # the schedule in azimuth: step 2 rad after the start, stirring 10 later, 8 of stirring,
    # then a 0.05 s ramp (the first StirringCommand of a phase is sent at its first command,
    # 5 ms grid)
    grid = 1 / 200 + 1e-3          # a phase starts at the first grid command: up to a period late
    assert stamp[S.PHASE_CYCLIC_STEP] - stamp[S.PHASE_TRIM] == pytest.approx(2 / OMEGA, abs=grid)
    assert stamp[S.PHASE_RAMP_DOWN] - stamp[S.PHASE_TRIM] == pytest.approx(20 / OMEGA, abs=grid)
    assert stamp[S.PHASE_DONE] - stamp[S.PHASE_RAMP_DOWN] == pytest.approx(0.05, abs=grid)
    # after the end: collective only on every blade, on the rig's joints (every command the
    # node stamped from PHASE_DONE on; a starved executor takes fewer of them in 0.2 s)
    after = _stamped_from(run['commands'][:run['commands_first']], stamp[S.PHASE_DONE])
    assert after, 'no command after the end'
    assert all(list(c.name) == ['p1', 'p2', 'p3'] for c in after)       # a 3-bladed rig
    np.testing.assert_allclose([c.position for c in after], COLLECTIVE, atol=1e-12)


def test_abort_ramps_back_to_trim_and_names_the_test_point(run):
    from rotor_id_msgs.msg import StirringCommand as S
    answers = run['answers']
    idle = answers['abort_idle']
    assert not idle.success and 'nothing to abort' in idle.message
    assert answers['start'].success and 'test point 2' in answers['start'].message
    assert not answers['start_again'].success and 'test point 2 is' in \
        answers['start_again'].message
    assert answers['abort'].success and answers['abort'].message.startswith('test point 2: ')
    assert 'aborted' in answers['abort'].message
    assert run['second_done']
    second = run['phases'][run['n_first']:]
    while second and second[0][0] == S.PHASE_DONE:     # still holding trim before the start
        second = second[1:]
    # duration_rad 500 would have stirred for 5 s: the abort ended it, through the ramp
    assert _sequence(second) == [S.PHASE_TRIM, S.PHASE_CYCLIC_STEP, S.PHASE_STIRRING,
                                 S.PHASE_RAMP_DOWN, S.PHASE_DONE]
    stamp = {p: s.sec + s.nanosec * 1e-9 for p, s in reversed(second)}
    grid = 1 / 200 + 1e-3
    ramp = stamp[S.PHASE_DONE] - stamp[S.PHASE_RAMP_DOWN]
    if 'ramped from a late command' in run['last_end']:
        # the node's tick came after the schedule's ramp had ended (a starved executor): it
        # ramps from the cyclic it last commanded, over the whole ramp_s, from then on
        load, busy = run['second_use']
        assert ramp >= 0.05 - grid, (ramp, run['last_end'])
        warnings.warn(f'{run["last_end"]}: the ramp ended {ramp:.3f} s after the abort (load '
                      f'{load:.1f}, CPU {100 * busy:.0f} % busy)')
    else:
        assert ramp == pytest.approx(0.05, abs=grid)
    assert stamp[S.PHASE_RAMP_DOWN] - stamp[S.PHASE_STIRRING] < 1.0
    last = _stamped_from(run['commands'], stamp[S.PHASE_DONE])
    assert last, 'no command after the abort'
    np.testing.assert_allclose([c.position for c in last], COLLECTIVE, atol=1e-12)


def test_settings_are_checked_at_run_time(run):
    assert not run['too_big'].successful
    assert 'amplitude_rad' in run['too_big'].reason and 'max_amplitude_rad' in \
        run['too_big'].reason
    assert not run['read_only'].successful and 'read-only' in run['read_only'].reason
    assert run['accepted'].successful


def test_pitch_commands_cannot_queue_a_stale_backlog(run):
    from rclpy.qos import HistoryPolicy
    qos = run['qos']
    assert qos.history == HistoryPolicy.KEEP_LAST and qos.depth <= 21       # 0.1 s at 200 Hz
    (offer,) = run['offers']                                 # what readers see, through DDS
    assert 0 < offer.qos_profile.lifespan.nanoseconds <= 0.2e9             # lead_s + 0.1 s


@pytest.mark.parametrize('broken', ['schedule', 'pitch_conversion'])
def test_an_exception_mid_stirring_ends_on_trim(tmp_path, monkeypatch, broken):
    """The command tick raises mid-stirring; close() (what spin_node runs next) ends on trim."""
    from rclpy.executors import SingleThreadedExecutor
    from rotor_id.nodes import stirring_input as module
    from rotor_id.nodes.common import joint_state, SENSOR_OFFER_QOS, SENSOR_QOS
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    node, context = _stirring_node(tmp_path, '/rig8', t0=5.0, step_after_rad=1.0,
                                   duration_rad=1e5, omegadot=-0.01,
                                   max_stirring_rate_rad_s=1e4, azimuth_timeout_s=5.0)
    test = rclpy.create_node('test_exception', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(test)
    shaft = test.create_publisher(JointState, '/rig8/stand/shaft', SENSOR_OFFER_QOS)
    commands = []
    test.create_subscription(JointState, '/rig8/stand/pitch_setpoint',
                             lambda m: commands.append(np.array(m.position)), SENSOR_QOS)
    test.create_timer(0.002, lambda: shaft.publish(joint_state(
        test.get_clock().now().nanoseconds, ['hub'],
        [OMEGA * test.get_clock().now().nanoseconds / 1e9], [OMEGA])))
    amplitude = math.radians(1.5)

    def spin_until(condition, seconds=20.0):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not condition():
            executor.spin_once(timeout_sec=0.01)
        return condition()

    raised = None
    try:
        assert spin_until(lambda: len(commands) > 10)
        assert node.on_start(Trigger.Request(), Trigger.Response()).success
        assert spin_until(lambda: np.ptp(commands[-1]) > 0.5 * amplitude), 'never stirred'

        def fail(*_args, **_kwargs):
            raise RuntimeError('a bug')
        if broken == 'schedule':
            monkeypatch.setattr(node.test_point, 'inputs', fail)
        else:
            monkeypatch.setattr(module, 'blade_pitch_from_multiblade', fail)
        with pytest.raises(RuntimeError, match='a bug') as raised:
            spin_until(lambda: False, 5.0)
        n = len(commands)
        node.close()                                 # spin_node's clean-up
        # take what is in flight: the stop ramp ends on trim (a starved executor takes longer)
        spin_until(lambda: len(commands) > n and np.allclose(commands[-1], COLLECTIVE,
                                                             rtol=0, atol=1e-12), 10.0)
        spin_until(lambda: False, 0.2)
    finally:
        executor.shutdown()
        node.destroy_node()
        test.destroy_node()
        rclpy.try_shutdown(context=context)
    assert raised is not None
    after = commands[n:]
    assert after, 'nothing published after the exception'
    np.testing.assert_allclose(after[-1], COLLECTIVE, atol=1e-12)
    if broken == 'schedule':      # the stop ramp ran (its own arithmetic): shrinking spreads
        spreads = [np.ptp(c) for c in after]
        assert len(after) >= 3 and max(spreads) <= 2 * amplitude + 1e-9


def test_a_start_before_the_rotor_turns_is_announced_however_late_the_first_sample(tmp_path):
    """
    A start asked before the shaft turns is announced by TRIM however late its first sample.

    The test point begins with the first azimuth sample (as a recording's first sample); when
    that sample reaches a busy node later than the step's
    ``step_after_rad`` (here 150 ms against 21 ms), the first command falls mid-schedule, and
    the test point is still announced first: a TRIM StirringCommand stamped with the first
    sample, before the phase the command is in (readers arm a test point on TRIM).
    """
    from rclpy.executors import SingleThreadedExecutor
    from rotor_id_msgs.msg import StirringCommand as S
    from std_srvs.srv import Trigger

    node, context = _stirring_node(tmp_path, '/rig9', t0=10.0, step_after_rad=2.0,
                                   duration_rad=8.0, ramp_s=0.05, omegadot=-1.0,
                                   max_stirring_rate_rad_s=1e4)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    stirring, commands = [], []
    node.pub_stirring.publish = lambda m: stirring.append((m.phase, _ns(m.header.stamp), m))
    node.pub_command.publish = lambda m: commands.append((_ns(m.header.stamp), m.position))
    try:
        assert node.on_start(Trigger.Request(), Trigger.Response()).success
        asked = node.get_clock().now().nanoseconds
        executor.spin_once(timeout_sec=0.05)
        before = len(stirring)
        time.sleep(0.15)
        # the shaft's first 150 ms of samples arrive at once, late (the node was busy)
        now = node.get_clock().now().nanoseconds
        stamps = np.arange(asked + 1_000_000, now, 2_000_000)
        node.azimuth.add_batch(stamps, np.mod(OMEGA * (stamps - stamps[0]) / 1e9, 2 * math.pi),
                               np.full(stamps.size, OMEGA), int(stamps[0]))
        first_command = len(commands)
        node.tick()
        after = stirring[before:]
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert len(after) >= 2 and after[0][0] == S.PHASE_TRIM, [p for p, _, _ in after]
    assert after[0][1] == stamps[0]                          # the first sample since the start
    assert after[1][0] != S.PHASE_TRIM and after[1][1] <= commands[first_command][0]
    assert np.ptp(commands[first_command][1]) > 0            # the schedule's cyclic, at its time


def test_a_command_late_past_the_ramp_still_ramps_the_cyclic_down(tmp_path):
    """
    A tick so late that the schedule's ramp is over still ramps the cyclic, never steps it.

    A starved node (here: no tick for 0.3 s while stirring; the test point ends 0.21 s after
    its start and ramps over 0.05 s) finds its test point past the end. The cyclic last
    commanded then goes to trim over ``ramp_s`` from that tick, through PHASE_RAMP_DOWN: the
    actuator sees no step, however late the node was.
    """
    from rotor_id_msgs.msg import StirringCommand as S
    from std_srvs.srv import Trigger

    node, context = _stirring_node(tmp_path, '/rig10', t0=10.0, step_after_rad=2.0,
                                   duration_rad=8.0, ramp_s=0.05, omegadot=-1.0,
                                   max_stirring_rate_rad_s=1e4)
    stirring, commands = [], []
    node.pub_stirring.publish = lambda m: stirring.append(m)
    node.pub_command.publish = lambda m: commands.append(np.asarray(m.position))
    shaft = {'last': node.get_clock().now().nanoseconds}

    def tick_now():
        # the shaft's samples up to now, then one command tick
        now = node.get_clock().now().nanoseconds
        stamps = np.arange(shaft['last'] + 2_000_000, now, 2_000_000)
        if stamps.size:
            node.azimuth.add_batch(stamps, np.mod(OMEGA * stamps / 1e9, 2 * math.pi),
                                   np.full(stamps.size, OMEGA))
            shaft['last'] = int(stamps[-1])
        node.tick()
        return stirring[-1].phase if stirring else None
    try:
        tick_now()
        assert node.on_start(Trigger.Request(), Trigger.Response()).success
        deadline = time.monotonic() + 5.0
        while tick_now() != S.PHASE_STIRRING and time.monotonic() < deadline:
            time.sleep(0.005)
        assert stirring[-1].phase == S.PHASE_STIRRING
        before, late = commands[-1], len(commands)
        late_messages = len(stirring)
        time.sleep(0.3)                                   # no tick: past the end and the ramp
        while tick_now() != S.PHASE_DONE and time.monotonic() < deadline:
            time.sleep(0.005)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    phases = [m.phase for m in stirring[late_messages:]]
    assert phases[0] == S.PHASE_RAMP_DOWN and phases[-1] == S.PHASE_DONE, phases
    # the cyclic amplitude A of each command: over three equally spaced blades the pitch's
    # standard deviation is A/√2 at any azimuth (their spread max − min is not: 1.5-1.73 A)
    spread = [float(np.std(c)) for c in commands[late - 1:]]
    assert 0.0 < spread[1] < spread[0] == float(np.std(before)), spread[:3]
    assert spread[-1] < 1e-12 and all(b <= a + 1e-12 for a, b in zip(spread[1:], spread[2:]))


def _stirring_node(tmp_path, namespace, **settings):
    """Return (a StirringInput on RIG with these parameters, its own rclpy context)."""
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.nodes.stirring_input import StirringInput
    description = tmp_path / 'rig.yaml'
    description.write_text(RIG)
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=next_domain(),
               signal_handler_options=SignalHandlerOptions.NO)
    params = [Parameter('run_description', value=str(description))] + [
        Parameter(name, value=value) for name, value in settings.items()]
    return StirringInput(parameter_overrides=params, context=context,
                         namespace=namespace), context


def _ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_lifecycle_states_gate_the_commands(tmp_path):
    """Unconfigured or inactive: nothing commanded, ~/start refused; configure checks the rig."""
    from rclpy.lifecycle import TransitionCallbackReturn as R
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.nodes.stirring_input import StirringInput
    from std_srvs.srv import Trigger

    description = tmp_path / 'rig.yaml'
    description.write_text(RIG)
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=next_domain(),
               signal_handler_options=SignalHandlerOptions.NO)
    nodes = []

    def make(state, rig):
        nodes.append(StirringInput(context=context, parameter_overrides=[
            Parameter('run_description', value=str(rig)),
            Parameter('initial_state', value=state)]))
        return nodes[-1]

    def start(node):
        return node.on_start(Trigger.Request(), Trigger.Response())
    try:
        missing = make('unconfigured', tmp_path / 'absent.yaml')
        assert missing.pub_command is None and not missing.commanding
        answer = start(missing)
        assert not answer.success and 'unconfigured' in answer.message
        assert missing.trigger_configure() == R.FAILURE      # stays unconfigured, says why
        assert 'absent.yaml' in missing.configure_error
        assert missing._state_label() == 'unconfigured'
        inactive = make('inactive', description)
        assert inactive.pub_command is not None and not inactive.commanding
        assert not start(inactive).success
        assert inactive.trigger_activate() == R.SUCCESS and inactive.commanding
        assert start(inactive).success
        assert inactive.trigger_deactivate() == R.SUCCESS and not inactive.commanding
        assert not inactive.start_requested                  # a pending start does not survive
        with pytest.raises(ValueError, match='initial_state'):
            make('running', description)
        with pytest.raises(ValueError, match='absent.yaml'):   # ros2 run: one line, exit 2
            make('active', tmp_path / 'absent.yaml')
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
