"""
stirring_input: the report's stirring schedule as per-blade pitch commands (``ros2 run``).

A managed (lifecycle) node that drives a swashplate; its contract is docs/actuator.md:

* unconfigured: publishes nothing. configure validates the parameters and loads the rig (the run
  description, parameter ``run_description``: topics, joint names, blade count, azimuth
  convention); a bad one is refused with the reason (FAILURE, stays unconfigured).
* inactive: publishes nothing.
* active: publishes trim (collective only, the same pitch on every blade) at ``rate_hz`` until a
  test point is asked for on ``~/start`` (std_srvs/Trigger). Nothing else starts one.
* deactivate, shutdown, SIGINT/SIGTERM, an exception in a callback, and the azimuth going
  stale (no sample for ``azimuth_timeout_s``) ramp the cyclic to trim over ``stop_ramp_s`` on
  the steady clock (not on the azimuth, which may be what failed), then publish trim; on a
  signal or an exception the final trim is flushed to the readers before the process exits.

``initial_state`` (default ``active``) is where the node brings itself at start: ``ros2 run``
holds trim at once; under a lifecycle manager or a supervisor give ``unconfigured``.

The schedule (:class:`rotor_id.physics.stirring.StirringSchedule`, Ch.2 eqs 1-5): trim, then
the lateral cyclic stepped ``step_after_rad`` of azimuth after the start (one revolution, as in
the recording convention of docs/run_description.md), then stirring ``t0`` later with phase
φ = ω̇ (t − t0)². It is bounded (:class:`rotor_id.excitation.StirringTestPoint`): it ends after
``duration_rad`` of azimuth or when its rate reaches ``max_stirring_rate_rad_s``; the cyclic then
ramps back to trim over ``ramp_s`` and PHASE_DONE is published; ``~/abort`` starts that ramp at
once (or cancels a start not yet begun). Time inside the schedule is the report's nondimensional
time: the unwrapped azimuth of blade 1 from the rig's azimuth topic, extrapolated with Ω to each
command's stamp.

Command timing: one command per tick of a timer at ``rate_hz``, stamped with the time it applies
from: now, or now + ``lead_s`` for a driver that asks for a lead (default 0: never ahead, never
in bursts). Publishes JointState (the blade_pitch joints, rad) on ``pitch_command`` and
rotor_id_msgs/StirringCommand on ``stirring``, both volatile keep-last.
"""

from dataclasses import dataclass
import math
import sys
import time

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from rclpy.duration import Duration
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rotor_id.excitation import (check_excitation_limits, PHASE_CYCLIC_STEP, PHASE_DONE,
                                 PHASE_NAMES, PHASE_RAMP_DOWN, PHASE_STIRRING, PHASE_TRIM,
                                 StirringTestPoint)
from rotor_id.nodes.common import (allow_runtime_changes, declare, Diagnostics, joint_state,
                                   node_run_description, Rig, RUN_DESCRIPTION_HELP, SENSOR_QOS,
                                   spin_node, time_msg)
from rotor_id.nodes.live import AzimuthTracker, BadSample, check_azimuth_sample
from rotor_id.nodes.polling import checked_azimuth_batch, one_by_one, SensorPoller
from rotor_id.physics.stirring import blade_pitch_from_multiblade, StirringSchedule
from rotor_id_msgs.msg import StirringCommand
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

TWO_PI = 2.0 * math.pi
NS = 1_000_000_000
#: Time a pitch command may live after the time it applies from, s (QoS lifespan on top of lead_s).
COMMAND_LIFETIME_S = 0.1
#: Azimuth samples kept for the unwrapping and t_at (s): commands apply from now (+ lead_s), so
#: older samples are never read.
AZIMUTH_KEPT_S = 2.0
#: Longest stop_ramp_s (s): the ramp on a signal must end well inside the 5 s a launch system
#: leaves between its SIGINT and its SIGTERM (ros2 launch's sigterm_timeout default).
MAX_STOP_RAMP_S = 2.0
#: After the stop ramp, trim is repeated this long (s): a best-effort reader that lags (it
#: has no acknowledgement to wait for) still receives trim last before the process exits.
FINAL_HOLD_S = 0.2
#: How long a stopping node waits for reliable readers of the pitch commands (a driver) to
#: acknowledge its final trim (s): short enough that SIGINT → exit stays within 5 s.
FINAL_FLUSH_S = 0.5
#: The StirringCommand: reliable (a phase change must arrive: the identifier arms on it),
#: volatile (a late or restarted reader never receives a past schedule), keep-last 20 (1 s at
#: the default 200 Hz / stirring_every 10) for a reader that falls briefly behind.
EXCITATION_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                            history=HistoryPolicy.KEEP_LAST, depth=20,
                            durability=DurabilityPolicy.VOLATILE)
