"""
state_estimator: Kalman reconstruction of the unmeasured states (``ros2 run rotor_id ...``).

Filters the flap stream with the run description's model (flap rates, and the inflow λI, λII of
the wake model, which no sensor measures) using the library's Kalman filter through
:class:`rotor_id.nodes.live.StreamingKalman`, and publishes rotor_id_msgs/StateEstimate with its
covariance on ``rotor_id/state`` (angles in rad, rates in rad/s: the model's d/dt of azimuth
times Ω). It takes the identifier's ParameterEstimate on ``rotor_id/estimate`` as its new
model parameters: the report's iterated filter / identification loop (Ch.2). Topics, joint
names and the azimuth convention are the run description's (docs/run_description.md).
"""

import math
import sys

import numpy as np
from rclpy.node import Node
from rotor_id.estimation import kernels
from rotor_id.nodes.common import (allow_runtime_changes, declare, Diagnostics,
                                   estimate_from_message, node_run_description, RESULT_QOS,
                                   Rig, SENSOR_BUFFER_QOS, spin_node, stamp_ns, STATE_QOS,
                                   wait_for_acks)
from rotor_id.nodes.live import (AzimuthTracker, BadSample, check_azimuth_sample,
                                 check_joint_sample, StampedSeries, StreamingKalman)
from rotor_id.nodes.polling import (checked_azimuth_batch, checked_joint_batch, one_by_one,
                                    SensorPoller)
from rotor_id.nodes.test_points import sampling_period_ns
from rotor_id.physics.stirring import SampledInput
from rotor_id.pipeline import channel_noise, model_for
from rotor_id_msgs.msg import ParameterEstimate, StateEstimate
from sensor_msgs.msg import JointState


#: Larger |flap| or |pitch| is refused as degrees (rad).
MAX_ABS_ANGLE_RAD = 0.7


