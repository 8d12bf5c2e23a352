"""
What every rotor_id node shares: QoS, parameters with descriptors, diagnostics, adapters.

Parameters declared with descriptors (units in the description, ranges), QoS by kind of data
and header stamps as docs/ros_interfaces.md tabulates them, /diagnostics at ~1 Hz by hand
(diagnostic_updater is not among the installed wheels), main() that shuts down cleanly on
SIGINT/SIGTERM.
"""

import faulthandler
import math
import os
from pathlib import Path
import signal
import sys
import threading
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.duration import Duration
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from rclpy.signals import SignalHandlerOptions
from rotor_id.io.run_description import load_run_description
from rotor_id.io.timebase import wrap_azimuth
from rotor_id_msgs.msg import IdentificationProgress, ParameterEstimate
from sensor_msgs.msg import JointState

NS = 1_000_000_000

#: Sensor streams (REP-2003, as rclpy's qos_profile_sensor_data): best effort, volatile, keep last.
#: Depth 1000 (1 s at 1 kHz), not 5: the plant publishes in bursts of a few ms of samples and a
#: busy subscriber must not drop them.
SENSOR_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT,
                        history=HistoryPolicy.KEEP_LAST, depth=1000,
                        durability=DurabilityPolicy.VOLATILE)
#: Buffering readers of the sensor streams (identifier, state estimator): 10 s at 1 kHz, so a
#: fit holding the interpreter on a busy machine does not cost samples.
SENSOR_BUFFER_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT,
                               history=HistoryPolicy.KEEP_LAST, depth=10000,
                               durability=DurabilityPolicy.VOLATILE)
#: What the plant offers on the sensor topics: reliable, so that a recorder (which adapts to the
#: offer) can take every sample, while best-effort readers (SENSOR_QOS) match it as well. The
#: writer keeps 10 s at 1 kHz for re-sending to a reader that fell behind.
SENSOR_OFFER_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                              history=HistoryPolicy.KEEP_LAST, depth=10000,
                              durability=DurabilityPolicy.VOLATILE)
#: Commands, states, progress, events: reliable, volatile (depth 1000: a reader that fell
#: behind, such as a recorder on a busy machine, still gets every message re-sent). A volatile
#: reader matches a volatile and a transient-local publisher alike.
STATE_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                       depth=1000, durability=DurabilityPolicy.VOLATILE)
#: Results (parameter estimates): as STATE_QOS but latched (transient local, the last 100
#: kept), like a map server's map: a reader that joins late (a dashboard started mid-run, a
#: restarted state estimator, a recorder or test process whose discovery lagged on a loaded
#: machine) still receives them. Volatile readers match it too, without the history. States
#: and commands stay volatile: a late reader must not act on old ones.
RESULT_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                        history=HistoryPolicy.KEEP_LAST, depth=100,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
DIAGNOSTICS_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                             history=HistoryPolicy.KEEP_LAST, depth=10)


# ------------------------------------------------------------------------------ parameters
def declare(node, name, default, description, low=None, high=None, read_only=True,
            constraints=''):
    """
    Declare a parameter with a descriptor (units in ``description``) and return its value.

    ``low``/``high`` give a floating-point or integer range matching the default's type.
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=constraints)
    if low is not None and high is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high),
                                                     step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(low), to_value=float(high), step=0.0)]
    return node.declare_parameter(name, default, descriptor).value


def resolve_config(path):
    """
    Find a config file given as a path, or by name in rotor_id's config directory.

    By name: the config/ of the source tree this module was imported from (a clone, where
    tools/env.sh puts the sources first so that edits apply without a rebuild), else the
    installed share/rotor_id/config. Raises FileNotFoundError naming the places tried.
    """
    candidate = Path(os.path.expanduser(str(path)))
    if candidate.is_file():
        return candidate
    tried = [str(candidate.resolve())]
    if not candidate.is_absolute():
        source = Path(__file__).resolve().parents[2] / 'config' / candidate
        if source.is_file() and (source.parents[1] / 'setup.py').is_file():
            return source
        tried.append(str(source))
        try:
            from ament_index_python.packages import get_package_share_directory
            share = Path(get_package_share_directory('rotor_id')) / 'config' / candidate
            if share.is_file():
                return share
            tried.append(str(share))
        except (ImportError, LookupError, ValueError):
            pass
    raise FileNotFoundError(f'config file {path} not found (looked at {", ".join(tried)})')


# ------------------------------------------------------------------------------ time
def stamp_ns(stamp):
    """builtin_interfaces/Time → integer ns."""
    return int(stamp.sec) * NS + int(stamp.nanosec)


def node_run_description(path):
    """Load the run description a node's ``run_description`` parameter names (one clear error)."""
    if not path:
        raise ValueError('parameter run_description is empty: give the path of a run '
                         'description YAML (see config/nodes_*.yaml and docs/run_description.md)')
    return load_run_description(resolve_config(path))