INITIAL_STATES = ('unconfigured', 'inactive', 'active')


def pitch_command_qos(lead_s, rate_hz):
    """
    Return the QoS of the pitch commands: no stale backlog can build up anywhere.

    Reliable, so a reader that is keeping up gets every command (the recorder too); volatile,
    so a driver that starts late never receives old commands; KEEP_LAST with a depth of the
    commands that can still be current (those of ``lead_s`` + 0.1 s, 21 at 200 Hz without a
    lead); and a lifespan of ``lead_s`` + 0.1 s, so that DDS drops from the writer's and the
    reader's queues any command whose time passed more than 0.1 s ago: a slow actuator driver
    is never fed a backlog of old commands.
    """
    return QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                      depth=int(math.ceil((lead_s + COMMAND_LIFETIME_S) * rate_hz)) + 1,
                      durability=DurabilityPolicy.VOLATILE,
                      lifespan=Duration(nanoseconds=int((lead_s + COMMAND_LIFETIME_S) * 1e9)))


@dataclass
class StopRamp:
    """The cyclic shrinking linearly to zero on the steady clock (the collective unchanged)."""

    start_s: float            # time.monotonic() at the ramp's start
    start_ns: int             # and on the node clock
    duration_s: float
    collective: float         # θ0, rad
    cyclic: tuple             # (θI, θII) at the start, rad
    stirring_phase: float     # φ frozen at the start, rad
    reason: str

    @property
    def end_s(self) -> float:
        """Return the steady-clock time at which the cyclic is zero."""
        return self.start_s + self.duration_s

    def scale(self, at_s: float) -> float:
        """Return the fraction of the starting cyclic still applied at steady time ``at_s``."""
        if self.duration_s <= 0.0 or at_s >= self.end_s:
            return 0.0
        return min(1.0, max(0.0, 1.0 - (at_s - self.start_s) / self.duration_s))


