"""
identifier: live output-error identification of the rotor (``ros2 run rotor_id identifier``).

Buffers ``/rotor/blade_pitch``, ``/rotor/blade_flap`` and ``/rotor/azimuth`` by header stamp, forms
a :class:`rotor_id.io.record.Record` exactly as the bag reader does (t = unwrapped azimuth, time
origin = first flap stamp received) and runs :func:`rotor_id.pipeline.identify` with the run
description (parameter ``run_description``, schema of ../shared/recordings/README.md):

* while the window fills, on the growing window [window start, latest sample] every
  ``update_every_rad`` of azimuth, and back to back in its last ``refit_tail_rad`` (published
  with STATUS_ITERATING: provisional);
* when the window is complete (final: STATUS_CONVERGED / MAX_ITERATIONS / FAILED), starting
  from the latest growing-window iterate, so that it needs few Gauss-Newton iterations; it
  stops a growing-window fit in progress after the current iteration (the first one is then
  published as it stands, so that a growing-window estimate always precedes the final one);
* on the ``~/identify`` service (rotor_id_msgs/srv/Identify) over any buffered window.

Each estimate carries the Cramér-Rao covariance and the data-length verdict of Ch.3
(target_met, additional_data_s for the targets ``target_std``); every Gauss-Newton iteration is
published on ``/rotor_id/progress``. Fits run in a worker thread so the subscriptions keep up.
"""

from dataclasses import replace
import json
import math
import sys
import threading
import time

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from rotor_id.estimation.output_error import STOP
from rotor_id.nodes.common import (declare, Diagnostics, estimate_message, node_run_description,
                                   NS, progress_message, RESULT_QOS, SENSOR_BUFFER_QOS,
                                   spin_node, stamp_ns, STATE_QOS, wait_for_acks)
from rotor_id.nodes.live import (BadSample, bound_history, check_azimuth_sample,
                                 check_joint_sample, data_length_verdict, record_from_series,
                                 StampedSeries, UnwrappedAzimuth, window_gaps)
from rotor_id.pipeline import identify, model_for
from rotor_id_msgs.msg import IdentificationProgress, ParameterEstimate
from rotor_id_msgs.srv import Identify
from sensor_msgs.msg import JointState


class _Superseded(Exception):
    """A provisional fit gave way to a final fit or a service call."""


def _thread_times(tid=None):
    """
    Return (CPU s, run-queue wait s) of a thread of this process (default: the caller).

    From /proc/<pid>/task/<tid>/schedstat (on CPU, waiting for a CPU): the run-queue wait is the
    time the thread was ready but the machine had no free core. Where that file is missing
    (not Linux) the CPU time is the caller's ``time.thread_time()`` and the wait is 0.
    """
    path = ('/proc/thread-self/schedstat' if tid is None
            else f'/proc/self/task/{tid}/schedstat')
    try:
        with open(path) as stat:
            on_cpu, waiting = stat.read().split()[:2]
        return int(on_cpu) / NS, int(waiting) / NS
    except (OSError, ValueError):
        return (time.thread_time() if tid is None else float('nan')), 0.0


