"""
identifier: live output-error identification of the rotor (``ros2 run rotor_id identifier``).

Runs test points one after another without restart. The test points, their buffers and the
window checks are :class:`rotor_id.nodes.test_points.TestPointSequence` (ROS-free); this node
only feeds it the checked samples of the rig's blade_pitch, blade_flap and azimuth topics and
the phase of the stirring schedule, and publishes what it returns. The rig (topics, joint names,
blade count, azimuth convention) is the run description's (``run_description``,
docs/run_description.md), as for every node and ``rotor-id identify``.

* A test point starts by the service ``~/start_test_point`` (std_srvs/Trigger: from the next
  flap sample; the answer names the test point) or, with ``auto_start: excitation``, when a
  stirring schedule starts (rotor_id_msgs/StirringCommand PHASE_TRIM after any other phase:
  from that command's stamp). ``~/abort`` (Trigger) aborts the test point in progress.
  ``window_s`` (the run description's unless the parameter is given) counts from the test
  point's first flap sample; set at run time (``ros2 param set``), it applies from the next test
  point armed: a window in progress is never changed (the answer and /diagnostics say so).
* While its window fills, growing-window fits every ``update_every_rad`` of azimuth and back to
  back in its last ``refit_tail_rad`` (KIND_PROVISIONAL, STATUS_ITERATING); once every stream
  covers the window, the final fit (KIND_FINAL: CONVERGED / MAX_ITERATIONS / FAILED) starting
  from the latest growing-window iterate; an aborted test point ends with STATUS_ABORTED.
* A window that misses samples in any channel (its start and end included) or whose azimuth
  slips against the rotor speed is published with STATUS_INCOMPLETE and the channels and
  counts missing: never as converged. ``window_start``/``window_end`` are the first and last
  flap samples used.
* The ``~/identify`` service (rotor_id_msgs/srv/Identify) fits any buffered window (KIND_ON_DEMAND,
  seconds after the latest test point's first flap sample).
* Each window's sensor values get the bag reader's checks (the same functions,
  :meth:`rotor_id.io.record.Record.repair_value_spikes` / ``stuck_flap_blades``): flap/pitch
  spikes are replaced by interpolation before the fit (``value_spikes_repaired`` on
  /diagnostics, logged once per test point, named in the estimate's message); a blade whose flap
  reads one exact value over the window (a dead sensor) fails the fit: STATUS_FAILED naming it,
  ERROR ``dead_flap_sensor`` on /diagnostics.

Each estimate carries the Cramér-Rao covariance and the data-length verdict of Ch.3
(target_met, additional_data_s for the targets ``target_std``); every Gauss-Newton iteration is
published on ``/rotor_id/progress``. Fits run in a separate process (or a worker thread), so
the subscriptions keep up. The sensor topics are taken in batches by a polling thread
(:mod:`rotor_id.nodes.polling`: every ``sensor_poll_period_s``, every ``sensor_poll_fast_s`` in a
window's last 10 ms), decoded and checked with numpy: less than half the CPU per message of
one executor callback each (bench/results/sensor_intake.md); with the per-sample checks the
callbacks took half a core at 1 kHz x 3 topics, and the fits waited for that core.
"""

import collections
from dataclasses import replace
import json
import math
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rotor_id.estimation.output_error import STOP
from rotor_id.nodes.common import (allow_runtime_changes, declare, Diagnostics,
                                   estimate_message, node_run_description,
                                   NS, progress_message, RESULT_QOS, Rig, SENSOR_BUFFER_QOS,
                                   spin_node, stamp_ns, STATE_QOS, time_msg, wait_for_acks)
from rotor_id.nodes.fit_process import (Abandoned, fit_window, FitOptions, FitProcess,
                                        thread_times, warm_up)
from rotor_id.nodes.live import BadSample, check_azimuth_sample, check_joint_sample
from rotor_id.nodes.polling import (checked_azimuth_batch, checked_joint_batch,
                                    incompatible_publishers, one_by_one, SensorPoller)
from rotor_id.nodes.test_points import (FitSchedule, outcome, Phase, sampling_period_ns,
                                        TestPointSequence, window_bounds)
from rotor_id.pipeline import adequacy_of, model_for
from rotor_id_msgs.msg import IdentificationProgress, ParameterEstimate, StirringCommand
from rotor_id_msgs.srv import Identify
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

#: What a final fit's outcome (rotor_id.nodes.test_points.outcome) is published as.
FINAL_STATUS = {'converged': ParameterEstimate.STATUS_CONVERGED,
                'not_converged': ParameterEstimate.STATUS_MAX_ITERATIONS,
                'incomplete': ParameterEstimate.STATUS_INCOMPLETE,
                'failed': ParameterEstimate.STATUS_FAILED}