# ------------------------------------------------------------------------------ the rig
RUN_DESCRIPTION_HELP = ('run description YAML of the rig (topics, joint names, blade count, '
                        'azimuth convention; docs/run_description.md): a path, or a name in '
                        "rotor_id's config/")


class Rig:
    """
    The test stand as every node sees it: one run description, read by the library's loader.

    Topics (``topics[role]`` for the recorded roles blade_pitch, blade_flap, azimuth and the
    node roles pitch_command, stirring, estimate, progress, state), joint names, blade count
    and azimuth convention. Relative topic names resolve in the node's namespace.
    """

    def __init__(self, description):
        self.description = description
        self.blades = description.rotor.blades
        self.flap_joints = description.blade_joints('blade_flap')
        self.pitch_joints = description.blade_joints('blade_pitch')
        self.azimuth_joint = description.azimuth_joint
        self.azimuth_convention = description.azimuth_convention
        self.topics = {**description.topics, **description.node_topics}

    def azimuth_position(self, psi):
        """Return what this rig's azimuth joint reads for the unwrapped azimuth ``psi`` (rad)."""
        return wrap_azimuth(psi) if self.azimuth_convention == 'wrapped' else psi


def declare_rig(node):
    """Declare the read-only ``run_description`` parameter and return the node's :class:`Rig`."""
    path = declare(node, 'run_description', '', RUN_DESCRIPTION_HELP)
    return Rig(node_run_description(path))


# ------------------------------------------------------------------------------ parameters
def allow_runtime_changes(node, check=None, apply=None):
    """
    Let ``ros2 param set`` change the node's parameters declared with ``read_only=False``.

    rclpy itself rejects read-only (structural) parameters, values of another type and values
    outside a descriptor's range, each with a reason. ``check(name, value, values)`` may
    reject more (return the reason, or None): ``values`` is the node's ``d`` with the proposed
    changes applied, for checks across parameters. Accepted values go into ``node.d``, then
    ``apply(names)`` runs with the names changed.
    """
    def on_set(parameters):
        proposed = dict(node.d)
        proposed.update({p.name: p.value for p in parameters})
        for parameter in parameters:
            reason = check(parameter.name, parameter.value, proposed) if check else None
            if reason:
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name}: {reason}')
        changed = {p.name: p.value for p in parameters if p.name in node.d}
        node.d.update(changed)
        if apply is not None and changed:
            apply(set(changed))
        return SetParametersResult(successful=True)
    node.add_on_set_parameters_callback(on_set)