class StirringInput(LifecycleNode):
    """Publishes bounded stirring test points, locked to the measured rotor azimuth."""

    def __init__(self, **node_options):
        super().__init__('stirring_input', **node_options)
        self.run_description = declare(self, 'run_description', '', RUN_DESCRIPTION_HELP)
        spec = [
            # test-point settings: settable at run time, used by the next test point
            ('collective_rad', math.radians(2.0), 'collective pitch theta_0 (rad): the trim held '
             'while active; a change applies from the next test point', -0.5, 0.5, False),
            ('amplitude_rad', math.radians(1.5), 'cyclic amplitude (rad; at most '
             'max_amplitude_rad)', 0.0, 0.3, False),
            ('omegadot', -0.1 / math.pi, 'stirring acceleration: phase = omegadot (t - t0)^2, '
             't in rad of azimuth (per rad^2); negative = progressing, positive = regressing',
             -10.0, 10.0, False),
            ('t0', 70.0, 'stirring start after the cyclic step (rad of azimuth; report: 70 '
             'at mu = 0, 12 at mu = 0.4)', 0.0, 1e6, False),
            ('step_after_rad', TWO_PI, 'lateral cyclic step after the test point starts '
             '(rad of azimuth)', 0.0, 1e6, False),
            ('duration_rad', 30.0, "longest stirring, after t0 (rad of azimuth; the report's "
             'windows need 12)', 1e-3, 1e7, False),
            ('ramp_s', 0.5, 'ramp of the cyclic back to trim at the end of the stirring or on '
             '~/abort (s, in azimuth at the measured rotor speed)', 0.0, 60.0, False),
            # safety limits and structure: read-only
            ('max_amplitude_rad', math.radians(3.0), 'largest cyclic amplitude accepted (rad)',
             0.0, 0.5),
            ('max_stirring_rate_rad_s', 2.0 * math.pi * 30.0, 'the stirring ends when its rate '
             '|d phi/dt| reaches this (rad/s; default: 30 Hz, 2/rev at 900 rpm)', 1e-3, 1e5),
            ('stop_ramp_s', 0.5, 'ramp of the cyclic to trim on deactivate, shutdown, '
             'SIGINT/SIGTERM, an exception or a stale azimuth (s, steady clock; at most '
             f'{MAX_STOP_RAMP_S:g})', 0.0, MAX_STOP_RAMP_S),
            ('azimuth_timeout_s', 0.25, 'no azimuth sample newer than this (s) while the cyclic '
             'is applied: ramp to trim. The cyclic phase is the azimuth extrapolated with the '
             'last rotor speed; 0.25 s is ~4 revolutions at 15 Hz, where a 0.5 % speed error '
             'already shifts it by 0.12 rad (7 deg)', 0.01, 10.0),
            ('rate_hz', 200.0, 'pitch command rate (Hz): one command per timer tick; the '
             'plant interpolates between commands', 1.0, 2000.0),
            ('lead_s', 0.0, 'stamp and publish each command this far ahead of the time it '
             'applies from (s). 0: published when due. >0 only for a driver that applies '
             'each command at its header.stamp, never on arrival', 0.0, 1.0),
            ('stirring_every', 10, 'publish the StirringCommand every this many commands',
             1, 100000),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
            ('initial_state', 'active', 'lifecycle state the node brings itself to at start: '
             'active (holds trim at once), inactive or unconfigured (a lifecycle manager or '
             'supervisor brings it up)'),
        ]
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:5],
                                read_only=s[5] if len(s) > 5 else True) for s in spec}
        if self.d['initial_state'] not in INITIAL_STATES:
            raise ValueError(f"initial_state {self.d['initial_state']!r} is not one of "
                             f'{", ".join(INITIAL_STATES)}')
        reason = self._limits_reason(self.d)
        if reason:
            raise ValueError(reason)
        allow_runtime_changes(self, lambda _name, _value, values: self._limits_reason(values))
        self.rig = self.joints = None
        self.pub_command = self.pub_stirring = self.timer = self.poller = None
        self.commanding = False          # active: the publishers are enabled
        self.configure_error = ''
        self.test_points = 0             # test points started
        self.published = 0
        self.skipped = 0                 # timer periods without a command (a late tick)
        self._reset_run_state()
        self.diagnostics = Diagnostics(self, 'stirring schedule')
        self._lifecycle_diagnostics('unconfigured')
        self.create_service(Trigger, '~/start', self.on_start)
        self.create_service(Trigger, '~/abort', self.on_abort)
        initial = self.d['initial_state']
        if initial != 'unconfigured' and \
                self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
            raise ValueError(self.configure_error or 'configure failed (see the log)')
        if initial == 'active' and self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
            raise ValueError('activate failed (see the log)')

    def _reset_run_state(self):
        self.test_point = None           # StirringTestPoint of the current or last test point
        self.holding = True              # trim, whatever the test point's schedule says
        self.start_requested = False
        self.requested_ns = None         # when the start was asked for (node clock)
        self.start_stamp = None          # the schedule's start, for its first StirringCommand
        self.ramp = None                 # StopRamp in progress
        self.azimuth = AzimuthTracker()
        self.last_stamp = None           # stamp of the last command (ns)
        self.previous_stamp = None       # and of the one before
        self.last_u = None               # its (θ0, θI, θII)
        self.last_phase = None
        self.trim_collective = self.d['collective_rad']

    @staticmethod
    def _limits_reason(values):
        return check_excitation_limits(values['amplitude_rad'], values['max_amplitude_rad'],
                                       values['duration_rad'],
                                       values['max_stirring_rate_rad_s'], values['ramp_s'])

    def _lifecycle_diagnostics(self, label):
        self.diagnostics.set_value('lifecycle', label)
        self.diagnostics.level_override = None if label == 'active' else (
            DiagnosticStatus.STALE, f'lifecycle state {label}: no pitch commands published')

    # -------------------------------------------------------------------------- lifecycle
    def on_configure(self, state):
        """Load the rig and check the settings; create the publishers and the azimuth reader."""
        try:
            rig = Rig(node_run_description(self.run_description))
        except Exception as exc:             # noqa: B902 - rclpy would swallow it unsaid
            self.configure_error = str(exc) if isinstance(exc, (ValueError, OSError)) else \
                f'{type(exc).__name__}: {exc}'
            self.get_logger().error(f'configure refused: {exc}')
            return TransitionCallbackReturn.FAILURE
        self.rig, self.joints = rig, rig.pitch_joints
        self.pub_command = self.create_lifecycle_publisher(
            JointState, rig.topics['pitch_command'],
            pitch_command_qos(self.d['lead_s'], self.d['rate_hz']))
        self.pub_stirring = self.create_lifecycle_publisher(
            StirringCommand, rig.topics['stirring'], EXCITATION_QOS)
        # the azimuth (1 kHz) is taken in batches at each tick (rotor_id.nodes.polling), not
        # by one executor callback per message
        self.diagnostics.watch('azimuth', rig.topics['azimuth'])
        self.poller = SensorPoller(self, on_error=lambda exc: self.diagnostics.count(
            'sensor_batch_error', f'{type(exc).__name__}: {exc}'))
        self.poller.subscribe(JointState, rig.topics['azimuth'],
                              lambda raws, _infos: self.on_azimuth_batch(raws), SENSOR_QOS)
        self.timer = self.create_timer(1.0 / self.d['rate_hz'], self.tick)
        self.timer.cancel()
        self._lifecycle_diagnostics('inactive')
        self.get_logger().info(
            f'configured: {len(self.joints)} blades, pitch commands on '
            f'{self.pub_command.topic_name} at {self.d["rate_hz"]:g} Hz, lead '
            f'{self.d["lead_s"]:g} s; stop ramp {self.d["stop_ramp_s"]:g} s, azimuth timeout '
            f'{self.d["azimuth_timeout_s"]:g} s')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        """Enable the publishers and hold trim (a test point starts only on ~/start)."""
        self._reset_run_state()
        result = super().on_activate(state)
        self.commanding = True
        self.timer.reset()
        self._lifecycle_diagnostics('active')
        self.diagnostics.idle = True
        self.get_logger().info(f'active: holding trim (collective {self.trim_collective:.4g} '
                               'rad on every blade); a test point starts on ~/start')
        return result

    def on_deactivate(self, state):
        """Ramp the cyclic to trim, publish trim, then stop publishing."""
        self.ramp_to_trim('deactivate requested')
        self.timer.cancel()
        self.commanding = False
        self._lifecycle_diagnostics('inactive')
        return super().on_deactivate(state)

    def on_cleanup(self, state):
        """Drop the publishers, the azimuth reader and the rig."""
        self._destroy_entities()
        self._lifecycle_diagnostics('unconfigured')
        return super().on_cleanup(state)

    def on_shutdown(self, state):
        """From active: ramp to trim and publish it first."""
        return self._end_on_trim('shutdown requested', 'finalized')

    def on_error(self, state):
        """Handle a transition that raised: trim if still commanding, then unconfigured."""
        return self._end_on_trim('error in a transition', 'unconfigured')

    def _end_on_trim(self, reason, label):
        self.ramp_to_trim(reason)
        self.commanding = False
        self._destroy_entities()
        self._lifecycle_diagnostics(label)
        return TransitionCallbackReturn.SUCCESS

    def _destroy_entities(self):
        if self.timer is not None:
            self.timer.cancel()
            self.destroy_timer(self.timer)
        for subscription, _handler in (self.poller.entries if self.poller else []):
            self.destroy_subscription(subscription)
        for publisher in (self.pub_command, self.pub_stirring):
            if publisher is not None:
                self.destroy_lifecycle_publisher(publisher)
        self.diagnostics.streams.pop('azimuth', None)
        self.pub_command = self.pub_stirring = self.timer = self.poller = None
        self.rig = self.joints = None

    def _state_label(self):
        return self._state_machine.current_state[1]

    # -------------------------------------------------------------------------- services
    def on_start(self, _request, response):
        """Ask for a new test point (refused unless active, and while one is running)."""
        response.success = False
        if not self.commanding:
            response.message = (f'stirring_input is {self._state_label()}: activate it first '
                                '(ros2 lifecycle set <node> activate)')
        elif self.start_requested:
            response.message = f'test point {self.test_points + 1} is about to start'
        elif self.ramp is not None:
            response.message = (f'ramping the cyclic to trim ({self.ramp.reason}); try again '
                                'once done')
        elif not self.holding and not self._done():
            response.message = (f'test point {self.test_points} is still running '
                                f'({self._phase_name()}); abort it first')
        else:
            self.start_requested = True
            self.requested_ns = self.get_clock().now().nanoseconds
            response.success = True
            response.message = (f'test point {self.test_points + 1} starts with the next pitch '
                                'command' + ('' if self._azimuth_fresh() else
                                             ' once a fresh azimuth sample arrives'))
            self.get_logger().info(response.message)
        return response

    def on_abort(self, _request, response):
        """Ramp the cyclic back to trim now (or cancel a start not yet begun)."""
        response.success = False
        if self.start_requested:
            self.start_requested = False
            response.success = True
            response.message = f'start of test point {self.test_points + 1} cancelled'
        elif self.ramp is not None:
            response.message = f'already ramping to trim ({self.ramp.reason})'
        elif self.test_point is None or self.holding or self._done():
            response.message = 'no test point is running: nothing to abort'
        else:
            t = self._t_now()
            changed = self.test_point.abort(t)
            response.success = True
            response.message = (f'test point {self.test_points}: '
                                + (f'aborted at t = {t:.4g}, cyclic back at trim by t = '
                                   f'{self.test_point.t_done:.4g}' if changed else
                                   'already ramping back to trim'))
        if response.success:
            self.get_logger().warning(response.message)
        return response

    # -------------------------------------------------------------------------- schedule
    def _t_now(self):
        return float(self.azimuth.t_at([self.get_clock().now().nanoseconds])[0])

    def _done(self):
        return self.test_point.phase(self._t_now()) == PHASE_DONE

    def _phase_name(self):
        return PHASE_NAMES[self.test_point.phase(self._t_now())]

    def _azimuth_fresh(self, now_ns=None):
        if not self.azimuth.ready:
            return False
        now_ns = self.get_clock().now().nanoseconds if now_ns is None else now_ns
        return now_ns - self.azimuth.series.last_stamp <= self.d['azimuth_timeout_s'] * NS

    def _start(self, t_start, omega):
        d = self.d
        step = t_start + d['step_after_rad']
        schedule = StirringSchedule(d['collective_rad'], d['amplitude_rad'], d['omegadot'],
                                    step + d['t0'], step)
        self.test_point = StirringTestPoint(schedule, omega, d['duration_rad'],
                                            d['max_stirring_rate_rad_s'], d['ramp_s'],
                                            d['max_amplitude_rad'])
        self.test_points += 1
        self.trim_collective = d['collective_rad']
        self.start_requested = False
        self.holding = False
        self.diagnostics.idle = False
        self.diagnostics.problem('azimuth_stale')
        self.get_logger().info(
            f'test point {self.test_points}: cyclic step at t = {step:.4g}, stirring '
            f'({schedule.direction}) at t = {schedule.t0:.4g}, ends by t = '
            f'{self.test_point.t_end:.4g} ({self.test_point.end_reason}), trim again by '
            f't = {self.test_point.t_done:.4g}')

    def on_azimuth_batch(self, raws):
        """Track the unwrapped azimuth of blade 1 from a batch of serialized samples."""
        self.diagnostics.received('azimuth', len(raws))
        checked = checked_azimuth_batch(raws, self.rig.azimuth_joint,
                                        self.azimuth.series.last_stamp,
                                        self.rig.azimuth_convention)
        if checked is None:               # one at a time: each refusal with its reason
            for stamp, names, position, velocity in one_by_one(raws, self.diagnostics):
                try:
                    psi, omega = check_azimuth_sample(
                        names, position, velocity, self.rig.azimuth_joint, stamp,
                        self.azimuth.series.last_stamp, self.rig.azimuth_convention)
                except BadSample as bad:
                    self.diagnostics.count(bad.kind, str(bad))
                    continue
                self.azimuth.add(stamp, psi, omega, stamp - int(AZIMUTH_KEPT_S * NS))
            return
        stamps, psi, omega = checked
        self.azimuth.add_batch(stamps, psi, omega, int(stamps[-1]) - int(AZIMUTH_KEPT_S * NS))

    def tick(self):
        """
        Publish the command for now (+ ``lead_s``): one per tick, never a burst.

        Takes the azimuth first; a cyclic applied while the azimuth is stale starts the stop
        ramp; a test point asked for starts with this command (its first StirringCommand,
        PHASE_TRIM, is stamped with the schedule's start). An exception starts the stop ramp
        and is raised again: the node then stops (spin_node), finishing the ramp in close().
        """
        try:
            self._tick()
        except Exception as exc:              # noqa: B902 - raised again after the ramp starts
            self.get_logger().error(f'{type(exc).__name__} in the command tick: {exc}; '
                                    'ramping the cyclic to trim and stopping')
            if self.ramp is None and self.commanding:
                self._begin_ramp(f'{type(exc).__name__} in the command tick')
            raise

    def _tick(self):
        if not self.commanding:
            return
        self.poller.poll()
        now = self.get_clock().now().nanoseconds
        stamp = now + int(self.d['lead_s'] * NS)
        if self.last_stamp is not None:
            if stamp <= self.last_stamp:
                return
            late = round((stamp - self.last_stamp) * self.d['rate_hz'] / NS) - 1
            if late > 0:
                self.skipped += late
                self.diagnostics.set_value('commands_skipped_late', self.skipped)
        fresh = self._azimuth_fresh(now)
        applied = self.last_u is not None and (self.last_u[1] or self.last_u[2])
        if not fresh and self.ramp is None and (applied or not self.holding):
            self._on_stale(now)
        if self.start_requested and fresh and self.ramp is None:
            self.start_stamp = self._start_stamp(now)
            self._start(float(self.azimuth.t_at([self.start_stamp])[0]), self.azimuth.omega)
        self.command(stamp, time.monotonic() + self.d['lead_s'])
        self.diagnostics.set_value('commands_published', self.published)

    def _start_stamp(self, now):
        """
        Return when a test point asked for starts: the first azimuth sample since the request.

        A start asked for before the rotor turned thus begins with its first sample (as a
        recording's first sample, docs/run_description.md), one asked for while it turns
        begins at once; never more than ``azimuth_timeout_s`` before now. On a busy node the
        first sample can arrive after the schedule's cyclic step: the first command then
        carries the schedule's cyclic at its time, and the test point is still announced by
        a TRIM StirringCommand stamped with this start (:meth:`command`).
        """
        stamps = self.azimuth.series.stamps
        i = int(np.searchsorted(stamps, self.requested_ns))
        first = int(stamps[i]) if i < len(stamps) else now
        return max(first, now - int(self.d['azimuth_timeout_s'] * NS))

    def _on_stale(self, now):
        age = ((now - self.azimuth.series.last_stamp) / NS if self.azimuth.ready
               else float('inf'))
        why = (f'azimuth stale: newest sample {age:.3f} s old (azimuth_timeout_s '
               f'{self.d["azimuth_timeout_s"]:g})')
        self.get_logger().error(f'{why}; ramping the cyclic to trim over '
                                f'{self.d["stop_ramp_s"]:g} s')
        self.diagnostics.problem('azimuth_stale', DiagnosticStatus.ERROR,
                                 f'{why}: test point {self.test_points} ended, holding trim')
        self._begin_ramp(why)

    def _begin_ramp(self, reason):
        """Start the stop ramp from the cyclic last commanded; the test point is over."""
        u = self.last_u if self.last_u is not None else (self.trim_collective, 0.0, 0.0)
        phi = 0.0
        if self.test_point is not None and not self.holding and self.azimuth.ready:
            try:
                t = self._t_now()
                self.test_point.abort(t, reason)
                phi = self.test_point.stirring_phase(t)
            except Exception:                # noqa: B902 - the ramp must start regardless
                pass
        applied = bool(u[1] or u[2])            # no cyclic: nothing to ramp, trim at once
        self.ramp = StopRamp(time.monotonic(), self.get_clock().now().nanoseconds,
                             self.d['stop_ramp_s'] if applied else 0.0, float(u[0]),
                             (float(u[1]), float(u[2])), float(phi), reason)
        self.holding = True
        self.trim_collective = float(u[0])
        self.start_requested = False
        return self.ramp

    def _inputs(self, t, at_s):
        """Return (u = [θ0, θI, θII], phase, φ, dφ/dt) at azimuth ``t``, steady time ``at_s``."""
        ramp = self.ramp
        if ramp is not None:
            scale = ramp.scale(at_s)
            u = [ramp.collective, scale * ramp.cyclic[0], scale * ramp.cyclic[1]]
            if scale > 0.0:
                return u, PHASE_RAMP_DOWN, ramp.stirring_phase, 0.0
            self.ramp = None
            self.diagnostics.set_value('last_end', f'stopped ({ramp.reason})')
            return u, PHASE_DONE, ramp.stirring_phase, 0.0
        point = self.test_point
        if point is None or self.holding or t is None:
            return [self.trim_collective, 0.0, 0.0], PHASE_DONE, 0.0, 0.0
        u, phase = point.inputs([t])[0], point.phase(t)
        last = self.last_u
        if phase == PHASE_DONE and self.last_phase in (PHASE_CYCLIC_STEP, PHASE_STIRRING) \
                and last is not None and (last[1] or last[2]):
            # a command so late (a starved node) that the schedule's ramp is already over: the
            # cyclic still ramps down from the one last commanded, never steps to trim
            period_s = 1.0 / self.d['rate_hz']
            self.ramp = StopRamp(at_s - period_s, self.get_clock().now().nanoseconds,
                                 self.d['ramp_s'] + period_s, float(last[0]),
                                 (float(last[1]), float(last[2])), point.stirring_phase(t),
                                 (f'aborted ({point.aborted})' if point.aborted
                                  else point.end_reason) + '; ramped from a late command')
            self.holding, self.trim_collective = True, float(last[0])
            return self._inputs(t, at_s)
        return (list(u), phase, point.stirring_phase(t), point.stirring_rate(t))

    def _phase_began(self, phase, t, applies, ramp):
        """
        Return when ``phase``, first commanded at ``applies``, began (ns): at most ``applies``.

        A test point's phases begin at its schedule's boundaries (azimuth, back to the node
        clock with the test point's Ω), the stop ramp's at its start and end; the first TRIM
        of a test point at its start (:meth:`_start_stamp`, which may precede the command
        before). Else not later than the first command of the phase, not earlier than the
        command before it.
        """
        began = applies
        point = self.test_point
        if ramp is not None:
            began = ramp.start_ns + (int(ramp.duration_s * NS) if phase == PHASE_DONE else 0)
        elif phase == PHASE_TRIM and self.start_stamp is not None:
            began, self.start_stamp = self.start_stamp, None
            return int(min(applies, began))
        elif point is not None and t is not None:
            boundary = {PHASE_CYCLIC_STEP: point.schedule.t_step,
                        PHASE_STIRRING: point.schedule.t0, PHASE_RAMP_DOWN: point.t_ramp,
                        PHASE_DONE: point.t_done}.get(phase)
            if boundary is not None:
                began = applies - int((t - boundary) / point.omega_rad_s * NS)
        earliest = self.previous_stamp if self.previous_stamp is not None else began
        return int(min(applies, max(began, earliest)))

    def command(self, applies, at_s):
        """Publish the pitch command, and every n-th StirringCommand, for time ``applies``."""
        t = float(self.azimuth.t_at([applies])[0]) if self.azimuth.ready else None
        ramp = self.ramp
        u, phase, phi, rate = self._inputs(t, at_s)
        if phase == PHASE_DONE and self.test_point is not None and not self.holding:
            self.holding = True           # the test point ended by itself: hold its trim
            self.trim_collective = float(u[0])
        pitch = blade_pitch_from_multiblade([0.0 if t is None else t], [u],
                                            len(self.joints))[0]
        self.pub_command.publish(joint_state(applies, self.joints, pitch,
                                             frame_id=self.d['frame_id']))
        self.published += 1
        self.previous_stamp = self.last_stamp
        self.last_stamp, self.last_u = applies, tuple(float(v) for v in u)
        if self.start_stamp is not None and phase != PHASE_TRIM:
            # a test point's first StirringCommand is TRIM, stamped with its start, whatever
            # phase its first command falls in: readers arm the test point on it
            self._publish_stirring(PHASE_TRIM, self.start_stamp,
                                   (self.trim_collective, 0.0, 0.0), 0.0, 0.0)
            self.start_stamp, self.last_phase = None, PHASE_TRIM
        changed = phase != self.last_phase
        self.last_phase = phase
        if changed:
            self._phase_changed(phase, t, ramp)
        # none but phase changes while a start is pending: the schedule's first (TRIM) is
        # stamped with its start, and no message may carry a later stamp before it
        if not changed and (self.start_requested
                            or (self.published - 1) % self.d['stirring_every']):
            return
        # a phase change is stamped with the time the phase began (docs/actuator.md)
        self._publish_stirring(phase, self._phase_began(phase, t, applies, ramp) if changed
                               else applies, u, phi, rate)
        if t is not None:
            self.diagnostics.set_value('t', f'{t:.4f}')

    def _publish_stirring(self, phase, stamp, u, phi, rate):
        cmd = StirringCommand()
        cmd.header.stamp = time_msg(stamp)
        cmd.header.frame_id = self.d['frame_id']
        cmd.collective, cmd.cyclic_forward, cmd.cyclic_left = (float(v) for v in u)
        cmd.stirring_phase = float(phi)
        cmd.stirring_rate = float(rate)
        cmd.phase = phase
        self.pub_stirring.publish(cmd)

    def _phase_changed(self, phase, t, ramp=None):
        self.diagnostics.set_value('state', PHASE_NAMES[phase])
        self.diagnostics.set_value('test_point', self.test_points)
        point = self.test_point
        if point is None or phase != PHASE_DONE:
            return
        why = (f'stopped ({ramp.reason})' if ramp is not None else
               f'aborted ({point.aborted})' if point.aborted else point.end_reason)
        self.diagnostics.set_value('last_end', why)
        self.diagnostics.idle = True
        at = '' if t is None else f' at t = {t:.4g}'
        self.get_logger().info(f'test point {self.test_points} done{at}: {why}; holding trim')

    # -------------------------------------------------------------------------- stopping
    def ramp_to_trim(self, reason):
        """
        Ramp the cyclic to trim now, on the steady clock, publish trim and flush it.

        Runs in the caller's thread (a transition, or close() after the executor stopped):
        commands at ``rate_hz`` stamped with the node clock, the cyclic shrinking linearly
        over ``stop_ramp_s`` from what was last commanded (the azimuth only extrapolated,
        never waited for), then trim for FINAL_HOLD_S; then reliable readers get up to
        FINAL_FLUSH_S to acknowledge it. Bound: ``stop_ramp_s`` + FINAL_HOLD_S + one command
        period + FINAL_FLUSH_S.
        Nothing happens unless the node is commanding (active).
        """
        if not self.commanding or self.pub_command is None:
            return
        period_s = 1.0 / self.d['rate_hz']
        lead_ns = int(self.d['lead_s'] * NS)
        try:
            if self.ramp is None:
                self._begin_ramp(reason)
            self.get_logger().info(f'{reason}: ramping the cyclic to trim within '
                                   f'{max(0.0, self.ramp.end_s - time.monotonic()):.3f} s')
            while self.ramp is not None:
                now = time.monotonic()
                self.command(self.get_clock().now().nanoseconds + lead_ns,
                             now + self.d['lead_s'])
                if self.ramp is not None:
                    time.sleep(max(0.0, min(period_s, self.ramp.end_s - now)))
            hold_until = time.monotonic() + FINAL_HOLD_S
            while True:
                self.command(self.get_clock().now().nanoseconds + lead_ns, time.monotonic())
                if time.monotonic() >= hold_until:
                    break
                time.sleep(period_s)
        except Exception as exc:              # noqa: B902 - trim must go out whatever failed
            self.get_logger().error(f'{type(exc).__name__} while ramping ({exc}): publishing '
                                    'trim directly')
            self.ramp = None
            collective = self.last_u[0] if self.last_u is not None else self.trim_collective
            self.pub_command.publish(joint_state(
                self.get_clock().now().nanoseconds + lead_ns, self.joints,
                [collective] * len(self.joints), frame_id=self.d['frame_id']))
            self.published += 1
        self.get_logger().info(f'at trim: final command sent, {self.published} in all')
        if not self.pub_command.wait_for_all_acked(Duration(nanoseconds=int(FINAL_FLUSH_S * NS))):
            self.get_logger().warning(
                f'a reliable reader of {self.pub_command.topic_name} had not acknowledged the '
                f'final trim within {FINAL_FLUSH_S:g} s (DDS may acknowledge only at its next '
                'heartbeat: delivered most likely, but not confirmed)')

    def close(self):
        """On exit (signal or exception): ramp to trim, publish and flush it, then report."""
        try:
            self.ramp_to_trim('stopping')
        finally:
            self.commanding = False
            print(f'stirring_input: published {self.published} pitch commands',
                  file=sys.stderr, flush=True)


def main(args=None):
    """Run the node until SIGINT/SIGTERM; it ends on trim (docs/actuator.md)."""
    return spin_node(StirringInput, args)


if __name__ == '__main__':
    raise SystemExit(main())