class Identifier(Node):
    """Output-error ML on the live streams, test point after test point."""

    def __init__(self, **node_options):
        super().__init__('identifier', **node_options)
        spec = [
            ('run_description', '', 'path of the run-description YAML (rotor, model, unknowns, '
             "window_s relative to a test point's first flap sample)"),
            ('target_std', [0.0], 'target Cramer-Rao sigma of each unknown, in the order of the '
             "run description's unknowns (units of the parameter; 0 = no target)"),
            ('auto_start', 'excitation', 'how test points start besides ~/start_test_point: '
             "'excitation' (a stirring schedule that starts arms one), 'data' (the first one at "
             "the first flap sample), 'none'"),
            ('update_every_rad', math.pi / 4, 'intermediate estimates every this much rotor '
             'azimuth while the window fills (rad; 0 = none)', 0.0, 1e6),
            ('min_window_rad', 3.0 * math.pi, 'first intermediate estimate after this much of '
             'the window (rad of azimuth; the wake case is informative from ~1.5 rev)',
             0.1, 1e6),
            ('refit_tail_rad', math.pi, 'in the last this much azimuth of the window the '
             'growing window is refitted back to back, whenever the worker is free, so the '
             'final fit starts next to its optimum (rad; 0 = only every update_every_rad)',
             0.0, 1e6),
            ('max_iter', 30, 'Gauss-Newton iteration limit of the final fit', 1, 1000),
            ('step_tol', 1e-3, 'converged when every Gauss-Newton step is below this many '
             'Cramer-Rao sigma (offline identify: 1e-6; 1e-3 sigma from the optimum is '
             'statistically nothing and saves 3-4 iterations of the final fit)', 1e-9, 0.1),
            ('max_iter_provisional', 8, 'Gauss-Newton iteration limit of the growing-window '
             'fits (each starts from the latest iterate of the previous one)', 1, 1000),
            ('max_abs_angle_rad', 0.7, 'larger |pitch| or |flap| is rejected as degrees (rad)',
             0.01, 3.2),
            ('pre_trigger_s', 5.0, 'samples kept before a test point is armed, beyond its '
             'window: a start command may refer to samples this old (s; a stirring node '
             'starved of CPU sends its first command, stamped with the sample it locked on, '
             'late)', 0.0, 60.0),
            ('gap_tolerance_periods', 1.5, 'a step between samples longer than this many '
             'sampling periods is a gap (the window is then incomplete)', 1.01, 100.0),
            ('azimuth_slip_tolerance_rad', 0.1, 'an azimuth step that differs from rotor speed '
             'x time step by more than this is a slip of the time base (rad)', 1e-4, 3.0),
            ('fit_process', True, 'fit in a separate process, so that a fit never waits for '
             "the interpreter lock behind the subscriptions (false: in a thread of the node's "
             "process; less CPU on the final's path, but slower under load: "
             'bench/results/live_latency.md)'),
            # best effort by default: it receives from every publisher, while a reliable
            # subscription receives nothing from a best-effort (sensor-data QoS) publisher
            ('sensor_reliability', 'best_effort', 'QoS reliability of the sensor '
             "subscriptions: 'best_effort' (matches any publisher; a starved node loses "
             "samples, and the window says so) or 'reliable' (what a publisher still holds is "
             're-sent, so a node that falls behind loses no sample; every publisher must offer '
             'reliable, as rotor_plant does)'),
            ('sensor_queue_depth', 10000, 'samples each sensor subscription queues while the '
             'node is busy (10 s at 1 kHz); older ones are lost, and the window says so',
             1, 1000000),
            ('sensor_poll_period_s', 0.005, 'the sensor topics are taken in batches this '
             'often (s), not one executor callback each (less than half the CPU per message)',
             1e-4, 0.1),
            ('sensor_poll_fast_s', 0.0002, 'and this often in the last few milliseconds of a '
             'window, so its last sample is taken promptly (s)', 1e-5, 0.1),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
            ('max_window_s', 60.0, 'longest window_s (end - start) the buffers are sized for '
             '(s; window_s is refused beyond it)', 0.01, 3600.0),
            ('min_window_samples', 50, 'fewest flap samples a window_s must span at the '
             'measured sample rate (shorter windows are refused)', 3, 10_000_000),
        ]
        # settable at run time (checked; used by the next fit): targets, fit and window-check
        # tolerances (window_s too, declared below: from the next test point)
        tunable = ('target_std', 'max_iter', 'step_tol', 'max_iter_provisional',
                   'gap_tolerance_periods', 'azimuth_slip_tolerance_rad')
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:], read_only=s[0] not in tunable)
                  for s in spec}
        self.rig = Rig(node_run_description(self.d['run_description']))
        self.description = desc = self.rig.description
        model_for(desc)        # a model this rotor cannot have (2 blades, no cyclic) fails here
        self.unknowns = list(desc.unknowns)
        self.d['window_s'] = declare(
            self, 'window_s', [float(v) for v in desc.window_s],
            "identification window [start, end], s after a test point's first flap sample "
            "(default: the run description's); a change applies from the next test point",
            read_only=False)
        self.points = None
        self.window_checked = 0           # test point whose window length was checked
        self.origin_reported = 0          # test point whose lost first sample was logged
        for name, reason in (('target_std', self._targets_reason(self.d['target_std'])),
                             ('window_s', self._window_reason(self.d['window_s']))):
            if reason:
                raise ValueError(f'{name}: {reason}')
        self._set_targets()
        n = desc.rotor.blades
        self.flap_joints, self.pitch_joints = self.rig.flap_joints, self.rig.pitch_joints
        self.points = TestPointSequence(
            n, self.d['window_s'], self.flap_joints,
            FitSchedule(self.d['update_every_rad'], self.d['min_window_rad'],
                        self.d['refit_tail_rad']),
            pre_trigger_s=self.d['pre_trigger_s'],
            gap_factor=self.d['gap_tolerance_periods'],
            slip_tolerance_rad=self.d['azimuth_slip_tolerance_rad'],
            auto_start=self.d['auto_start'])
        self.lock = threading.Lock()      # the test points: executor and worker threads
        self.wake = threading.Condition()
        self.requests = []                # (FitRequest, kind, time, future) for the worker
        self.arrival = None               # monotonic time the newest sample was taken
        self.latencies_ms = []
        self.breakdowns = []              # where each published estimate's latency went (ms)
        self.taken = 0                    # sensor samples accepted (all three topics)
        self.busy = False                 # the worker is fitting
        self.worker_times = (float('nan'), float('nan'))   # its CPU and CPU-wait s, at exit
        self.provisional_points = set()   # test points with a growing-window estimate out
        self.provisional_wall_s = collections.deque(maxlen=5)  # their recent fits' wall times
        self.provisional_skipped = 0      # not asked for: they would have delayed the final
        self.final_to_check = None        # (request, Identification) of the final just fitted
        self.spikes_seen = set()          # (test point, quantity, blade, stamp) repaired
        self.spikes_logged = set()        # test points whose spikes were logged
        self.spikes_repaired = 0          # distinct flap/pitch samples replaced as spikes
        self.provisional_requested = set()  # test points with a growing-window fit asked for
        self.guess = {}                   # warm start: the latest sane iterate of a window fit
        self.bounds = None                # (lower, upper) of each unknown, for that check
        self.last_fit_s = float('nan')
        self.pub_estimate = self.create_publisher(ParameterEstimate, self.rig.topics['estimate'],
                                                  RESULT_QOS)
        self.pub_progress = self.create_publisher(IdentificationProgress,
                                                  self.rig.topics['progress'], STATE_QOS)
        reliability = {'reliable': ReliabilityPolicy.RELIABLE,
                       'best_effort': ReliabilityPolicy.BEST_EFFORT}.get(
                           self.d['sensor_reliability'])
        if reliability is None:
            raise ValueError(f"sensor_reliability must be 'reliable' or 'best_effort', got "
                             f"{self.d['sensor_reliability']!r}")
        sensor_qos = QoSProfile(reliability=reliability, history=SENSOR_BUFFER_QOS.history,
                                depth=self.d['sensor_queue_depth'],
                                durability=SENSOR_BUFFER_QOS.durability)
        self.diagnostics = Diagnostics(self, 'identification')
        self.diagnostics.set_value('value_spikes_repaired', 0)
        # after the Diagnostics' own check, so that nothing is applied when that one refuses
        allow_runtime_changes(self, self._check_parameter, self._apply_parameters)
        # taken in batches by a thread (rotor_id.nodes.polling), not one callback per message
        self.poller = SensorPoller(self, self.d['sensor_poll_period_s'], self._poll_period,
                                   self._poll_error, after_poll=self._after_poll)
        self.newest = {}                  # role -> (stamps, source ns, received ns, taken ns)
        self.sensor_subscriptions = {}
        for role, handler in (('blade_flap', self.on_flap_batch),
                              ('blade_pitch', self.on_pitch_batch),
                              ('azimuth', self.on_azimuth_batch)):
            self.diagnostics.watch(role, desc.topics[role])
            self.sensor_subscriptions[role] = self.poller.subscribe(
                JointState, desc.topics[role],
                lambda raws, infos, role=role, handler=handler: handler(role, raws, infos),
                sensor_qos)
        self.sensor_qos = sensor_qos
        self.incompatible_seen = set()    # publishers already reported
        self.create_timer(1.0, self._check_publishers)
        # volatile: a latched schedule of the past must not start a test point
        self.create_subscription(StirringCommand, self.rig.topics['stirring'], self.on_stirring,
                                 STATE_QOS)
        # own callback group: while a service call awaits its fit, data keep being taken
        self.create_service(Identify, '~/identify', self.on_identify,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(Trigger, '~/start_test_point', self.on_start_test_point)
        self.create_service(Trigger, '~/abort', self.on_abort)
        self.created = time.monotonic()
        self.create_timer(0.05, self.schedule)        # also checked on every azimuth sample
        self.fitter = FitProcess() if self.d['fit_process'] else None
        self.running_kind = None          # kind of the fit in progress (None: idle)
        self.running_point = None         # and its test point
        self.running = True
        self.worker = threading.Thread(target=self.work, name='identifier-fit', daemon=True)
        self.worker.start()
        self.poller.start()
        self._report_state()
        self._report_window()
        self.get_logger().info(f'{desc.model}: identifying {", ".join(self.unknowns)} over '
                               f'window_s {self.points.window_s} of each test point from '
                               f'{desc.topics["blade_flap"]} (auto_start: '
                               f'{self.d["auto_start"]})')

    def _check_publishers(self):
        """Count each sensor publisher whose QoS offer the subscription cannot match."""
        for subscription in self.sensor_subscriptions.values():
            for gid, policy in incompatible_publishers(self, subscription, self.sensor_qos):
                if gid in self.incompatible_seen:
                    continue
                self.incompatible_seen.add(gid)
                self.diagnostics.count(
                    'incompatible_qos', f'a publisher of {subscription.topic_name} does not '
                    f'offer what the subscription requests (policy {policy}): with '
                    f"sensor_reliability '{self.d['sensor_reliability']}' no sample of it "
                    'arrives; set sensor_reliability: best_effort for a best-effort publisher')

    def _targets_reason(self, targets):
        targets = list(targets)
        if targets != [0.0] and len(targets) != len(self.unknowns):
            return (f'target_std has {len(targets)} values for the unknowns {self.unknowns}; '
                    'give one per unknown (0 = no target)')
        if not all(math.isfinite(v) and v >= 0 for v in targets):
            return f'target_std {targets}: every target must be a finite sigma >= 0'
        return None

    def _window_reason(self, window_s):
        """Why ``window_s`` cannot be used (None: it can), before any test point uses it."""
        try:
            t0, t1 = window_bounds(window_s)
        except ValueError as exc:
            return str(exc)
        if t1 - t0 > self.d['max_window_s']:
            return (f'window_s {t0:g}-{t1:g} s is {t1 - t0:g} s long, more than max_window_s '
                    f"{self.d['max_window_s']:g} s (the buffers' bound; a read-only parameter "
                    'set at start)')
        period_ns = (sampling_period_ns(self.points.flap.stamps)
                     if self.points is not None else math.nan)
        samples = (t1 - t0) * NS / period_ns if period_ns > 0 else math.inf
        if samples < self.d['min_window_samples']:
            return (f'window_s {t0:g}-{t1:g} s spans {samples:.0f} flap samples at the '
                    f'measured {NS / period_ns:.0f} Hz, fewer than min_window_samples '
                    f"{self.d['min_window_samples']}; give a longer window")
        return None

    def _check_parameter(self, name, value, _values):
        if name == 'target_std':
            return self._targets_reason(value)
        if name == 'window_s':
            return self._window_reason(value)
        return None

    def _apply_parameters(self, names):
        if 'target_std' in names:
            self._set_targets()
        if names & {'gap_tolerance_periods', 'azimuth_slip_tolerance_rad'}:
            with self.lock:               # the window checks of the next fit request on
                self.points.gap_factor = float(self.d['gap_tolerance_periods'])
                self.points.slip_tolerance_rad = float(self.d['azimuth_slip_tolerance_rad'])
            self.get_logger().info(
                f'window checks from the next fit request: gaps over '
                f'{self.points.gap_factor:g} sampling periods, azimuth slips over '
                f'{self.points.slip_tolerance_rad:g} rad')
        if 'window_s' in names:
            # rclpy answers a successful set without a reason: the log and /diagnostics say
            # when the new window applies
            with self.lock:
                note = self.points.set_window(self.d['window_s'])
                if self.points.flap.size < 2:
                    note += (' (no flap sample yet: its length in samples is checked against '
                             f"min_window_samples {self.d['min_window_samples']} by the fit "
                             'only)')
            self.get_logger().info(note)
            self._report_window(note)

    def _report_window(self, note=''):
        t0, t1 = self.points.window_s
        self.diagnostics.set_value('window_s_next', f'{t0:.4f}-{t1:.4f} s')
        if note:
            self.diagnostics.set_value('window_s_change', note)

    def _set_targets(self):
        targets = list(self.d['target_std'])
        self.targets = np.array([0.0] * len(self.unknowns) if targets == [0.0] else targets,
                                dtype=float)

    # -------------------------------------------------------------------------- buffering
    def _take_one(self, role, stamp, names, position, velocity=()):
        """Check and buffer one sample of a sensor topic (call with the lock held)."""
        points = self.points
        try:
            if role == 'azimuth':
                psi, omega = check_azimuth_sample(
                    names, position, velocity, self.rig.azimuth_joint, stamp,
                    points.azimuth.series.last_stamp, self.rig.azimuth_convention)
                points.add_azimuth(stamp, psi, omega)
            else:
                flap = role == 'blade_flap'
                values = check_joint_sample(
                    names, position, self.flap_joints if flap else self.pitch_joints, stamp,
                    (points.flap if flap else points.pitch).last_stamp,
                    self.d['max_abs_angle_rad'], extra_joints=True)
                (points.add_flap if flap else points.add_pitch)(stamp, values)
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return False
        self.taken += 1
        return True

    def _take_batch(self, role, raws):
        """
        Check and buffer a batch of serialized samples of one topic (call with the lock held).

        Decoded together (rotor_id.io.jointstate_cdr) and checked together
        (:func:`~rotor_id.nodes.live.check_joint_batch`); a batch with anything odd in it (a
        message of another layout, a sample refused) is taken one message at a time instead,
        so each refusal is counted with its reason exactly as a single message would be.
        """
        points = self.points
        if role == 'azimuth':
            checked = checked_azimuth_batch(raws, self.rig.azimuth_joint,
                                            points.azimuth.series.last_stamp,
                                            self.rig.azimuth_convention)
        else:
            flap = role == 'blade_flap'
            checked = checked_joint_batch(raws, self.flap_joints if flap else self.pitch_joints,
                                          (points.flap if flap else points.pitch).last_stamp,
                                          self.d['max_abs_angle_rad'])
        if checked is None:
            stamps = []
            for stamp, names, position, velocity in one_by_one(raws, self.diagnostics):
                stamps.append(stamp)
                self._take_one(role, stamp, names, position, velocity)
            return np.array(stamps, dtype=np.int64)
        stamps = [int(v) for v in checked[0]]
        if role == 'azimuth':
            for stamp, angle, speed in zip(stamps, checked[1].tolist(), checked[2].tolist()):
                points.add_azimuth(stamp, angle, speed)
        else:
            add = points.add_flap if role == 'blade_flap' else points.add_pitch
            for stamp, row in zip(stamps, checked[1]):
                add(stamp, row)
        self.taken += len(stamps)
        return checked[0]

    def _on_batch(self, role, raws, infos):
        """Poller thread: take a batch of one sensor topic, with its timing (ns, system)."""
        taken_ns = time.time_ns()
        for _ in raws:
            self.diagnostics.received(role)
        with self.lock:
            before = self.points.phase
            stamps = self._take_batch(role, raws)
            changed = self.points.phase != before
        if len(stamps) == len(infos):     # for the latency: when each sample was sent, received
            self.newest[role] = (stamps, np.array([i['source_timestamp'] for i in infos]),
                                 np.array([i['received_timestamp'] for i in infos]), taken_ns)
        if changed:
            self._report_state()

    on_flap_batch = on_pitch_batch = on_azimuth_batch = _on_batch

    def _after_poll(self, taken):
        """After a poll that took samples: ask for the fits that are due."""
        self.arrival = time.monotonic()
        self.schedule()

    def _poll_period(self):
        """Poll fast in the last few milliseconds of a window (its last sample taken at once)."""
        with self.lock:
            point = self.points.current
            covered = self.points.covered_s(point) if point is not None else None
        if covered is not None and covered >= point.window_s[1] - FAST_POLL_SPAN_S:
            return self.d['sensor_poll_fast_s']
        return self.d['sensor_poll_period_s']

    def _poll_error(self, exc):
        self.diagnostics.count('sensor_batch_error', f'{type(exc).__name__}: {exc}')

    def on_flap(self, msg):
        """Take one flap sample (an armed test point starts at its first one)."""
        with self.lock:
            before = self.points.phase
            self._take_one('blade_flap', stamp_ns(msg.header.stamp), msg.name, msg.position)
            changed = self.points.phase != before
        if changed:
            self._report_state()

    def on_pitch(self, msg):
        """Take one pitch sample."""
        with self.lock:
            self._take_one('blade_pitch', stamp_ns(msg.header.stamp), msg.name, msg.position)

    def on_azimuth(self, msg):
        """Take one azimuth / rotor-speed sample; ask for the fits that are due."""
        with self.lock:
            taken = self._take_one('azimuth', stamp_ns(msg.header.stamp), msg.name,
                                   msg.position, msg.velocity)
        if taken:
            self.arrival = time.monotonic()
            self.schedule()

    def on_stirring(self, msg):
        """Follow the stirring schedule's phase: a schedule that starts arms a test point."""
        with self.lock:
            before = self.points.count
            ended = self.points.on_excitation(msg.phase, stamp_ns(msg.header.stamp))
            started = self.points.count != before
        for point in ended:
            self._publish_aborted(point)
        if started:
            self.get_logger().info(f'{self.points.latest.describe()}: armed by the stirring '
                                   'schedule')
        if ended or started:
            self._report_state()

    # -------------------------------------------------------------------------- services
    def on_start_test_point(self, request, response):
        """Trigger: arm a test point from the next flap sample; the answer names it."""
        with self.lock:
            point, text = self.points.arm('service')
        response.success, response.message = point is not None, text
        self.get_logger().info(text)
        self._report_state()
        return response

    def on_abort(self, request, response):
        """Trigger: abort the test point in progress (its result, if any, is not published)."""
        with self.lock:
            point = self.points.abort()
            latest = self.points.latest
        if point is None:
            response.success = False
            response.message = ('no test point in progress' +
                                (f' (last: {latest.describe()})' if latest else ''))
        else:
            self._publish_aborted(point)
            response.success, response.message = True, point.describe()
        self.get_logger().info(response.message)
        self._report_state()
        return response

    def _publish_aborted(self, point):
        msg = ParameterEstimate(status=ParameterEstimate.STATUS_ABORTED, names=self.unknowns,
                                kind=ParameterEstimate.KIND_FINAL, test_point=point.number,
                                message=f'{point.describe()}: {point.detail}',
                                additional_data_s=-1.0)
        msg.computed_at = self.get_clock().now().to_msg()
        # data time: the newest flap sample when it was aborted (none yet: the clock's time)
        with self.lock:
            newest = self.points.flap.last_stamp
        msg.header.stamp = msg.computed_at if newest is None else time_msg(newest)
        msg.header.frame_id = self.d['frame_id']
        msg.model = self.description.model
        if point.stamp0_ns is not None:
            msg.test_point_start = time_msg(point.stamp0_ns)
        msg.window_requested_start_s, msg.window_requested_end_s = point.window_s
        self.pub_estimate.publish(msg)
        self.get_logger().warning(msg.message)

    def _report_state(self):
        latest = self.points.latest
        if (latest is not None and latest.origin_received_ns is not None
                and self.origin_reported != latest.number):
            self.origin_reported = latest.number
            self.get_logger().info(
                f'{latest.describe()}: its first flap sample was lost (the first received is '
                f'{(latest.origin_received_ns - latest.stamp0_ns) / 1e6:.1f} ms later); its '
                'window starts from where the sample grid puts it')
        self.diagnostics.set_value('test_point', latest.describe() if latest else 'none yet')
        self.diagnostics.set_value('test_point_phase', self.points.phase.name.lower())
        # between test points quiet inputs are STALE, not a fault (never received: ERROR)
        self.diagnostics.idle = self.points.phase not in (Phase.ARMED, Phase.RECORDING,
                                                          Phase.FITTING)

    def _check_window_samples(self, point):
        """WARN on /diagnostics while a window spans fewer flap samples than min_window_samples."""
        t0, t1 = point.window_s
        period_ns = sampling_period_ns(self.points.flap.stamps)
        if not period_ns > 0:
            return
        samples = (t1 - t0) * NS / period_ns
        if samples >= self.d['min_window_samples']:
            self.diagnostics.problem('window_too_short')
            return
        text = (f'{point.describe()}: window_s {t0:g}-{t1:g} s spans {samples:.0f} flap samples '
                f'at the measured {NS / period_ns:.0f} Hz, fewer than min_window_samples '
                f"{self.d['min_window_samples']}: its estimate rests on few samples (set a "
                'longer window_s)')
        if self.diagnostics.problems.get('window_too_short', (None, ''))[1] != text:
            self.get_logger().warning(text)
        self.diagnostics.problem('window_too_short', DiagnosticStatus.WARN, text)

    # -------------------------------------------------------------------------- scheduling
    def schedule(self):
        """Ask the test points for the fit that is due (growing window or final); queue it."""
        clock = time.perf_counter()
        with self.lock:
            point = self.points.current
            if (point is not None and point.phase == Phase.RECORDING
                    and self.window_checked != point.number and self.points.flap.size > 2):
                self.window_checked = point.number        # once per test point
                self._check_window_samples(point)
            request = self.points.due(worker_idle=not (self.busy or self.requests))
            first = self._missed_provisional(request)
        if request is not None and not request.final and self._would_straddle(request):
            self.provisional_skipped += 1
            return
        for request in ([first] if first is not None else []) + [request]:
            if request is None:
                continue
            if not request.final:
                self.provisional_requested = {n for n in self.provisional_requested
                                              if n > request.test_point - 16}
                self.provisional_requested.add(request.test_point)
            # the window's data copied out and checked (ms)
            request.build_ms = (time.perf_counter() - clock) * 1e3
            request.last_sample = self._last_sample(request)
            kind = (ParameterEstimate.KIND_FINAL if request.final
                    else ParameterEstimate.KIND_PROVISIONAL)
            self._submit(request, kind)
            if request.final:
                self._report_state()

    def _missed_provisional(self, request):
        """
        Return the growing-window fit a final request skipped over, or None (lock held).

        Samples that arrive in a burst (a node starved of CPU catching up) can cross a test
        point's growing-window points and its window's end in one batch: its first growing
        window is then asked for here, before the final, so one precedes every final estimate
        (unless growing windows are switched off).
        """
        if (request is None or not request.final or self.d['update_every_rad'] <= 0
                or request.test_point in self.provisional_requested):
            return None
        point = self.points.points.get(request.test_point)
        t0, t1 = request.window_s
        first = t0 + self.d['min_window_rad'] / self.points.azimuth.omega
        if point is None or not first < t1:
            return None
        return self.points.request(point, (t0, first), False)

    def _would_straddle(self, request):
        """
        Say whether a growing-window fit asked for now would still run at the window's end.

        The final fit would then wait for it (at least its current iteration). Judged from the
        wall time of this node's recent growing-window fits (x 1.5, or 20 ms before any), with
        the rotor time left in the window taken as wall time (the samples arrive in real
        time). The first growing-window estimate of a test point is never skipped: one precedes
        every final estimate.
        """
        return request.test_point in self.provisional_points and self._near_end(request)

    def _near_end(self, request):
        """Say whether a growing-window fit of ``request`` would end after its window's end."""
        horizon = 1.5 * max(self.provisional_wall_s, default=PROVISIONAL_DEFAULT_S)
        point = self.points.points.get(request.test_point)
        return point is not None and point.window_s[1] - request.window_s[1] < horizon

    def _last_sample(self, request):
        """
        (sent, received, taken) system-clock ns of the window's last sample, or None.

        The last of the three topics' newest samples at or before the window's end (within
        half a sampling period), from the batches just taken (the final fit is asked for in
        the poll that completes the window).
        """
        hi = request.stamp0_ns + int(round(request.window_s[1] * NS))
        found = None
        for stamps, sent, received, taken in list(self.newest.values()):
            period = int(np.median(np.diff(stamps))) if stamps.size > 1 else 0
            i = int(np.searchsorted(stamps, hi + period // 2, side='right')) - 1
            if 0 <= i < stamps.size and (found is None or sent[i] > found[0]):
                found = (int(sent[i]), int(received[i]), taken)
        return found

    def _submit(self, request, kind, future=None):
        """
        Queue a fit for the worker.

        A newer request replaces the provisional ones still waiting, and a final one (or a
        service call) also stops a provisional fit in progress after its current iteration.
        Until a growing-window estimate of its test point was published, a final request
        leaves the waiting one in place (it stops after its first iteration and is published),
        so that one always precedes each test point's final estimate, however late the worker
        thread gets a CPU.
        """
        final = kind != ParameterEstimate.KIND_PROVISIONAL
        with self.wake:
            keep = final and request.test_point not in self.provisional_points
            self.requests = [r for r in self.requests
                             if r[1] != ParameterEstimate.KIND_PROVISIONAL or keep]
            request.worker_busy = self.busy    # the final waits for a fit in progress
            self.requests.append((request, kind, self.arrival or time.monotonic(), future))
            self.wake.notify()
            if final:
                self._give_way()

    def _give_way(self):
        """Stop (or abandon) a growing-window fit in the fit process: a final fit waits."""
        if self.fitter is not None and self.running_kind == ParameterEstimate.KIND_PROVISIONAL:
            (self.fitter.abandon if self.running_point in self.provisional_points
             else self.fitter.stop)()

    def work(self):
        """Worker thread: run the queued fits in order, publish them (or answer the service)."""
        # load the compiled kernels and fitting modules now, not in the first test point's fits
        warm_s = self.fitter.wait_ready() if self.fitter is not None else warm_up()
        self.get_logger().info(f'fits ready ({"fit process" if self.fitter else "thread"}: '
                               f'kernels and modules loaded in {warm_s:.2f} s)')
        while self.running:
            with self.wake:
                while not self.requests and self.running:
                    self.wake.wait(0.2)
                if not self.running:
                    break
                request, kind, requested, future = self.requests.pop(0)
                self.busy, self.running_kind = True, kind
                self.running_point = request.test_point
            try:
                self._run(request, kind, requested, future)
            finally:
                self.busy, self.running_kind = False, None
        self.worker_times = thread_times()

    def _run(self, request, kind, requested, future):
        """Fit one request; publish it with its latency and where that time went."""
        started = time.monotonic()
        cpu0, waiting0 = thread_times()
        taken0 = self.taken
        timing = {'record': getattr(request, 'build_ms', 0.0)}
        msg = self.fit(request, kind, timing=timing, remember=future is None)
        if msg is None:                   # superseded by a final fit or a service call
            return
        if future is not None:
            future.set_result(msg)
            return
        if kind == ParameterEstimate.KIND_FINAL:
            with self.lock:
                point = self.points.finish(request.test_point, _OUTCOME_OF[msg.status])
            if point is None:             # aborted while it was fitted: already published
                return
        published = time.monotonic()
        self.pub_estimate.publish(msg)
        done, done_ns = time.monotonic(), time.time_ns()
        cpu1, waiting1 = thread_times()
        if kind == ParameterEstimate.KIND_FINAL:   # off the latency path: after publishing
            self._report_state()
            if getattr(request, 'log_line', None):
                self.get_logger().info(request.log_line)
        if kind == ParameterEstimate.KIND_PROVISIONAL:
            self.provisional_wall_s.append(done - started)
            self.provisional_points = {n for n in self.provisional_points
                                       if n > request.test_point - 16} | {request.test_point}
        # latency: newest sample of the window taken -> its estimate published
        self.latencies_ms.append((done - requested) * 1e3)
        cpu, waiting = (cpu1 - cpu0) * 1e3, (waiting1 - waiting0) * 1e3
        # in the fit process: its wall time (identify and verdict there, and the pipe)
        stages = timing.get('in_fit_process', sum(timing.get(k, 0.0)
                                                  for k in ('identify', 'verdict')))
        stages += timing.get('message', 0.0) + timing.get('value_checks', 0.0)
        self.breakdowns.append({
            'kind': 'final' if request.final else 'provisional',
            'test_point': request.test_point, 'window_end_s': round(request.window_s[1], 5),
            'total': self.latencies_ms[-1],
            'queued': (started - requested) * 1e3 - timing['record'], **timing,
            'publish': (done - published) * 1e3,
            # between the stages: mostly taking the GIL back after a blocking call
            'other': (published - started) * 1e3 - stages,
            'cpu': cpu, 'cpu_wait': waiting,
            'gil_or_lock_wait': max(0.0, (done - started) * 1e3 - cpu - waiting
                                    - timing.get('in_fit_process', 0.0)),
            'samples_taken': self.taken - taken0,
            'worker_busy': bool(getattr(request, 'worker_busy', False)),
            # the window's last sample: sent by its publisher -> received by DDS here -> taken
            # by the poller; end to end: sent -> this estimate published (system clock)
            **_sample_times(getattr(request, 'last_sample', None), done_ns)})
        lat = np.array(self.latencies_ms)
        self.diagnostics.set_value('latency_ms_last', f'{lat[-1]:.1f}')
        self.diagnostics.set_value('latency_ms_median', f'{np.median(lat):.1f}')
        self.diagnostics.set_value('latency_ms_max', f'{lat.max():.1f}')
        self.diagnostics.set_value('latency_count', lat.size)
        self.diagnostics.set_value('latency_breakdown_last', _breakdown_text(self.breakdowns[-1]))
        if kind == ParameterEstimate.KIND_FINAL:
            self._check_final(request)

    def _check_final(self, request):
        """
        Check the residual adequacy of a test point's final estimate, once it is published.

        It is not on the latency path (it costs about as much CPU as the fit), and a
        ParameterEstimate has no field for it: an inadequate fit is a WARN on /diagnostics
        (``final_adequacy``, with the figures and where) and a logged warning naming the test
        point; ``adequacy`` / ``adequacy_test_point`` give the last verdict.
        """
        pending, self.final_to_check = self.final_to_check, None
        if pending is None or pending[0] is not request or request.record is None:
            return
        ident = pending[1]
        point = f'test point {request.test_point}' if request.test_point else 'final estimate'
        try:
            result = adequacy_of(ident, request.record)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            self.diagnostics.problem('final_adequacy', DiagnosticStatus.WARN,
                                     f'{point}: the adequacy check failed ({exc})')
            return
        self.diagnostics.set_value('adequacy', result.verdict.value)
        self.diagnostics.set_value('adequacy_test_point', request.test_point)
        self.diagnostics.set_value('adequacy_misfit_channels', ' '.join(
            (result.location or {}).get('channels', [])))
        warning = result.warning()
        if warning is None:
            self.diagnostics.problem('final_adequacy')
            return
        self.diagnostics.problem('final_adequacy', DiagnosticStatus.WARN, f'{point}: {warning}')
        self.get_logger().warning(f'{point}: {warning}')

    # -------------------------------------------------------------------------- fitting
    def _final_waiting(self):
        """Say whether a final fit or a service call waits for the worker."""
        return any(r[1] != ParameterEstimate.KIND_PROVISIONAL for r in self.requests)

    def _remember(self, names, values):
        """
        Keep the unknowns of an iterate as the next fit's starting values.

        Every accepted Gauss-Newton iterate has a lower cost than the fit's start, so the latest
        one is kept whether or not its fit converged, if finite and strictly inside the
        physical bounds (an iterate stuck at a bound is no better start than the guess).
        """
        if self.bounds is None:
            model = model_for(self.description)
            self.bounds = {n: (model.parameter(n).lower, model.parameter(n).upper)
                           for n in self.unknowns}
        guess = {n: float(values[list(names).index(n)]) for n in self.unknowns}
        if all(math.isfinite(v) and self.bounds[n][0] < v < self.bounds[n][1]
               for n, v in guess.items()):
            self.guess = guess

    def _annotate(self, msg, request, kind):
        """
        Test point, window used and integrity fields of an estimate (from the request).

        ``header.stamp`` is the data time: the window's end (its last flap sample used, or with
        none used the end of the window asked for), never the time of computation
        (``computed_at``).
        """
        check = request.check
        msg.kind = kind
        msg.test_point = request.test_point
        msg.test_point_start = time_msg(request.stamp0_ns)
        msg.window_requested_start_s, msg.window_requested_end_s = (
            float(v) for v in request.window_s)
        first, last = check.used_ns()
        if first is not None:
            msg.window_start, msg.window_end = time_msg(first), time_msg(last)
            msg.window_s = (last - first) / NS
        msg.header.stamp = msg.window_end if first is not None else time_msg(check.hi_ns)
        msg.time_base_consistent = check.time_base_consistent
        missing = check.missing
        msg.missing_channels = list(missing)
        msg.missing_samples = [int(v) for v in missing.values()]
        return msg

    def fit(self, request, kind, max_iter=None, timing=None, remember=True):
        """
        Identify a FitRequest's window; return a ParameterEstimate.

        The status never claims convergence from an incomplete window
        (:func:`rotor_id.nodes.test_points.outcome`). ``timing`` (a dict), when given, receives
        the milliseconds of each stage. With ``remember`` (test points, not service calls) the
        iterates are the next fit's starting values. Returns None when a provisional fit gave
        way to a final one.
        """
        timing = {} if timing is None else timing
        final = kind != ParameterEstimate.KIND_PROVISIONAL
        check = request.check
        problems = check.describe()
        if not check.complete:
            self.diagnostics.count('window_incomplete', problems)
        if request.record is None:
            status = (ParameterEstimate.STATUS_INCOMPLETE if not check.complete
                      else ParameterEstimate.STATUS_FAILED)
            return self._failed(request, kind, status, request.error +
                                (f'; {problems}' if problems else ''))
        clock = time.perf_counter()
        dead, repaired = self._check_values(request)
        timing['value_checks'] = (time.perf_counter() - clock) * 1e3
        if dead:
            return self._failed(request, kind, ParameterEstimate.STATUS_FAILED, dead +
                                (f'; {problems}' if problems else ''))
        desc, options = self._fit_setup(request, kind, max_iter)

        def progress(info):
            self.pub_progress.publish(progress_message(
                info, self.get_clock().now().to_msg()))
            if remember:
                self._remember(info['names'], info['values'])
            if not final and self._final_waiting():
                if self.fitter is not None:
                    self._give_way()
                elif request.test_point in self.provisional_points:
                    raise Abandoned
                else:
                    return STOP           # the first growing-window estimate: publish it now
            return None

        started = time.perf_counter()
        try:
            if self.fitter is not None:
                ident, verdict, fit_timing = self.fitter.fit(request, desc, options, progress)
                timing['in_fit_process'] = (time.perf_counter() - started) * 1e3
            else:
                ident, verdict, fit_timing = fit_window(
                    request, desc, options, progress,
                    hurry=None if final else self._final_waiting)
        except Abandoned:
            return None
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            status = (ParameterEstimate.STATUS_INCOMPLETE if not check.complete
                      else ParameterEstimate.STATUS_FAILED)
            return self._failed(request, kind, status, str(exc) +
                                (f'; {problems}' if problems else ''))
        timing.update(fit_timing)
        est = ident.estimate
        if kind == ParameterEstimate.KIND_FINAL:
            self.final_to_check = (request, ident)   # its adequacy: after it is published
        self.last_fit_s = time.perf_counter() - started
        clock = time.perf_counter()
        if remember:
            self._remember(est.names, est.values)
        if (not final and self._final_waiting()
                and request.test_point in self.provisional_points):
            return None                   # the final fit is waiting: give way to it now
        result = outcome(check, True, est.converged)
        if result == 'incomplete':
            status = ParameterEstimate.STATUS_INCOMPLETE
        elif kind == ParameterEstimate.KIND_PROVISIONAL:
            status = ParameterEstimate.STATUS_ITERATING
        else:
            status = FINAL_STATUS[result]
        label = {ParameterEstimate.KIND_PROVISIONAL: 'growing window (provisional)',
                 ParameterEstimate.KIND_FINAL: 'final',
                 ParameterEstimate.KIND_ON_DEMAND: 'on demand'}[kind]
        point = f'test point {request.test_point}, ' if request.test_point else ''
        note = (f'{point}{label}: {request.window_s[0]:.4f}-{request.window_s[1]:.4f} s, '
                + (f'INCOMPLETE WINDOW ({problems}), no convergence claimed (fit: '
                   f'{est.message})' if result == 'incomplete' else est.message)
                + f', {self.last_fit_s * 1e3:.0f} ms' + (f'; {repaired}' if repaired else ''))
        msg = estimate_message(ident, self.get_clock().now().to_msg(), status, verdict,
                               self.d['frame_id'], note)
        self._annotate(msg, request, kind)
        self.diagnostics.set_value('last_estimate', ', '.join(
            f'{n}={v:.4g}±{s:.2g}' for n, v, s in zip(msg.names, msg.values, msg.std)))
        self.diagnostics.set_value('last_fit_ms', f'{self.last_fit_s * 1e3:.1f}')
        timing['message'] = (time.perf_counter() - clock) * 1e3
        if kind == ParameterEstimate.KIND_FINAL:      # logged once it is published (_run)
            request.log_line = (f'{point}final estimate: '
                                f'{self.diagnostics.values["last_estimate"]} ({note}); '
                                f'target met: {verdict[0]}')
        return msg

    def _check_values(self, request):
        """
        Check a window's sensor values as the bag reader does (the same functions).

        Returns (why it cannot be fitted or '', what was repaired or '').

        A blade's flap reading one exact value over the requested window is a dead sensor: the
        ERROR ``dead_flap_sensor`` on /diagnostics, cleared by the next window whose flap
        readings all move. Flap/pitch spikes are replaced in the request's record (its own
        copy of the buffers) before the fit; ``value_spikes_repaired`` counts the samples
        replaced, each once however many growing windows see it, ``value_spike_last`` names
        the last one, and the first spike of each test point is logged.
        """
        record = request.record
        point = (f'test point {request.test_point}' if request.test_point
                 else 'on-demand window')
        t0, t1 = request.window_s
        dead = record.stuck_flap_blades(t0, t1)
        if dead:
            text = (f'{point}: the flap of {", ".join(name for name, _ in dead)} reads exactly '
                    f'{", ".join(f"{value:.6g}" for _, value in dead)} rad in every sample of '
                    f'window_s [{t0:g}, {t1:g}] s: a dead or disconnected sensor (a real '
                    'reading shows noise and the stirring response); no estimate. Check the '
                    'sensor and its wiring')
            self.diagnostics.problem('dead_flap_sensor', DiagnosticStatus.ERROR, text)
            return text, ''
        self.diagnostics.problem('dead_flap_sensor')
        repairs = record.repair_value_spikes()
        if not repairs:
            return '', ''
        said, new = [], 0
        for quantity, blade, repair in repairs:
            stamps = record.stamp0_ns + np.round(record.time_s[repair.indices] * NS)
            for stamp in stamps.astype(np.int64).tolist():
                key = (request.test_point, quantity, blade, stamp)
                if key not in self.spikes_seen:
                    self.spikes_seen.add(key)
                    new += 1
            said.append(f'{blade} {quantity}: {repair.count}, e.g. {repair.value:.4g} rad among '
                        f'{repair.neighbours:.4g} at {record.time_s[repair.index]:.4f} s')
        text = (f'value spike(s) replaced by interpolation (a bit flip or a dropped reading) '
                f'in {"; ".join(said)}')
        if new:
            self.spikes_repaired += new
            self.diagnostics.set_value('value_spikes_repaired', self.spikes_repaired)
            self.diagnostics.set_value('value_spike_last', f'{point}: {said[-1]}')
            if request.test_point not in self.spikes_logged:
                self.spikes_logged.add(request.test_point)
                self.get_logger().warning(f'{point}: {text}; check the sensor if this recurs '
                                          '(counted on /diagnostics: value_spikes_repaired)')
        # keys of older test points are no longer needed
        self.spikes_seen = {k for k in self.spikes_seen if k[0] >= request.test_point - 1}
        return '', text

    def _fit_setup(self, request, kind, max_iter=None):
        """Return the run description (warm start: the latest iterate) and FitOptions of a fit."""
        final = kind != ParameterEstimate.KIND_PROVISIONAL
        desc = self.description
        if self.guess:
            desc = replace(desc, initial_guess={**desc.initial_guess, **self.guess})
        # growing windows start from the latest iterate (or the description's guess) without
        # the multi-start grid; the final fit uses the grid only if there is no iterate yet
        # and the description does not give every starting value
        options = FitOptions(max_iter=max_iter or self.d['max_iter' if final
                                                         else 'max_iter_provisional'],
                             multi_start=final, step_tol=self.d['step_tol'],
                             targets=tuple(self.targets),
                             # a growing window next to the window's end: the final's verdict
                             # follows at once, its own extrapolation would only delay it
                             full_verdict=final or not (self._final_waiting()
                                                        or self._near_end(request)))
        return desc, options

    def _failed(self, request, kind, status, reason):
        self.get_logger().warning(f'identification over {request.window_s} s: {reason}')
        msg = ParameterEstimate(status=status, message=reason, names=self.unknowns,
                                additional_data_s=-1.0)
        msg.computed_at = self.get_clock().now().to_msg()
        msg.header.frame_id = self.d['frame_id']
        msg.model = self.description.model
        return self._annotate(msg, request, kind)

    async def on_identify(self, request, response):
        """
        Identify.srv: fit the buffered data between the given bounds (0, 0 = all).

        The bounds are seconds after the latest test point's first flap sample (or the oldest
        sample kept). The fit runs on the worker thread; the executor keeps taking data.
        """
        with self.lock:
            buffered = self.points.buffered_s()
            if buffered is None:
                response.success, response.message = False, 'no data buffered yet'
                return response
            origin, first, covered = buffered
            start = request.window_start_s
            end = request.window_end_s if request.window_end_s > 0 else covered
            if request.window_start_s == 0 and request.window_end_s == 0:
                start = max(first, 0.0)
            if not (first - 1e-3 <= start < end <= covered + 1e-3):
                response.success = False
                response.message = (f'window [{start}, {end}] s is not inside the buffered '
                                    f'[{first:.4f}, {covered:.4f}] s (seconds after the '
                                    "latest test point's first flap sample)")
                return response
            fit_request = self.points.window_request(0, origin, (start, end), True)
        future = Future(executor=self.executor)
        future.add_done_callback(lambda _: None)     # wakes the executor when the fit is done
        self._submit(fit_request, ParameterEstimate.KIND_ON_DEMAND, future)
        msg = await future
        response.estimate = msg
        response.success = msg.status not in (ParameterEstimate.STATUS_FAILED,
                                              ParameterEstimate.STATUS_INCOMPLETE)
        response.message = msg.message
        if msg.status != ParameterEstimate.STATUS_FAILED:
            self.pub_estimate.publish(msg)
        return response

    def close(self):
        """Stop the poller and the worker thread; print the estimate latencies."""
        poller_times = self.poller.thread_times()
        self.poller.stop()
        self.running = False
        with self.wake:
            self.wake.notify()
        self.worker.join(timeout=5.0)
        if self.fitter is not None:
            self.fitter.close()
        wait_for_acks([self.pub_estimate, self.pub_progress])
        print(f'identifier: estimate latencies (ms): '
              f'{" ".join(f"{v:.1f}" for v in self.latencies_ms)}', file=sys.stderr, flush=True)
        # one JSON line each: where the latency went, and the CPU the two threads used
        print(f'identifier: latency breakdown (ms): {json.dumps(self.breakdowns)}',
              file=sys.stderr, flush=True)
        threads = {'wall_s': time.monotonic() - self.created, 'samples_taken': self.taken,
                   'polls': self.poller.polls, 'provisional_skipped': self.provisional_skipped}
        for name, (cpu, waiting) in (('executor', thread_times()),     # (this is the executor)
                                     ('poller', poller_times), ('worker', self.worker_times)):
            threads[f'{name}_cpu_s'], threads[f'{name}_cpu_wait_s'] = cpu, waiting
        print(f'identifier: thread times: {json.dumps(threads)}', file=sys.stderr, flush=True)


#: Wall time assumed for a growing-window fit before one was timed (s).
PROVISIONAL_DEFAULT_S = 0.02

#: Rotor time before a window's end from which the sensor topics are polled fast (s).
FAST_POLL_SPAN_S = 0.01

#: The test point's outcome a final estimate's status stands for.
_OUTCOME_OF = {status: result for result, status in FINAL_STATUS.items()}


def _sample_times(last_sample, published_ns):
    """Milliseconds from the window's last sample being sent to its estimate published."""
    if last_sample is None:
        return {}
    sent, received, taken = last_sample
    return {'sent_to_received': (received - sent) / 1e6, 'received_to_taken': (taken - received)
            / 1e6, 'end_to_end': (published_ns - sent) / 1e6}


def _breakdown_text(b):
    """One line of a latency breakdown (ms) for /diagnostics."""
    return (f'{b["total"]:.1f} = record {b.get("record", 0):.1f} + queued {b["queued"]:.1f} + '
            f'value checks {b.get("value_checks", 0):.1f} + '
            f'identify {b.get("identify", 0):.1f} (Gauss-Newton {b.get("gauss_newton", 0):.1f}, '
            f'{b.get("iterations", 0)} it) + verdict {b.get("verdict", 0):.1f} + message '
            f'{b.get("message", 0):.1f} + publish {b["publish"]:.1f} + other {b["other"]:.1f}; '
            f'worker on CPU {b["cpu"]:.1f}, waiting for a CPU {b["cpu_wait"]:.1f}, for the GIL '
            f'or the buffer lock {b["gil_or_lock_wait"]:.1f}; {b["samples_taken"]} samples '
            'taken meanwhile')


#: Interpreter-lock switch interval of the identifier process (s; Python's default 5 ms). The
#: executor thread runs callbacks back to back at 3 kHz; the worker thread that takes a finished
#: fit from the fit process and publishes it would wait up to this long for the lock each time.
GIL_SWITCH_INTERVAL_S = 0.0005


def main(args=None):
    """Run the node until SIGINT/SIGTERM (fits in a worker thread or the fit process)."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    return spin_node(Identifier, args)


if __name__ == '__main__':
    raise SystemExit(main())
