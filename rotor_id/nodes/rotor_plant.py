"""
rotor_plant: the simulated rotor of the test stand, in real time (``ros2 run rotor_id ...``).

The rig it simulates is the run description's (parameter ``run_description``, docs/
run_description.md): blade count and rotor constants, topics, joint names, azimuth convention.
Subscribes ``pitch_command`` (JointState, the blade_pitch joints, rad); publishes
``blade_pitch`` and ``blade_flap`` (JointState, rad, header.stamp = acquisition time) and
``azimuth`` (the azimuth joint: position = azimuth of blade 1, wrapped to [0, 2π) or
unwrapped as the description says; velocity = Ω in rad/s). The physics is
:class:`rotor_id.nodes.live.PlantStepper` (one library model, the library's simulator).
"""

import math

import numpy as np
from rclpy.node import Node
from rotor_id.io.jointstate_cdr import encode_rows
from rotor_id.nodes.common import (declare, declare_rig, Diagnostics, NS, PacedTicks,
                                   SENSOR_OFFER_QOS, SENSOR_QOS, spin_node, wait_for_acks)
from rotor_id.nodes.live import BadSample, check_joint_sample, PlantStepper, rotor_constants
from rotor_id.nodes.polling import one_by_one, SensorPoller
from rotor_id.physics.models import MODEL_NAMES
from rotor_id.physics.stirring import multiblade_from_blade_pitch
from sensor_msgs.msg import JointState

TWO_PI = 2.0 * math.pi
#: With wait_for_commands and no command yet: one more free sample this often (s), so that a
#: stirring node that matched after the last one, or lost it (best effort on a loaded
#: machine), locks onto the next instead of both waiting for each other for ever.
LOCK_ON_PERIOD_S = 0.25


