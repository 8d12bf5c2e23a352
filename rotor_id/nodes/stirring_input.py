"""
stirring_input: the report's stirring schedule as per-blade pitch commands (``ros2 run``).

The schedule (:class:`rotor_id.physics.stirring.StirringSchedule`, Ch.2 eqs 1-5): collective only
(trim), then the lateral cyclic stepped on ``step_after_rad`` of azimuth after the test point
starts (one revolution, as in the recording convention of docs/run_description.md), then
stirring ``t0`` later with phase φ = ω̇ (t − t0)². It is bounded
(:class:`rotor_id.excitation.StirringTestPoint`): the stirring ends after ``duration_rad`` of
azimuth or when its rate reaches ``max_stirring_rate_rad_s``, the cyclic then ramps back to trim
over ``ramp_s`` and PHASE_DONE is published; ``~/abort`` (std_srvs/Trigger) starts that ramp at
once, ``~/start`` (std_srvs/Trigger) starts a new test point once the previous one is done
(``autostart``: the first one starts with the first azimuth sample). After a test point the node
holds trim (collective only), so that an actuator driver never sees its command stream stop.

Time is the report's nondimensional time: the unwrapped azimuth of blade 1 from the rig's
azimuth topic, extrapolated with Ω to each command's stamp: the time the command applies from,
on a regular grid that runs ``lead_s`` ahead of the clock (the plant interpolates between
commands). Commands whose time passed more than ``max_command_age_s`` ago (the node was
stalled) are skipped, never sent late. The rig (topics, joint names, blade count, azimuth
convention) is the run description's (parameter ``run_description``). Publishes JointState
(the blade_pitch joints, rad) on ``pitch_command`` and rotor_id_msgs/StirringCommand on
``stirring``.
"""

import math
import sys

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rotor_id.excitation import (check_excitation_limits, PHASE_DONE, PHASE_NAMES,
                                 StirringTestPoint)
from rotor_id.nodes.common import (allow_runtime_changes, declare, declare_rig, Diagnostics,
                                   joint_state, RESULT_QOS, SENSOR_QOS, spin_node, time_msg,
                                   wait_for_acks)
from rotor_id.nodes.live import AzimuthTracker, BadSample, check_azimuth_sample
from rotor_id.nodes.polling import checked_azimuth_batch, one_by_one, SensorPoller
from rotor_id.physics.stirring import blade_pitch_from_multiblade, StirringSchedule
from rotor_id_msgs.msg import StirringCommand
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

TWO_PI = 2.0 * math.pi
#: Time a pitch command may live after the time it applies from, s (QoS lifespan on top of lead_s).
COMMAND_LIFETIME_S = 0.1
#: Azimuth samples kept for the unwrapping and t_at (s): commands apply from at most
#: max_command_age_s ago, so older samples are never read.
AZIMUTH_KEPT_S = 2.0


def pitch_command_qos(lead_s, rate_hz):
    """
    Return the QoS of the pitch commands: no stale backlog can build up anywhere.

    Reliable, so a reader that is keeping up gets every command of the grid (the recorder
    too); KEEP_LAST with a depth of the commands of one lead (``lead_s`` × ``rate_hz`` + 1, 21
    by default, not 10000), so a reader that falls behind is re-sent at most that many, all of
    them current or ahead; and a lifespan of ``lead_s`` + 0.1 s, so that DDS drops from the
    writer's and the reader's queues any command whose time passed more than 0.1 s ago: a slow
    actuator driver is never fed a backlog of old commands. Best effort would also avoid the
    backlog but loses commands under load even when the reader keeps up.
    """
    return QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                      depth=int(math.ceil(lead_s * rate_hz)) + 1,
                      durability=DurabilityPolicy.VOLATILE,
                      lifespan=Duration(nanoseconds=int((lead_s + COMMAND_LIFETIME_S) * 1e9)))


