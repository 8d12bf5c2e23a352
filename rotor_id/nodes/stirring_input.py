"""
stirring_input: the report's stirring schedule as per-blade pitch commands (``ros2 run``).

The schedule (:class:`rotor_id.physics.stirring.StirringSchedule`, Ch.2 eqs 1-5): collective only
(trim), then the lateral cyclic stepped on ``step_after_rad`` of azimuth after the first azimuth
sample (one revolution, as in ../shared/recordings/README.md), then stirring ``t0`` later with
phase φ = ω̇ (t − t0)². Time is the report's nondimensional time: the unwrapped azimuth of blade 1
from ``/rotor/azimuth``, extrapolated with Ω to each command's stamp: the time the command applies
from, on a regular grid that starts at the first azimuth stamp and runs ``lead_s`` ahead of the
clock (the plant interpolates between commands).
Publishes JointState blade_1..N (rad) on ``/rotor/pitch_command`` and
rotor_id_msgs/StirringCommand on ``/rotor/stirring``.
"""

import math
import sys

from rclpy.node import Node
from rotor_id.nodes.common import (declare, Diagnostics, joint_state, RESULT_QOS, SENSOR_OFFER_QOS,
                                   SENSOR_QOS, spin_node, stamp_ns, time_msg, wait_for_acks)
from rotor_id.nodes.live import AzimuthTracker, BadSample, check_azimuth_sample
from rotor_id.physics.stirring import blade_pitch_from_multiblade, StirringSchedule
from rotor_id_msgs.msg import StirringCommand
from sensor_msgs.msg import JointState

TWO_PI = 2.0 * math.pi


class StirringInput(Node):
    """Publishes the stirring transient, locked to the measured rotor azimuth."""

    def __init__(self):
        super().__init__('stirring_input')
        spec = [
            ('collective_rad', math.radians(2.0), 'collective pitch theta_0 (rad)', -0.5, 0.5),
            ('amplitude_rad', math.radians(1.5), 'cyclic amplitude (rad)', 0.0, 0.3),
            ('omegadot', -0.1 / math.pi, 'stirring acceleration: phase = omegadot (t - t0)^2, '
             't in rad of azimuth (per rad^2); negative = progressing, positive = regressing',
             -10.0, 10.0),
            ('t0', 70.0, 'stirring start after the cyclic step (rad of azimuth; report: 70 '
             'at mu = 0, 12 at mu = 0.4)', 0.0, 1e6),
            ('step_after_rad', TWO_PI, 'lateral cyclic step after the first azimuth sample '
             '(rad of azimuth)', 0.0, 1e6),
            ('rate_hz', 200.0, 'pitch command rate (Hz); the plant interpolates between '
             'commands', 1.0, 10000.0),
            ('lead_s', 0.1, 'commands are published up to this far ahead of the clock, each '
             'stamped with the time it applies from (s)', 0.0, 5.0),
            ('stirring_every', 10, 'publish the StirringCommand every this many commands',
             1, 100000),
            ('n_blades', 4, 'number of blades N', 1, 12),
            ('joint_names', [''], 'joint name of each blade (empty: blade_1..blade_N)'),
            ('azimuth_joint', 'rotor', 'joint name on the azimuth topic'),
            ('azimuth_topic', '/rotor/azimuth', 'azimuth and rotor speed topic (subscribed)'),
            ('pitch_command_topic', '/rotor/pitch_command', 'per-blade pitch command topic'),
            ('stirring_topic', '/rotor/stirring', 'StirringCommand topic'),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
        ]
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:]) for s in spec}
        d = self.d
        self.joints = list(d['joint_names'])
        if self.joints == ['']:
            self.joints = [f'blade_{k}' for k in range(1, d['n_blades'] + 1)]
        if len(self.joints) != d['n_blades']:
            raise ValueError(f'joint_names has {len(self.joints)} names for n_blades = '
                             f'{d["n_blades"]}')
        self.schedule = None
        self.next_ns = None              # stamp of the next command on the grid
        self.azimuth = AzimuthTracker()
        self.published = 0
        # commands are offered reliable (CONVENTIONS §4); the plant reads them best effort
        self.pub_command = self.create_publisher(JointState, d['pitch_command_topic'],
                                                 SENSOR_OFFER_QOS)
        # what was commanded, for monitors and the bag (no node acts on it): latched
        self.pub_stirring = self.create_publisher(StirringCommand, d['stirring_topic'],
                                                  RESULT_QOS)
        self.create_subscription(JointState, d['azimuth_topic'], self.on_azimuth, SENSOR_QOS)
        self.diagnostics = Diagnostics(self, 'stirring schedule')
        self.create_timer(1.0 / d['rate_hz'], self.tick)

    def on_azimuth(self, msg):
        """Track the unwrapped azimuth of blade 1 (nearest branch to what Ω predicts)."""
        stamp = stamp_ns(msg.header.stamp)
        try:
            psi, omega = check_azimuth_sample(msg.name, msg.position, msg.velocity,
                                              self.d['azimuth_joint'], stamp,
                                              self.azimuth.series.last_stamp)
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return
        self.azimuth.add(stamp, psi, omega)
        if self.schedule is None:
            self.next_ns = stamp
            step = psi + self.d['step_after_rad']
            self.schedule = StirringSchedule(self.d['collective_rad'], self.d['amplitude_rad'],
                                             self.d['omegadot'], step + self.d['t0'], step)
            self.get_logger().info(f'azimuth locked: cyclic step at t = {step:.4g}, stirring '
                                   f'({self.schedule.direction}) at t = {self.schedule.t0:.4g}')

    def tick(self):
        """
        Publish the commands due up to ``lead_s`` ahead, on a regular grid of stamps.

        The grid starts at the first azimuth stamp, so a late start or a stalled process still
        gives the rotor every command of the schedule (in a burst).
        """
        if self.schedule is None:
            self.diagnostics.set_value('state', 'waiting for the azimuth')
            return
        horizon = self.get_clock().now().nanoseconds + int(self.d['lead_s'] * 1e9)
        period = int(1e9 / self.d['rate_hz'])
        for _ in range(1000):
            if self.next_ns > horizon:
                break
            self.command(self.next_ns)
            self.next_ns += period
        self.diagnostics.set_value('commands_published', self.published)

    def command(self, applies):
        """Publish the pitch command, and every n-th StirringCommand, for time ``applies``."""
        t = float(self.azimuth.t_at([applies])[0])
        omega = self.azimuth.omega
        u = self.schedule.inputs([t])
        pitch = blade_pitch_from_multiblade([t], u, len(self.joints))[0]
        self.pub_command.publish(joint_state(applies, self.joints, pitch,
                                             frame_id=self.d['frame_id']))
        self.published += 1
        if (self.published - 1) % self.d['stirring_every']:
            return
        cmd = StirringCommand()
        cmd.header.stamp = time_msg(applies)
        cmd.header.frame_id = self.d['frame_id']
        cmd.collective, cmd.cyclic_forward, cmd.cyclic_left = (float(v) for v in u[0])
        cmd.stirring_phase = float(self.schedule.phase(t))
        cmd.stirring_rate = float(self.schedule.stirring_rate(t) * omega)
        cmd.phase = (StirringCommand.PHASE_TRIM if t < self.schedule.t_step
                     else StirringCommand.PHASE_CYCLIC_STEP if t <= self.schedule.t0
                     else StirringCommand.PHASE_STIRRING)
        self.pub_stirring.publish(cmd)
        self.diagnostics.set_value('state', ('trim', 'cyclic step', 'stirring')[cmd.phase])
        self.diagnostics.set_value('t', f'{t:.4f}')

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