class RotorPlant(Node):
    """Simulated rotor: pitch commands in, measured pitch, flap and azimuth out."""

    def __init__(self, **node_options):
        super().__init__('rotor_plant', **node_options)
        self.rig = rig = declare_rig(self)
        d = self._declare_all()
        spec = rig.description.rotor
        self.rotor = rotor_constants(spec.blades, spec.advance_ratio, spec.flap_frequency,
                                     spec.tip_loss, spec.pitch_flap_coupling)
        self.omega = d['rotor_speed_rad_s']
        self.rate = d['sample_rate_hz']
        noisy = [s for s in d['process_noise_states'] if s]
        self.stepper = PlantStepper(
            d['model'], self.rotor,
            {k: d[k] for k in ('A', 'AL_over_tau', 'inv_tau', 'AL0_over_tau0', 'inv_tau0',
                               'gamma')},
            self.omega, self.rate, d['initial_collective_rad'], d['flap_noise_std_rad'],
            d['pitch_noise_std_rad'], d['process_noise_std'], noisy or None, d['seed'],
            t_start=d['initial_azimuth_rad'], inflow=d['inflow'])
        self.d = d
        self.start_ns = None
        self.ready_ns = None
        self.last_cmd_ns = None
        self.commands = 0
        self.published = 0              # samples published
        self.offered_ns = None          # when the last free sample (no command yet) was due
        blades = rig.description.rotor.blades
        self.pending = (np.empty(0), np.empty((0, blades)), np.empty((0, blades)))
        self.ahead = int(round(d['simulate_ahead_s'] * self.rate))
        offer = SENSOR_OFFER_QOS if d['reliable_sensors'] else SENSOR_QOS
        topics = rig.topics
        self.pub_pitch = self.create_publisher(JointState, topics['blade_pitch'], offer)
        self.pub_flap = self.create_publisher(JointState, topics['blade_flap'], offer)
        self.pub_azimuth = self.create_publisher(JointState, topics['azimuth'], offer)
        self.diagnostics = Diagnostics(self, 'simulated rotor')
        # the commands are taken at each tick, before simulating (rotor_id.nodes.polling): one
        # executor wake-up per tick instead of one more per command
        self.diagnostics.watch('pitch_command', topics['pitch_command'])
        self.poller = SensorPoller(self, on_error=lambda exc: self.diagnostics.count(
            'sensor_batch_error', f'{type(exc).__name__}: {exc}'))
        self.poller.subscribe(JointState, topics['pitch_command'],
                              lambda raws, _infos: self.on_commands(raws), SENSOR_QOS)
        # ticks paced by a thread of their own, not an executor timer: the executor's
        # wake-up per tick (wait set rebuilt in Python) was a third of this node's main thread
        self.ticks = PacedTicks(self, d['publish_period_s'], self.tick, 'plant-ticks')
        self.get_logger().info(
            f'{d["model"]} rotor at {self.omega:.4g} rad/s, {self.rate:g} Hz, flap noise '
            f'{d["flap_noise_std_rad"]:.3g} rad; waiting for {d["wait_for_subscribers"]} '
            f'subscriber(s) of {self.pub_azimuth.topic_name}')

    def _declare_all(self):
        two_deg = math.radians(2.0)
        spec = [
            ('model', 'multiblade_wake', f'truth model: {", ".join(MODEL_NAMES)}'),
            ('inflow', 'cyclic', 'wake model inflow: cyclic (report) | three_state'),
            ('A', 0.5, 'wake model: flap damping A = gamma B^4/8 (-), Ch.2 eq. 27', 1e-3, 10.0),
            ('AL_over_tau', 0.25, 'wake model: wake gain over time constant AL/tau (-)',
             0.0, 50.0),
            ('inv_tau', 0.125, 'wake model: inverse wake time constant 1/tau (-)', 1e-4, 50.0),
            ('AL0_over_tau0', 0.25, 'three-state inflow: uniform gain over time constant (-)',
             0.0, 50.0),
            ('inv_tau0', 0.125, 'three-state inflow: inverse uniform time constant (-)',
             1e-4, 50.0),
            ('gamma', 5.0, 'blade Lock number gamma (-) of the other models', 0.05, 50.0),
            ('rotor_speed_rad_s', 2.0 * math.pi * 15.0, 'rotor speed Omega (rad/s)',
             1.0, 1000.0),
            ('sample_rate_hz', 1000.0, 'sensor sample rate (Hz)', 10.0, 20000.0),
            ('initial_collective_rad', two_deg, 'collective pitch of the trim before the '
             'first command (rad)', -0.5, 0.5),
            ('initial_azimuth_rad', 0.0, 'azimuth of blade 1 at the first sample (rad)',
             0.0, TWO_PI),
            ('flap_noise_std_rad', math.radians(0.05), 'flap sensor noise sigma (rad)',
             0.0, 0.1),
            ('pitch_noise_std_rad', math.radians(0.005), 'pitch sensor noise sigma (rad)',
             0.0, 0.1),
            ('process_noise_std', 0.0, 'system noise intensity q (rad per sqrt unit of '
             'nondimensional time), report eq. 29a', 0.0, 1.0),
            ('process_noise_states', [''], 'states driven by system noise (empty: lambda_I, '
             'lambda_II for the wake model, the flap rates otherwise)'),
            ('seed', 0, 'random seed of the noise', 0, 2**31 - 1),
            ('command_latency_s', 0.02, 'simulate this far behind the clock, so that the pitch '
             'commands for a sample have arrived when it is computed (s; the samples keep '
             'their acquisition stamps)', 0.0, 1.0),
            ('wait_for_commands', True, 'never simulate past the newest pitch command (a '
             'simulated rotor on a busy machine then stays on schedule; samples keep their '
             'stamps); false: hold the last command'),
            ('publish_period_s', 0.005, 'period of the simulation/publishing timer (s)',
             0.0005, 0.1),
            ('simulate_ahead_s', 0.02, 'with wait_for_commands, simulate up to this far past '
             'the samples due (never past the newest command; published when due): one '
             'simulation call per this long, not per tick (s)', 0.0, 1.0),
            ('max_batch', 50, 'most samples simulated per timer tick', 1, 100000),
            ('wait_for_subscribers', 0, 'start the rotor once this many subscribers of the '
             'azimuth topic are matched (0: at once)', 0, 100),
            ('start_delay_s', 1.0, 'then wait this long, so they are all spinning (s)',
             0.0, 60.0),
            ('duration_s', 0.0, 'stop publishing after this much rotor time (s of samples); 0: '
             'run until stopped',
             0.0, 1e6),
            ('max_abs_pitch_rad', 0.7, 'larger |pitch command| is rejected as degrees (rad)',
             0.01, 3.2),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
            ('reliable_sensors', True, 'offer the sensor topics RELIABLE (KEEP_LAST 10000) so a '
             'recorder can take every sample (best-effort readers match either way); false: '
             'best effort, like most sensor drivers'),
        ]
        return {item[0]: declare(self, item[0], item[1], item[2], *item[3:]) for item in spec}

    def t_at(self, ns):
        """Nondimensional time (azimuth of blade 1, unwrapped) at ROS time ``ns``."""
        return self.d['initial_azimuth_rad'] + self.omega * (ns - self.start_ns) / NS

    def on_commands(self, raws):
        """Take a batch of serialized pitch commands, in order (each as :meth:`on_command`)."""
        for _ in raws:
            self.diagnostics.received('pitch_command')
        for stamp, names, position, _velocity in one_by_one(raws, self.diagnostics):
            self.on_command(stamp, names, position)

    def on_command(self, stamp, names, position):
        """Hold a per-blade pitch command, converted to the swashplate input (eq. 3)."""
        try:
            pitch = check_joint_sample(names, position, self.rig.pitch_joints, stamp,
                                       self.last_cmd_ns, self.d['max_abs_pitch_rad'])
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return
        self.last_cmd_ns = stamp
        if self.start_ns is None:
            return
        t_cmd = self.t_at(stamp)
        self.stepper.command(t_cmd, multiblade_from_blade_pitch([t_cmd], pitch[None, :])[0])
        self.commands += 1

    def tick(self):
        """Take the commands that arrived, advance the simulation to now, publish the samples."""
        self.poller.poll()
        now = self.get_clock().now().nanoseconds
        if self.start_ns is None:
            if self.ready_ns is None:
                if self.pub_azimuth.get_subscription_count() < \
                        self.d['wait_for_subscribers']:
                    return
                self.ready_ns = now
            if now - self.ready_ns < self.d['start_delay_s'] * NS:
                return
            self.start_ns = now
            self.get_logger().info('rotor started (trim at collective only)')
            return
        elapsed = (now - self.start_ns) / NS - self.d['command_latency_s']
        if self.d['duration_s'] > 0 and self.published >= self.d['duration_s'] * self.rate:
            if not self.ticks.stopping.is_set():
                self.ticks.stop()
                self.diagnostics.idle = True          # finished by design: quiet is STALE
                self.get_logger().info(f'run complete: {self.published} samples')
            return
        due = int(elapsed * self.rate)
        simulate_to = due
        if self.d['wait_for_commands']:
            # a free sample now and then until the first command (the stirring node locks onto
            # the first it receives), then follow the commands
            if self.commands:
                commanded = max(1, int((self.stepper.cmd_t[-1] - self.d['initial_azimuth_rad'])
                                       / self.stepper.step + 1e-9))
            elif due > self.published and (self.offered_ns is None or
                                           now - self.offered_ns >= LOCK_ON_PERIOD_S * NS):
                self.offered_ns = now
                commanded = self.published + 1
            else:
                commanded = self.published
            due = min(due, commanded)
            self.diagnostics.set_value('waiting_for_commands', due < int(elapsed * self.rate))
            # the samples up to the newest command do not depend on when they are computed:
            # simulated ahead, they cost one simulation call per simulate_ahead_s, not per tick
            simulate_to = max(due, min(due + self.ahead, commanded))
        if due - self.published <= 0:
            return
        if self.stepper.samples < due:
            # a bounded batch per tick, so the commands are taken in between while catching up
            self._simulate(min(simulate_to - self.stepper.samples, self.d['max_batch']))
        self._publish(min(due - self.published, self.d['max_batch'], self.pending[0].size))
        self.diagnostics.set_value('samples_published', self.published)
        self.diagnostics.set_value('commands_received', self.commands)

    def _simulate(self, n):
        """Simulate the next ``n`` samples into the ones waiting to be published."""
        t, flap, pitch = self.stepper.advance(n)
        self.pending = tuple(np.concatenate([old, new]) for old, new in
                             zip(self.pending, (t, flap, pitch)))

    def _publish(self, n):
        """Publish the next ``n`` simulated samples, stamped on the sample grid."""
        t, flap, pitch = (v[:n] for v in self.pending)
        self.pending = tuple(v[n:] for v in self.pending)
        first = self.published + 1
        self.published += n
        psi = self.rig.azimuth_position(t)
        frame, rig = self.d['frame_id'], self.rig
        stamps = self.start_ns + np.round((first + np.arange(n)) * NS
                                          / self.rate).astype(np.int64)
        # serialized once per batch with numpy (the bytes rclpy would send for the same
        # JointState), published as CDR: no message object and conversion per sample
        pitch_rows = encode_rows(stamps, rig.pitch_joints, pitch, frame_id=frame)
        flap_rows = encode_rows(stamps, rig.flap_joints, flap, frame_id=frame)
        azimuth_rows = encode_rows(stamps, [rig.azimuth_joint], psi[:, None],
                                   np.full((n, 1), self.omega), frame_id=frame)
        for i in range(n):
            self.pub_pitch.publish(pitch_rows[i].tobytes())
            self.pub_flap.publish(flap_rows[i].tobytes())
            self.pub_azimuth.publish(azimuth_rows[i].tobytes())

    def close(self):
        """Stop the ticks; let reliable readers (a recorder) take the samples in flight."""
        self.ticks.stop()
        wait_for_acks([self.pub_pitch, self.pub_flap, self.pub_azimuth])


def main(args=None):
    """Run the node until SIGINT/SIGTERM."""
    return spin_node(RotorPlant, args)


if __name__ == '__main__':
    raise SystemExit(main())