class StirringInput(Node):
    """Publishes bounded stirring test points, locked to the measured rotor azimuth."""

    def __init__(self, **node_options):
        super().__init__('stirring_input', **node_options)
        self.rig = rig = declare_rig(self)
        spec = [
            # test-point settings: settable at run time, used by the next test point
            ('collective_rad', math.radians(2.0), 'collective pitch theta_0 (rad)', -0.5, 0.5,
             False),
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
             'abort (s)', 0.0, 60.0, False),
            # safety limits and structure: read-only
            ('max_amplitude_rad', math.radians(3.0), 'largest cyclic amplitude accepted (rad)',
             0.0, 0.5),
            ('max_stirring_rate_rad_s', 2.0 * math.pi * 30.0, 'the stirring ends when its rate '
             '|d phi/dt| reaches this (rad/s; default: 30 Hz, 2/rev at 900 rpm)', 1e-3, 1e5),
            ('autostart', True, 'start the first test point with the first azimuth sample '
             '(false: wait for ~/start)'),
            ('rate_hz', 200.0, 'pitch command rate (Hz); the plant interpolates between '
             'commands', 1.0, 10000.0),
            ('lead_s', 0.1, 'commands are published up to this far ahead of the clock, each '
             'stamped with the time it applies from (s)', 0.0, 5.0),
            ('publish_period_s', 0.02, 'publish the commands due up to lead_s ahead this often '
             '(s; at most lead_s / 2 and at least one command period is used): one wake-up per '
             'batch of commands, not per command', 1e-4, 1.0),
            ('max_command_age_s', COMMAND_LIFETIME_S, 'commands that would apply more than this '
             'long ago (the node was stalled) are skipped, never sent late (s)', 0.0, 1.0),
            ('stirring_every', 10, 'publish the StirringCommand every this many commands',
             1, 100000),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
        ]
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:5],
                                read_only=s[5] if len(s) > 5 else True) for s in spec}
        reason = self._limits_reason(self.d)
        if reason:
            raise ValueError(reason)
        allow_runtime_changes(self, lambda _name, _value, values: self._limits_reason(values))
        self.joints = rig.pitch_joints
        self.test_point = None           # StirringTestPoint of the current or last test point
        self.start_requested = self.d['autostart']
        self.next_ns = None              # stamp of the next command on the grid
        self.azimuth = AzimuthTracker()
        self.published = 0
        self.skipped = 0
        self.last_phase = None
        self.pub_command = self.create_publisher(
            JointState, rig.topics['pitch_command'],
            pitch_command_qos(self.d['lead_s'], self.d['rate_hz']))
        # what was commanded, for monitors, the identifier and the bag: latched
        self.pub_stirring = self.create_publisher(StirringCommand, rig.topics['stirring'],
                                                  RESULT_QOS)
        self.diagnostics = Diagnostics(self, 'stirring schedule')
        # the azimuth (1 kHz) is taken in batches at each tick (rotor_id.nodes.polling), not
        # by one executor callback per message: that was most of this node's CPU
        self.diagnostics.watch('azimuth', rig.topics['azimuth'])
        self.poller = SensorPoller(self, on_error=lambda exc: self.diagnostics.count(
            'sensor_batch_error', f'{type(exc).__name__}: {exc}'))
        self.poller.subscribe(JointState, rig.topics['azimuth'],
                              lambda raws, _infos: self.on_azimuth_batch(raws), SENSOR_QOS)
        self.create_service(Trigger, '~/start', self.on_start)
        self.create_service(Trigger, '~/abort', self.on_abort)
        self.create_timer(self.tick_period_s(self.d), self.tick)

    @staticmethod
    def tick_period_s(d):
        """Timer period: ``publish_period_s``, within [one command period, lead_s / 2]."""
        return min(d['publish_period_s'], max(1.0 / d['rate_hz'], 0.5 * d['lead_s']))

    @staticmethod
    def _limits_reason(values):
        return check_excitation_limits(values['amplitude_rad'], values['max_amplitude_rad'],
                                       values['duration_rad'],
                                       values['max_stirring_rate_rad_s'], values['ramp_s'])

    # -------------------------------------------------------------------------- services
    def on_start(self, _request, response):
        """Start a new test point (refused while one is running)."""
        if self.start_requested:
            response.success = False
            response.message = f'test point {self.test_points + 1} is about to start'
        elif self.test_point is not None and not self._done():
            response.success = False
            response.message = (f'test point {self.test_points} is still running '
                                f'({self._phase_name()}); abort it first')
        else:
            self.start_requested = True
            response.success = True
            response.message = (f'test point {self.test_points + 1} starts with the next pitch '
                                'command' + ('' if self.azimuth.ready else
                                             ' (once the azimuth arrives)'))
        return response

    def on_abort(self, _request, response):
        """Ramp the cyclic back to trim from the first command not yet sent."""
        if self.test_point is None or self._done():
            response.success = False
            response.message = 'no test point is running: nothing to abort'
            return response
        t = float(self.azimuth.t_at([self.next_ns])[0])
        changed = self.test_point.abort(t)
        response.success = True
        response.message = (f'test point {self.test_points}: '
                            + (f'aborted at t = {t:.4g}, cyclic back at trim by t = '
                               f'{self.test_point.t_done:.4g}' if changed else
                               'already ramping back to trim'))
        self.get_logger().warning(response.message)
        return response

    # -------------------------------------------------------------------------- schedule
    @property
    def test_points(self):
        """Return the number of test points started."""
        return getattr(self, '_test_points', 0)

    def _done(self):
        t = float(self.azimuth.t_at([self.next_ns])[0])
        return self.test_point.phase(t) == PHASE_DONE

    def _phase_name(self):
        t = float(self.azimuth.t_at([self.next_ns])[0])
        return PHASE_NAMES[self.test_point.phase(t)]

    def _start(self, t_start, omega):
        d = self.d
        step = t_start + d['step_after_rad']
        schedule = StirringSchedule(d['collective_rad'], d['amplitude_rad'], d['omegadot'],
                                    step + d['t0'], step)
        self.test_point = StirringTestPoint(schedule, omega, d['duration_rad'],
                                            d['max_stirring_rate_rad_s'], d['ramp_s'],
                                            d['max_amplitude_rad'])
        self._test_points = self.test_points + 1
        self.start_requested = False
        self.diagnostics.idle = False
        self.get_logger().info(
            f'test point {self.test_points}: cyclic step at t = {step:.4g}, stirring '
            f'({schedule.direction}) at t = {schedule.t0:.4g}, ends by t = '
            f'{self.test_point.t_end:.4g} ({self.test_point.end_reason}), trim again by '
            f't = {self.test_point.t_done:.4g}')

    def on_azimuth_batch(self, raws):
        """Track the unwrapped azimuth of blade 1 from a batch of serialized samples."""
        for _ in raws:
            self.diagnostics.received('azimuth')
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
                self._add_azimuth(stamp, psi, omega)
            return
        for stamp, psi, omega in zip(checked[0].tolist(), checked[1].tolist(),
                                     checked[2].tolist()):
            self._add_azimuth(stamp, psi, omega)

    def _add_azimuth(self, stamp, psi, omega):
        """Add an accepted sample (the nearest branch to what Ω predicts); start the grid."""
        self.azimuth.add(stamp, psi, omega, stamp - int(AZIMUTH_KEPT_S * 1e9))
        if self.next_ns is None:
            self.next_ns = stamp

    def tick(self):
        """
        Publish the commands due up to ``lead_s`` ahead, on a regular grid of stamps.

        The grid starts at the first azimuth stamp; commands whose time is more than
        ``max_command_age_s`` in the past (a stalled process) are skipped and counted, never sent
        late. A test point starts with the first command sent after it was asked for, so its
        first StirringCommand (PHASE_TRIM) is stamped with the schedule's start.
        """
        self.poller.poll()
        if self.next_ns is None:
            self.diagnostics.set_value('state', 'waiting for the azimuth')
            return
        now = self.get_clock().now().nanoseconds
        horizon = now + int(self.d['lead_s'] * 1e9)
        period = int(1e9 / self.d['rate_hz'])
        oldest = now - int(self.d['max_command_age_s'] * 1e9)
        if self.next_ns < oldest:
            late = (oldest - self.next_ns) // period + 1
            self.next_ns += late * period
            self.skipped += late
            self.diagnostics.set_value('commands_skipped_late', self.skipped)
        if self.start_requested:
            self._start(float(self.azimuth.t_at([self.next_ns])[0]), self.azimuth.omega)
        for _ in range(1000):
            if self.next_ns > horizon:
                break
            self.command(self.next_ns)
            self.next_ns += period
        self.diagnostics.set_value('commands_published', self.published)

    def command(self, applies):
        """Publish the pitch command, and every n-th StirringCommand, for time ``applies``."""
        t = float(self.azimuth.t_at([applies])[0])
        point = self.test_point
        if point is None:              # waiting for ~/start: hold trim
            u = [[self.d['collective_rad'], 0.0, 0.0]]
            phase, phi, rate = PHASE_DONE, 0.0, 0.0
        else:
            u = point.inputs([t])
            phase, phi, rate = point.phase(t), point.stirring_phase(t), point.stirring_rate(t)
        pitch = blade_pitch_from_multiblade([t], u, len(self.joints))[0]
        self.pub_command.publish(joint_state(applies, self.joints, pitch,
                                             frame_id=self.d['frame_id']))
        self.published += 1
        changed = phase != self.last_phase
        self.last_phase = phase
        if changed:
            self._phase_changed(phase, t)
        if (self.published - 1) % self.d['stirring_every'] and not changed:
            return
        cmd = StirringCommand()
        cmd.header.stamp = time_msg(applies)
        cmd.header.frame_id = self.d['frame_id']
        cmd.collective, cmd.cyclic_forward, cmd.cyclic_left = (float(v) for v in u[0])
        cmd.stirring_phase = phi
        cmd.stirring_rate = rate
        cmd.phase = phase
        self.pub_stirring.publish(cmd)
        self.diagnostics.set_value('t', f'{t:.4f}')

    def _phase_changed(self, phase, t):
        self.diagnostics.set_value('state', PHASE_NAMES[phase])
        self.diagnostics.set_value('test_point', self.test_points)
        point = self.test_point
        if point is None or phase != PHASE_DONE:
            return
        why = f'aborted ({point.aborted})' if point.aborted else point.end_reason
        self.diagnostics.set_value('last_end', why)
        self.diagnostics.idle = True
        self.get_logger().info(f'test point {self.test_points} done at t = {t:.4g}: {why}; '
                               'holding trim')

    def close(self):
        """Let reliable readers take what is in flight; print how many commands were sent."""
        wait_for_acks([self.pub_command, self.pub_stirring])
        print(f'stirring_input: published {self.published} pitch commands',
              file=sys.stderr, flush=True)


def main(args=None):
    """Run the node until SIGINT/SIGTERM."""
    return spin_node(StirringInput, args)


if __name__ == '__main__':
    raise SystemExit(main())