def time_msg(ns):
    """Integer ns → builtin_interfaces/Time."""
    ns = int(ns)
    return Time(sec=ns // NS, nanosec=ns % NS)


# ------------------------------------------------------------------------------ JointState
def joint_state(stamp, names, position, velocity=None, frame_id='rotor'):
    """Build a sensor_msgs/JointState: ``header.stamp`` (ns or Time), names, values (rad)."""
    msg = JointState()
    msg.header.stamp = time_msg(stamp) if isinstance(stamp, (int, np.integer)) else stamp
    msg.header.frame_id = frame_id
    msg.name = list(names)
    msg.position = [float(v) for v in position]
    if velocity is not None:
        msg.velocity = [float(v) for v in velocity]
    return msg


# ------------------------------------------------------------------------------ diagnostics
#: Levels from least to most severe: an ERROR outweighs the STALE of an idle node.
_SEVERITY = [DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.STALE,
             DiagnosticStatus.ERROR]


class Diagnostics:
    """
    The health of one node, published as a DiagnosticArray on /diagnostics (~1 Hz).

    One status per node: name ``<namespace/node>: <task>`` (``identifier: identification`` in
    the root namespace, ``rig2/identifier: identification`` under ``/rig2``), hardware_id the
    node's parameter ``hardware_id`` (default: its fully qualified name, so two rigs on one
    graph never share one). /diagnostics stays absolute: the ROS convention, where aggregators
    and rqt_robot_monitor listen. Levels, the worst one wins:

    * ERROR: a watched input (:meth:`watch`) gave no data for ``stale_error_s`` (none at all
      since the start, or none since its last message), or :meth:`problem` said so;
    * WARN: messages rejected in the last period (the message names the last reason), an input
      silent for ``stale_warn_s``, an input slower than ``min_rate_hz``, or :meth:`problem`;
    * STALE: the node is idle by design (:attr:`idle`: a finished schedule, a finished run) and
      its inputs went quiet: what it reports is old, nothing is wrong;
    * OK: data flowing, nothing rejected. A node that never received data is never OK.

    ``stale_warn_s``, ``stale_error_s`` and ``min_rate_hz`` are parameters settable at run time.
    """

    def __init__(self, node, task, period_s=1.0, hardware_id=None):
        self.node = node
        qualified = node.get_fully_qualified_name().lstrip('/')
        self.name = f'{qualified}: {task}'
        self.hardware_id = hardware_id or declare(
            node, 'hardware_id', '', 'hardware_id of this node on /diagnostics (empty: the '
            "node's fully qualified name, e.g. /rig2/identifier)") or \
            node.get_fully_qualified_name()
        self.settings = {
            'stale_warn_s': declare(node, 'stale_warn_s', 2.0, 'an input silent this long is '
                                    'WARN on /diagnostics (s)', 0.01, 3600.0, read_only=False),
            'stale_error_s': declare(node, 'stale_error_s', 10.0, 'and this long ERROR (s; at '
                                     'least stale_warn_s)', 0.01, 3600.0, read_only=False),
            'min_rate_hz': declare(node, 'min_rate_hz', 50.0, 'an input arriving slower than '
                                   'this is WARN on /diagnostics (Hz; 0 = no check)', 0.0, 1e6,
                                   read_only=False),
        }
        node.add_on_set_parameters_callback(self._on_set)
        self.counts = {}
        self.values = {}
        self.last_reason = ''
        self._reported = 0
        self.level_override = None
        self.problems = {}
        self.idle = False
        self.streams = {}                 # name -> [topic, received, first_ns, last_ns, at_period]
        self.started_ns = self._now()
        self._period_start_ns = self.started_ns
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        self.timer = node.create_timer(period_s, self.publish)

    def _now(self):
        return time.monotonic_ns()

    def _on_set(self, parameters):
        proposed = {**self.settings, **{p.name: p.value for p in parameters
                                        if p.name in self.settings}}
        if proposed['stale_error_s'] < proposed['stale_warn_s']:
            return SetParametersResult(
                successful=False, reason=f'stale_error_s {proposed["stale_error_s"]} is below '
                f'stale_warn_s {proposed["stale_warn_s"]}: the ERROR must come after the WARN')
        self.settings = proposed
        return SetParametersResult(successful=True)

    def watch(self, stream, topic):
        """Check an input for staleness and rate; call :meth:`received` on each message."""
        self.streams[stream] = [topic, 0, None, None, 0]

    def received(self, stream, count=1):
        """Note ``count`` messages of a watched input arriving now (accepted or not)."""
        entry = self.streams[stream]
        now = self._now()
        entry[1] += count
        entry[3] = now
        if entry[2] is None:
            entry[2] = now

    def subscribe(self, msg_type, topic, callback, qos, stream=None, **kwargs):
        """``node.create_subscription`` of a watched input (``stream``: name, default topic)."""
        stream = stream or topic
        self.watch(stream, topic)

        def watched(msg):
            self.received(stream)
            callback(msg)
        return self.node.create_subscription(msg_type, topic, watched, qos, **kwargs)

    def problem(self, key, level=None, message=''):
        """Raise (level WARN or ERROR, with a message) or clear (level None) a node problem."""
        if level is None:
            self.problems.pop(key, None)
        else:
            self.problems[key] = (level, message)

    def count(self, kind, reason=''):
        """Count one rejected message of ``kind`` (reason: a short explanation)."""
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if reason:
            self.last_reason = f'{kind}: {reason}'
        total = sum(self.counts.values())
        if total in (1, 10, 100, 1000) or total % 10000 == 0:
            self.node.get_logger().warning(
                f'rejected message ({kind}): {reason} [{total} rejected so far; see /diagnostics]')

    def set_value(self, key, value):
        """Report a value (shown as a string)."""
        self.values[key] = value

    @property
    def rejected(self):
        """Total number of rejected messages."""
        return sum(self.counts.values())

    def stream_findings(self, now_ns=None):
        """Return ([(level, text)], {key: value}) of the watched inputs at ``now_ns``."""
        now = self._now() if now_ns is None else now_ns
        warn_s, error_s = self.settings['stale_warn_s'], self.settings['stale_error_s']
        period_s = max((now - self._period_start_ns) / NS, 1e-9)
        findings, values = [], {}
        for stream, entry in self.streams.items():
            topic, received, first, last, at_period = entry
            silent_s = (now - (last if last is not None else self.started_ns)) / NS
            values[f'{stream}_messages'] = received
            values[f'{stream}_silent_s'] = f'{silent_s:.2f}'
            what = (f'no data on {topic} since the start {silent_s:.1f} s ago: check the run '
                    "description's topics, the namespace and that the publisher runs"
                    if last is None else f'no data on {topic} for {silent_s:.1f} s')
            if silent_s >= warn_s:
                level = (DiagnosticStatus.STALE if self.idle and last is not None
                         else DiagnosticStatus.ERROR if silent_s >= error_s
                         else DiagnosticStatus.WARN)
                findings.append((level, what))
            elif first is not None and first <= self._period_start_ns:
                rate = (received - at_period) / period_s
                values[f'{stream}_rate_hz'] = f'{rate:.1f}'
                if not self.idle and rate < self.settings['min_rate_hz']:
                    findings.append((DiagnosticStatus.WARN, f'{topic} at {rate:.1f} Hz, below '
                                     f'min_rate_hz {self.settings["min_rate_hz"]:g}'))
        return findings, values

    def publish(self):
        """Publish the current status."""
        total = self.rejected
        now = self._now()
        findings, stream_values = self.stream_findings(now)
        findings += list(self.problems.values())
        if total > self._reported:
            findings.append((DiagnosticStatus.WARN,
                             f'{total - self._reported} message(s) rejected in the last '
                             f'period; last: {self.last_reason}'))
        status = DiagnosticStatus(name=self.name, hardware_id=self.hardware_id)
        if self.level_override is not None:
            status.level, status.message = self.level_override
        elif findings:
            worst = max((level for level, _ in findings), key=_SEVERITY.index)
            status.level = worst
            status.message = '; '.join(text for level, text in findings if level == worst)
        else:
            status.level = DiagnosticStatus.OK
            status.message = 'ok' if not total else f'ok ({total} rejected earlier)'
        self._reported = total
        for entry in self.streams.values():
            entry[4] = entry[1]
        self._period_start_ns = now
        values = {'rejected_total': total, **{f'rejected_{k}': v for k, v in self.counts.items()},
                  **stream_values, **self.values}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(msg)


# ------------------------------------------------------------------------------ estimates
def estimate_message(identification, computed_at, status=None, target=(True, 0.0),
                     frame_id='rotor', message=None):
    """
    rotor_id_msgs/ParameterEstimate of an Identification's unknowns (SI, rad).

    ``header.stamp`` is the data time, the end of the identified window (``window_end``);
    ``computed_at`` (a builtin_interfaces/Time) is when the estimate was made.
    """
    est = identification.estimate
    unknowns = list(identification.unknowns)
    idx = [est.names.index(n) for n in unknowns]
    cov = est.covariance[np.ix_(idx, idx)]
    model = identification.model
    msg = ParameterEstimate()
    msg.computed_at = computed_at
    msg.header.frame_id = frame_id
    msg.model = model.name
    msg.names = unknowns
    msg.units = [_unit(model.parameter(n).unit) for n in unknowns]
    msg.values = [float(est.values[i]) for i in idx]
    msg.std = [float(math.sqrt(max(cov[j, j], 0.0))) for j in range(len(idx))]
    msg.covariance = [float(c) for c in cov.ravel()]
    msg.correlation = [float(c) for c in est.correlation[np.ix_(idx, idx)].ravel()]
    msg.noise_std = [float(s) for s in est.noise_std]
    msg.channel_names = list(est.channel_names)
    msg.cost = float(est.cost)
    msg.iteration = int(est.iterations)
    if status is None:
        status = (ParameterEstimate.STATUS_CONVERGED if est.converged
                  else ParameterEstimate.STATUS_MAX_ITERATIONS)
    msg.status = status
    msg.message = message if message is not None else est.message
    part = identification.experiments[0]
    rec_ns = getattr(identification, 'stamp0_ns', 0)
    omega = identification.omega_rad_s
    msg.window_start = time_msg(rec_ns + int(round(identification.window_s[0] * NS)))
    msg.window_end = time_msg(rec_ns + int(round(identification.window_s[1] * NS)))
    msg.header.stamp = msg.window_end
    msg.window_s = float((part.t[-1] - part.t[0]) / omega) if omega > 0 else 0.0
    msg.target_met, msg.additional_data_s = bool(target[0]), float(target[1])
    return msg


def _unit(unit):
    return {'-': '1', 'angle': 'rad'}.get(unit, unit)


def progress_message(info, stamp):
    """rotor_id_msgs/IdentificationProgress from fit_output_error's per-iteration dict."""
    msg = IdentificationProgress()
    msg.header.stamp = stamp
    msg.iteration = int(info['iteration'])
    msg.cost = float(info['cost'])
    names = list(info['names'])
    msg.names = names
    msg.values = [float(v) for v in info['values']]
    msg.elapsed = float(info['elapsed'])
    msg.message = str(info.get('message', info.get('label', '')))
    return msg


def estimate_from_message(msg):
    """(names, values, std, covariance (n, n)) of a ParameterEstimate, as numpy arrays."""
    n = len(msg.names)
    cov = np.asarray(msg.covariance, dtype=float)
    cov = cov.reshape(n, n) if cov.size == n * n else np.full((n, n), np.nan)
    return list(msg.names), np.asarray(msg.values, dtype=float), \
        np.asarray(msg.std, dtype=float), cov


class PacedTicks:
    """
    Call ``tick()`` every ``period_s`` of the monotonic clock, from a thread of its own.

    Instead of an executor timer: every executor wake-up rebuilds its wait set in Python, which
    was most of the main thread of a node ticking at 50-200 Hz. A late tick is not followed by
    a burst of catch-up ticks. Like a timer's, the ticks start once an executor spins the node
    (its 0.2 s timer starts the thread); an exception in ``tick`` ends the thread and is
    raised again by that timer in the executor, so the node stops as for a callback's.
    """

    def __init__(self, node, period_s, tick, name='ticks'):
        self.period_s = float(period_s)
        self.tick = tick
        self.stopping = threading.Event()
        self.error = None
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        node.create_timer(0.2, self._watch)

    def _run(self):
        due = time.monotonic()
        while not self.stopping.is_set():
            due += self.period_s
            if self.stopping.wait(max(0.0, due - time.monotonic())):
                break
            due = max(due, time.monotonic() - self.period_s)
            try:
                self.tick()
            except Exception as exc:        # noqa: B902 - raised again by the executor
                self.error = exc
                return

    def _watch(self):
        if self.error is not None:
            raise self.error
        if self.thread.ident is None and not self.stopping.is_set():
            self.thread.start()

    def stop(self, timeout_s=2.0):
        """Stop the ticks (from any thread; waits for a tick in progress unless it is this one)."""
        self.stopping.set()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout_s)