class StateEstimator(Node):
    """Kalman filter on the live flap stream, re-parameterised by the identifier."""

    def __init__(self, **node_options):
        super().__init__('state_estimator', **node_options)
        spec = [
            ('run_description', '', 'run-description YAML: rotor, model and topics'),
            ('flap_noise_std_rad', math.radians(0.05), 'flap sensor noise sigma (rad)',
             1e-7, 0.1),
            ('process_noise_std', 0.01, 'system-noise intensity sqrt(q) on the inflow rows '
             '(wake) or flap-rate rows (rad per sqrt unit of azimuth)', 0.0, 10.0),
            ('initial_std_rad', 0.02, 'prior sigma of every state at the first sample (rad)',
             1e-6, 1.0),
            ('update_period_s', 0.02, 'filter the new samples and publish the state this often '
             '(s)', 0.001, 1.0),
            ('buffer_s', 2.0, 'samples kept for filtering (s): the buffers never grow with the '
             'run; samples not filtered within this time are dropped and counted', 0.1, 600.0),
            ('use_provisional', False, 'also adopt provisional (growing-window) estimates'),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
        ]
        # settable at run time (ranges checked by their descriptors): used when the filter
        # (re)starts, use_provisional at the next estimate
        tunable = ('flap_noise_std_rad', 'process_noise_std', 'initial_std_rad',
                   'use_provisional')
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:], read_only=s[0] not in tunable)
                  for s in spec}
        self.rig = Rig(node_run_description(self.d['run_description']))
        desc = self.rig.description
        self.model = model_for(desc)
        self.p = self.model.nominal()
        self.noise = channel_noise(self.model, self.d['flap_noise_std_rad'])
        allow_runtime_changes(self, apply=lambda names: setattr(
            self, 'noise', channel_noise(self.model, self.d['flap_noise_std_rad'])))
        n = desc.rotor.blades
        self.flap_joints, self.pitch_joints = self.rig.flap_joints, self.rig.pitch_joints
        self.flap = StampedSeries(n)
        self.pitch = StampedSeries(n)
        self.azimuth = AzimuthTracker()
        self.done_ns = None                # stamp of the last flap sample filtered
        self.filtered = 0                  # flap samples filtered so far
        self.kalman = None
        self.updates = 0
        self.published = 0
        # volatile, as robot_localization's state: a late reader starts from the next state
        self.pub_state = self.create_publisher(StateEstimate, self.rig.topics['state'],
                                               STATE_QOS)
        self.diagnostics = Diagnostics(self, 'state reconstruction')
        # the sensor topics are taken in batches at each tick (rotor_id.nodes.polling), not by
        # one executor callback per message (several times the CPU per message at 3 kHz;
        # bench/results/sensor_intake.md)
        self.poller = SensorPoller(self, on_error=lambda exc: self.diagnostics.count(
            'sensor_batch_error', f'{type(exc).__name__}: {exc}'))
        for role, series, joints in (('blade_flap', self.flap, self.flap_joints),
                                     ('blade_pitch', self.pitch, self.pitch_joints),
                                     ('azimuth', None, None)):
            self.diagnostics.watch(role, desc.topics[role])
            self.poller.subscribe(
                JointState, desc.topics[role],
                lambda raws, _infos, role=role, series=series, joints=joints:
                self._take_batch(role, series, joints, raws), SENSOR_BUFFER_QOS)
        # transient local: a restarted state estimator takes the identifier's latched estimates
        self.create_subscription(ParameterEstimate, self.rig.topics['estimate'],
                                 self.on_estimate, RESULT_QOS)
        # the compiled filter scan now (0.4-1 s from numba's cache), not mid-run: each batch
        # is then one call instead of numpy per sample (bench/state_estimator_cpu.py)
        kernels.prefer()
        self.create_timer(self.d['update_period_s'], self.tick)

    def _take_batch(self, role, series, joints, raws):
        """Check and buffer a batch of serialized samples of one sensor topic."""
        self.diagnostics.received(role, len(raws))
        if role == 'azimuth':
            checked = checked_azimuth_batch(raws, self.rig.azimuth_joint,
                                            self.azimuth.series.last_stamp,
                                            self.rig.azimuth_convention)
        else:
            checked = checked_joint_batch(raws, joints, series.last_stamp, MAX_ABS_ANGLE_RAD)
        if checked is None:               # one at a time: each refusal with its reason
            for stamp, names, position, velocity in one_by_one(raws, self.diagnostics):
                if role == 'azimuth':
                    self._take_azimuth(stamp, names, position, velocity)
                else:
                    self._take_joint(series, joints, stamp, names, position)
        elif not checked[0].size:
            return
        elif role == 'azimuth':         # whole batches: no Python per sample but the unwrapping
            self.azimuth.add_batch(*checked, self._keep_from(int(checked[0][0])))
        else:
            series.extend(checked[0], checked[1], self._keep_from(int(checked[0][0])))

    def _take_joint(self, series, joints, stamp, names, position):
        try:
            values = check_joint_sample(names, position, joints, stamp, series.last_stamp,
                                        MAX_ABS_ANGLE_RAD, extra_joints=True)
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return
        series.append(stamp, values, self._keep_from(stamp))

    def _take_azimuth(self, stamp, names, position, velocity):
        try:
            psi, omega = check_azimuth_sample(names, position, velocity, self.rig.azimuth_joint,
                                              stamp, self.azimuth.series.last_stamp,
                                              self.rig.azimuth_convention)
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return
        self.azimuth.add(stamp, psi, omega, self._keep_from(stamp))

    def _joint_callback(self, series, joints):
        """Take one flap or pitch JointState message (what a batch does per message)."""
        def callback(msg):
            self._take_joint(series, joints, stamp_ns(msg.header.stamp), msg.name,
                             msg.position)
        return callback

    def on_azimuth(self, msg):
        """Track the unwrapped azimuth (the model's time) from one message."""
        self._take_azimuth(stamp_ns(msg.header.stamp), msg.name, msg.position, msg.velocity)

    def _keep_from(self, stamp):
        """Oldest stamp the buffers keep: ``buffer_s`` before the newest sample."""
        return stamp - int(self.d['buffer_s'] * 1e9)

    def on_estimate(self, msg):
        """
        Adopt the identifier's parameters: a test point's result, or provisional if asked to.

        Never from an incomplete window, a failed fit or an aborted test point.
        """
        adopt = (ParameterEstimate.STATUS_CONVERGED, ParameterEstimate.STATUS_MAX_ITERATIONS)
        if self.d['use_provisional']:
            adopt += (ParameterEstimate.STATUS_ITERATING,)
        if msg.status not in adopt:
            return
        names, values, _, _ = estimate_from_message(msg)
        if not np.all(np.isfinite(values)):
            self.diagnostics.count('non_finite', 'estimate with non-finite values')
            return
        for name, value in zip(names, values):
            if name in self.model.parameter_names:
                self.p[self.model.parameter_names.index(name)] = value
        if self.kalman is not None:
            self.kalman.p = self.p.copy()
        self.updates += 1
        self.diagnostics.set_value('parameters', ', '.join(
            f'{n}={v:.4g}' for n, v in zip(self.model.parameter_names, self.p)))
        self.diagnostics.set_value('parameter_updates', self.updates)

    def tick(self):
        """Take the new samples; filter those pitch and azimuth cover; publish the last state."""
        self.poller.poll()
        if not self.azimuth.ready or self.pitch.size < 2:
            return
        limit = min(self.pitch.last_stamp, self.azimuth.series.last_stamp)
        end = int(np.searchsorted(self.flap.stamps, limit, side='right'))
        start = (0 if self.done_ns is None else
                 int(np.searchsorted(self.flap.stamps, self.done_ns, side='right')))
        if end <= start:
            return
        stamps = self.flap.stamps[start:end]
        t = self.azimuth.t_at(stamps)
        first = max(0, int(np.searchsorted(self.pitch.stamps, stamps[0])) - 20)
        t_pitch = self.azimuth.t_at(self.pitch.stamps[first:])
        keep = np.concatenate([[True], np.diff(t_pitch) > 0])
        inputs = SampledInput.from_blade_pitch(t_pitch[keep], self.pitch.values[first:][keep])
        y = self.model.observe_blades(t, self.flap.values[start:end])
        # (the median step only when samples after the last filtered one may be gone)
        if (self.done_ns is not None and self.flap.first_stamp > self.done_ns
                and (self.flap.first_stamp - self.done_ns >
                     1.5 * sampling_period_ns(self.flap.stamps))):
            self.diagnostics.count('dropped_unfiltered', 'flap samples older than buffer_s '
                                   'were dropped before they were filtered')
        self.done_ns = int(stamps[-1])
        self.filtered += end - start
        try:
            if self.kalman is None:
                self._start(t[0], inputs)
            x, P = self.kalman.advance(t, inputs, y)
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
                raise FloatingPointError('non-finite state or covariance')
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            # count, report, and start the filter afresh from the next samples
            self.diagnostics.count('filter_restarts', f'{type(exc).__name__}: {exc}')
            self.kalman = None
            return
        self._publish(int(stamps[-1]), t[-1], x, P)

    def _start(self, t0, inputs):
        names = self.model.parameter_names
        if 'theta0' in names:
            self.p[names.index('theta0')] = float(inputs([t0])[0, 0])
        n = self.model.n_states
        x0 = (self.model.equilibrium([t0], self.p, inputs([t0])) if self.model.time_invariant
              else np.zeros(n))
        P0 = np.eye(n) * self.d['initial_std_rad']**2
        self.kalman = StreamingKalman(self.model, self.p.copy(), self.noise, x0, P0,
                                      self.d['process_noise_std'])

    def _publish(self, stamp, t, x, P):
        omega = self.azimuth.omega
        rates = [s.endswith('_dot') for s in self.model.state_names]
        rate = np.where(rates, omega, 1.0)
        msg = StateEstimate()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.header.frame_id = self.d['frame_id']
        msg.names = list(self.model.state_names)
        msg.units = ['rad/s' if r else 'rad' for r in rates]
        msg.values = (x * rate).tolist()
        msg.covariance = (P * np.outer(rate, rate)).ravel().tolist()
        msg.azimuth = float(math.fmod(t, 2.0 * math.pi))
        msg.rotor_speed = float(omega)
        self.pub_state.publish(msg)
        self.published += 1
        self.diagnostics.set_value('samples_filtered', self.filtered)

    def close(self):
        """Let reliable readers take what is in flight; print how many states were sent."""
        wait_for_acks([self.pub_state])
        print(f'state_estimator: published {self.published} state estimates',
              file=sys.stderr, flush=True)


def main(args=None):
    """Run the node until SIGINT/SIGTERM."""
    return spin_node(StateEstimator, args)


if __name__ == '__main__':
    raise SystemExit(main())