class Identifier(Node):
    """Output-error ML on the live streams, with progress and the data-length verdict."""

    def __init__(self):
        super().__init__('identifier')
        spec = [
            ('run_description', '', 'path of the run-description YAML (rotor, model, unknowns, '
             'window_s relative to the first flap stamp received)'),
            ('target_std', [0.0], 'target Cramer-Rao sigma of each unknown, in the order of the '
             "run description's unknowns (units of the parameter; 0 = no target)"),
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
            ('estimate_topic', '/rotor_id/estimate', 'ParameterEstimate topic'),
            ('progress_topic', '/rotor_id/progress', 'IdentificationProgress topic'),
            ('frame_id', 'rotor', 'header.frame_id of the published messages'),
        ]
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:]) for s in spec}
        self.description = node_run_description(self.d['run_description'])
        desc = self.description
        self.unknowns = list(desc.unknowns)
        targets = list(self.d['target_std'])
        if targets == [0.0]:
            targets = [0.0] * len(self.unknowns)
        if len(targets) != len(self.unknowns):
            raise ValueError(f'target_std has {len(targets)} values for the unknowns '
                             f'{self.unknowns}; give one per unknown (0 = no target)')
        self.targets = np.array(targets, dtype=float)
        n = desc.rotor.blades
        joints = desc.joint_names or {}
        self.flap_joints = list(joints.get('blade_flap') or
                                [f'blade_{k}' for k in range(1, n + 1)])
        self.pitch_joints = list(joints.get('blade_pitch') or self.flap_joints)
        self.flap = StampedSeries(n)
        self.pitch = StampedSeries(n)
        self.azimuth = StampedSeries(2)
        self.unwrapped = UnwrappedAzimuth()    # the record's t at the azimuth stamps
        self.stamp0 = None
        self.lock = threading.Lock()
        self.wake = threading.Condition()
        self.requests = []                # (window_s, final, time, future) for the worker
        self.arrival = None               # monotonic time the newest sample was taken
        self.latencies_ms = []
        self.breakdowns = []              # where each published estimate's latency went (ms)
        self.taken = 0                    # sensor samples accepted (all three topics)
        self.busy = False                 # the worker is fitting
        self.worker_times = (float('nan'), float('nan'))   # its CPU and CPU-wait s, at exit
        self.provisional_published = 0
        self.final_done = False
        self.next_update = None
        self.first_update = None
        self.requested_until = -math.inf  # end of the newest growing window asked for
        self.guess = {}                   # warm start: the latest sane iterate of a window fit
        self.bounds = None                # (lower, upper) of each unknown, for that check
        self.last_fit_s = float('nan')
        self.pub_estimate = self.create_publisher(ParameterEstimate, self.d['estimate_topic'],
                                                  RESULT_QOS)
        self.pub_progress = self.create_publisher(IdentificationProgress,
                                                  self.d['progress_topic'], STATE_QOS)
        for role, callback in (('blade_flap', self.on_flap), ('blade_pitch', self.on_pitch),
                               ('azimuth', self.on_azimuth)):
            self.create_subscription(JointState, desc.topics[role], callback, SENSOR_BUFFER_QOS)
        # own callback group: while a service call awaits its fit, data keep being taken
        self.create_service(Identify, '~/identify', self.on_identify,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.diagnostics = Diagnostics(self, 'identification')
        self.created = time.monotonic()
        self.create_timer(0.05, self.schedule)        # also checked on every azimuth sample
        self.running = True
        self.worker = threading.Thread(target=self.work, name='identifier-fit', daemon=True)
        self.worker.start()
        self.get_logger().info(f'{desc.model}: identifying {", ".join(self.unknowns)} over '
                               f'window_s {desc.window_s} from {desc.topics["blade_flap"]}')

    # -------------------------------------------------------------------------- buffering
    def _accept(self, series, msg, joints, max_abs):
        stamp = stamp_ns(msg.header.stamp)
        try:
            values = check_joint_sample(msg.name, msg.position, joints, stamp,
                                        series.last_stamp, max_abs)
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return None
        with self.lock:
            series.append(stamp, values)
        self.taken += 1
        return stamp

    def on_flap(self, msg):
        """Buffer one flap sample (its stamp starts the record's clock)."""
        stamp = self._accept(self.flap, msg, self.flap_joints, self.d['max_abs_angle_rad'])
        if stamp is not None and self.stamp0 is None:
            self.stamp0 = stamp

    def on_pitch(self, msg):
        """Buffer one pitch sample."""
        self._accept(self.pitch, msg, self.pitch_joints, self.d['max_abs_angle_rad'])

    def on_azimuth(self, msg):
        """Buffer one azimuth / rotor-speed sample."""
        stamp = stamp_ns(msg.header.stamp)
        try:
            psi, omega = check_azimuth_sample(msg.name, msg.position, msg.velocity, 'rotor',
                                              stamp, self.azimuth.last_stamp)
        except BadSample as bad:
            self.diagnostics.count(bad.kind, str(bad))
            return
        with self.lock:
            self.azimuth.append(stamp, (psi, omega))
            self.unwrapped.add(stamp, psi, omega)
        self.taken += 1
        self.arrival = time.monotonic()
        self.schedule()

    # -------------------------------------------------------------------------- scheduling
    def _covered_s(self):
        """Seconds since the first flap stamp up to which all three streams have data."""
        if self.stamp0 is None or min(self.pitch.size, self.azimuth.size) == 0:
            return None
        last = min(self.flap.last_stamp, self.pitch.last_stamp, self.azimuth.last_stamp)
        return (last - self.stamp0) / NS

    def schedule(self):
        """
        Ask the worker for growing-window fits while the window fills, then the final one.

        The first after ``min_window_rad``, then one every ``update_every_rad``; in the last
        ``refit_tail_rad`` of the window a new one as soon as the worker is free, so the last
        growing-window iterate (the final fit's start) is as close to the end as possible.
        """
        covered = self._covered_s()
        if covered is None or self.final_done:
            return
        t0, t1 = self.description.window_s
        omega = self.azimuth.values[-1, 1]
        period = (self.flap.stamps[-1] - self.flap.stamps[-2]) / NS if self.flap.size > 1 else 0
        if covered >= t1 - period:
            self.final_done = True
            self._submit((t0, t1), True)
            return
        if self.d['update_every_rad'] <= 0:
            return
        if self.next_update is None:
            self.first_update = self.next_update = t0 + self.d['min_window_rad'] / omega
        if covered < self.first_update or covered <= self.requested_until:
            return
        if covered >= self.next_update:
            self.next_update = covered + self.d['update_every_rad'] / omega
        elif covered < t1 - self.d['refit_tail_rad'] / omega or self.busy or self.requests:
            return
        self.requested_until = covered
        self._submit((t0, covered), False)

    def _submit(self, window_s, final, future=None):
        """
        Queue a fit for the worker.

        A newer request replaces the provisional ones still waiting, and a final one (or a
        service call) also stops a provisional fit in progress after its current iteration.
        Until a growing-window estimate was published, a final request leaves the waiting one
        in place (it stops after its first iteration and is published), so that one always
        precedes the final estimate, however late the worker thread gets a CPU.
        """
        with self.wake:
            keep = final and not self.provisional_published
            self.requests = [r for r in self.requests if r[1] or r[3] is not None or keep]
            self.requests.append((window_s, final, self.arrival or time.monotonic(), future))
            self.wake.notify()

    def work(self):
        """Worker thread: run the queued fits in order, publish them (or answer the service)."""
        while self.running:
            with self.wake:
                while not self.requests and self.running:
                    self.wake.wait(0.2)
                if not self.running:
                    break
                window_s, final, requested, future = self.requests.pop(0)
                self.busy = True
            try:
                self._run(window_s, final, requested, future)
            finally:
                self.busy = False
        self.worker_times = _thread_times()

    def _run(self, window_s, final, requested, future):
        """Fit one request; publish it with its latency and where that time went."""
        started = time.monotonic()
        cpu0, waiting0 = _thread_times()
        taken0 = self.taken
        timing = {}
        msg = self.fit(window_s, final, timing=timing, remember=future is None)
        if msg is None:                   # superseded by a final fit or a service call
            return
        if future is not None:
            future.set_result(msg)
            return
        published = time.monotonic()
        self.pub_estimate.publish(msg)
        done = time.monotonic()
        cpu1, waiting1 = _thread_times()
        self.provisional_published += not final
        # latency: newest sample of the window taken -> its estimate published
        self.latencies_ms.append((done - requested) * 1e3)
        cpu, waiting = (cpu1 - cpu0) * 1e3, (waiting1 - waiting0) * 1e3
        stages = sum(timing.get(k, 0.0) for k in ('record', 'identify', 'verdict', 'message'))
        self.breakdowns.append({
            'kind': 'final' if final else 'provisional', 'window_end_s': round(window_s[1], 5),
            'total': self.latencies_ms[-1], 'queued': (started - requested) * 1e3, **timing,
            'publish': (done - published) * 1e3,
            # between the stages: mostly taking the GIL back after a blocking call
            'other': (published - started) * 1e3 - stages,
            'cpu': cpu, 'cpu_wait': waiting,
            'gil_or_lock_wait': max(0.0, (done - started) * 1e3 - cpu - waiting),
            'samples_taken': self.taken - taken0})
        lat = np.array(self.latencies_ms)
        self.diagnostics.set_value('latency_ms_last', f'{lat[-1]:.1f}')
        self.diagnostics.set_value('latency_ms_median', f'{np.median(lat):.1f}')
        self.diagnostics.set_value('latency_ms_max', f'{lat.max():.1f}')
        self.diagnostics.set_value('latency_count', lat.size)
        self.diagnostics.set_value('latency_breakdown_last', _breakdown_text(self.breakdowns[-1]))

    # -------------------------------------------------------------------------- fitting
    def _final_waiting(self):
        """Say whether a final fit or a service call waits for the worker."""
        return any(r[1] or r[3] is not None for r in self.requests)

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

    def fit(self, window_s, final, max_iter=None, timing=None, remember=True):
        """
        Identify over ``window_s``; return a ParameterEstimate (STATUS_FAILED on error).

        ``timing`` (a dict), when given, receives the milliseconds of each stage. With
        ``remember`` (growing windows and the final one, not service calls) the iterates are
        the next fit's starting values. Returns None when a provisional fit gave way.
        """
        timing = {} if timing is None else timing
        clock = time.perf_counter()
        with self.lock:
            try:
                # only the window and 1.5 revolutions either side (identify uses one)
                margin = int(3.0 * math.pi / self.azimuth.values[-1, 1] * NS)
                span = (self.stamp0 + int(window_s[0] * NS) - margin,
                        self.stamp0 + int(window_s[1] * NS) + margin)
                record = record_from_series(self.flap, self.pitch, self.azimuth,
                                            self.flap_joints, self.stamp0, span_ns=span,
                                            unwrapped=self.unwrapped)
            except ValueError as exc:
                return self._failed(str(exc), window_s)
            gaps = window_gaps({'flap': self.flap, 'pitch': self.pitch,
                                'azimuth': self.azimuth},
                               self.stamp0 + int(window_s[0] * NS),
                               self.stamp0 + int(window_s[1] * NS))
        timing['record'] = (time.perf_counter() - clock) * 1e3
        if gaps:       # interpolated across: say so (the blade pitch turns once per revolution)
            self.diagnostics.count('window_gaps', '; '.join(gaps))
        desc = self.description
        if self.guess:
            desc = replace(desc, initial_guess={**desc.initial_guess, **self.guess})

        def progress(info):
            self.pub_progress.publish(progress_message(
                info, self.get_clock().now().to_msg()))
            if remember:
                self._remember(info['names'], info['values'])
            if not final and self._final_waiting():
                if self.provisional_published:
                    raise _Superseded
                return STOP               # the first growing-window estimate: publish it now
            return None

        started = time.perf_counter()
        try:
            # growing windows start from the latest iterate (or the description's guess) without
            # the multi-start grid; the final fit uses the grid only if there is no iterate yet
            # and the description does not give every starting value
            ident = identify(record, desc, progress=progress, window_s=window_s,
                             max_iter=max_iter or self.d['max_iter' if final
                                                         else 'max_iter_provisional'],
                             multi_start=final, step_tol=self.d['step_tol'])
        except _Superseded:
            return None
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            return self._failed(str(exc), window_s)
        ident.stamp0_ns = self.stamp0
        est = ident.estimate
        self.last_fit_s = time.perf_counter() - started
        timing['identify'] = self.last_fit_s * 1e3
        timing['gauss_newton'] = est.history[-1]['elapsed'] * 1e3 if est.history else 0.0
        timing['iterations'] = int(est.iterations)
        clock = time.perf_counter()
        if remember:
            self._remember(est.names, est.values)
        hurry = not final and self._final_waiting()
        if hurry and self.provisional_published:
            return None                   # the final fit is waiting: give way to it now
        std = np.array([est.std_of(n) for n in self.unknowns])
        verdict = data_length_verdict(std, self.targets)
        if not verdict[0] and not hurry:  # how much more data: from the M⁻¹(t_f) trend
            t, hist = bound_history(ident)
            verdict = data_length_verdict(std, self.targets, t, hist, ident.omega_rad_s)
        timing['verdict'] = (time.perf_counter() - clock) * 1e3
        clock = time.perf_counter()
        status = None if final else ParameterEstimate.STATUS_ITERATING
        note = (f'{"final" if final else "growing window (provisional)"}: '
                f'{window_s[0]:.4f}-{window_s[1]:.4f} s, {est.message}, '
                f'{self.last_fit_s * 1e3:.0f} ms'
                + ('' if not gaps else '; WARNING samples lost: ' + '; '.join(gaps)))
        msg = estimate_message(ident, self.get_clock().now().to_msg(), status, verdict,
                               self.d['frame_id'], note)
        self.diagnostics.set_value('last_estimate', ', '.join(
            f'{n}={v:.4g}±{s:.2g}' for n, v, s in zip(msg.names, msg.values, msg.std)))
        self.diagnostics.set_value('last_fit_ms', f'{self.last_fit_s * 1e3:.1f}')
        timing['message'] = (time.perf_counter() - clock) * 1e3
        if final:
            self.get_logger().info(f'final estimate: {self.diagnostics.values["last_estimate"]}'
                                   f' ({est.message}); target met: {verdict[0]}')
        return msg

    def _failed(self, reason, window_s):
        self.get_logger().warning(f'identification over {window_s} s failed: {reason}')
        msg = ParameterEstimate(status=ParameterEstimate.STATUS_FAILED, message=reason,
                                names=self.unknowns, additional_data_s=-1.0)
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.d['frame_id']
        msg.model = self.description.model
        return msg

    async def on_identify(self, request, response):
        """
        Identify.srv: fit the buffered data between the given bounds (0, 0 = all).

        The fit runs on the worker thread; the executor keeps taking sensor data meanwhile.
        """
        covered = self._covered_s()
        if covered is None:
            response.success, response.message = False, 'no data buffered yet'
            return response
        start = request.window_start_s
        end = request.window_end_s if request.window_end_s > 0 else covered
        if not (0 <= start < end <= covered + 1e-3):
            response.success = False
            response.message = (f'window [{start}, {end}] s is not inside the buffered '
                                f'[0, {covered:.4f}] s')
            return response
        future = Future(executor=self.executor)
        future.add_done_callback(lambda _: None)     # wakes the executor when the fit is done
        self._submit((start, end), True, future)
        msg = await future
        response.estimate = msg
        response.success = msg.status != ParameterEstimate.STATUS_FAILED
        response.message = msg.message
        if response.success:
            self.pub_estimate.publish(msg)
        return response

    def close(self):
        """Stop the worker thread; print the estimate latencies."""
        self.running = False
        with self.wake:
            self.wake.notify()
        self.worker.join(timeout=5.0)
        wait_for_acks([self.pub_estimate, self.pub_progress])
        print(f'identifier: estimate latencies (ms): '
              f'{" ".join(f"{v:.1f}" for v in self.latencies_ms)}', file=sys.stderr, flush=True)
        # one JSON line each: where the latency went, and the CPU the two threads used
        print(f'identifier: latency breakdown (ms): {json.dumps(self.breakdowns)}',
              file=sys.stderr, flush=True)
        threads = {'wall_s': time.monotonic() - self.created, 'samples_taken': self.taken}
        for name, (cpu, waiting) in (('executor', _thread_times()),     # (this is the executor)
                                     ('worker', self.worker_times)):
            threads[f'{name}_cpu_s'], threads[f'{name}_cpu_wait_s'] = cpu, waiting
        print(f'identifier: thread times: {json.dumps(threads)}', file=sys.stderr, flush=True)


def _breakdown_text(b):
    """One line of a latency breakdown (ms) for /diagnostics."""
    return (f'{b["total"]:.1f} = queued {b["queued"]:.1f} + record {b.get("record", 0):.1f} + '
            f'identify {b.get("identify", 0):.1f} (Gauss-Newton {b.get("gauss_newton", 0):.1f}, '
            f'{b.get("iterations", 0)} it) + verdict {b.get("verdict", 0):.1f} + message '
            f'{b.get("message", 0):.1f} + publish {b["publish"]:.1f} + other {b["other"]:.1f}; '
            f'worker on CPU {b["cpu"]:.1f}, waiting for a CPU {b["cpu_wait"]:.1f}, for the GIL '
            f'or the buffer lock {b["gil_or_lock_wait"]:.1f}; {b["samples_taken"]} samples '
            'taken meanwhile')


def main(args=None):
    """Run the node until SIGINT/SIGTERM (fits run on the node's worker thread)."""
    return spin_node(Identifier, args)


if __name__ == '__main__':
    raise SystemExit(main())