#: How long a stopping node waits for reliable readers to acknowledge what it sent. With the
#: tick thread's join (2 s) and the executor's shutdown (1 s) it bounds a node's clean-up;
#: processes.STOP_TIMEOUT_S leaves a loaded machine room above it.
ACK_WAIT_S = 10.0


def wait_for_acks(publishers, timeout_s=ACK_WAIT_S):
    """
    Before exiting: give reliable readers (a lagging recorder) the messages still in flight.

    Returns the topics whose readers had not acknowledged everything by ``timeout_s``; each is
    one line on stderr, since what they missed is not in a recording.
    """
    deadline = time.monotonic() + timeout_s
    missed = []
    for publisher in publishers:
        if publisher.qos_profile.reliability == ReliabilityPolicy.RELIABLE:
            left = max(0.0, deadline - time.monotonic())
            if not publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                missed.append(publisher.topic_name)
    for topic in missed:
        print(f'warning: a reliable reader of {topic} had not acknowledged every message '
              f'{timeout_s:.0f} s after the stop; a recording of it may lack the last ones',
              file=sys.stderr, flush=True)
    return missed


# ------------------------------------------------------------------------------ main
def spin_node(node_factory, args=None, executor_factory=None, after_stop=None,
              runtime_errors=()):
    """
    Run a node as main() does in demo_nodes_py (Jazzy); returns exit code.

    A configuration error while constructing the node (ValueError) is one line on stderr and
    exit code 2, never a traceback. SIGINT and SIGTERM only set a flag that the spin loop checks
    every 0.1 s: rclpy's own handler raises ExternalShutdownException and then
    KeyboardInterrupt, which can land inside a message conversion or the clean-up.
    ``after_stop(node, executor)`` runs once the stop is asked for, before the clean-up (the
    recorder drains what was delivered); ``runtime_errors`` raised while spinning are one line
    and exit code 2 as well.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    # SIGUSR1: every thread's stack on stderr (a supervisor sends it to a node that did not
    # stop in time, before killing it, so that its log says where it hung)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    stop = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, _frame: stop.append(number))
    node = executor = None
    code = 0
    try:
        try:
            node = node_factory()
        except (ValueError, ParameterException, NameValidationException) as exc:
            print(f'rotor_id: configuration error: {exc}', file=sys.stderr)
            return 2
        executor = (executor_factory or SingleThreadedExecutor)()
        executor.add_node(node)
        while not stop:
            executor.spin_once(timeout_sec=0.1)
        if after_stop is not None:
            after_stop(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except runtime_errors as exc:
        print(f'{getattr(node, "get_name", lambda: "rotor_id")()}: error: {exc}',
              file=sys.stderr)
        code = 2
    finally:
        for signum in (signal.SIGINT, signal.SIGTERM):   # stopping already: no second interrupt
            signal.signal(signum, signal.SIG_IGN)
        steps = _CleanUpClock(getattr(node, 'get_name', lambda: 'rotor_id')())
        if node is not None:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
                steps.done('close')
            node.destroy_node()
            steps.done('destroy_node')
        if executor is not None:
            # shut down here, while the context lives: an executor left to the garbage
            # collector after rclpy's shutdown prints a traceback from its __del__
            executor.shutdown(timeout_sec=1.0)
            del executor
            steps.done('executor.shutdown')
        rclpy.try_shutdown()
        steps.done('rclpy.try_shutdown')
        steps.report()
    return code


class _CleanUpClock:
    """Seconds spent in each clean-up step; one stderr line when the whole took long."""

    SLOW_S = 5.0

    def __init__(self, name):
        self.name = name
        self.start = self.last = time.monotonic()
        self.steps = []

    def done(self, step):
        now = time.monotonic()
        self.steps.append((step, now - self.last))
        self.last = now

    def report(self):
        total = self.last - self.start
        if total > self.SLOW_S:
            print(f'{self.name}: slow clean-up, {total:.1f} s: '
                  + ', '.join(f'{step} {s:.1f} s' for step, s in self.steps),
                  file=sys.stderr, flush=True)
