"""
Sensor subscriptions taken in batches by a thread of the node, not one executor callback each.

At 1 kHz x 3 topics an rclpy executor wakes, rebuilds its wait set and runs a Python callback
for every message: a third of a core for a node that reads the three sensor topics on this
project's 2-core machine; taken and decoded in batches, less than half of that
(bench/results/sensor_intake.md). A :class:`SensorPoller`
keeps the subscriptions out of the executor's wait set and takes whatever they queued, as
serialized CDR bytes, every ``period_s`` (or faster while the caller needs a prompt sample, e.g.
at the end of an identification window); the caller decodes a batch with numpy
(:mod:`rotor_id.io.jointstate_cdr`). Each message comes with its DDS source and reception
timestamps (system clock, ns), so the time from publication to being taken is measured.

``Subscription.handle.take_message`` is what rclpy's executor and ``wait_for_message`` call.
The subscriptions have no QoS event handlers: with Fast DDS an event in an executor's wait set
wakes it at every message of its subscription (measured: the executor thread then spun at 60-70 %
of a core while the poller took the data). A node that needs to know of publishers offering an
incompatible QoS asks the graph (:func:`incompatible_publishers`).
"""

import threading
import time

from rclpy.callback_groups import CallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rotor_id.io.jointstate_cdr import decode_batch, decode_one
from rotor_id.nodes.live import check_azimuth_batch, check_joint_batch


class _PolledGroup(CallbackGroup):
    """Keeps its entities out of every executor's wait set: the poller takes them."""

    def can_execute(self, entity):
        """Never."""
        return False

    def beginning_execution(self, entity):
        """Never."""
        return False


class SensorPoller:
    """
    Take the messages of some subscriptions in batches, from a thread.

    Parameters
    ----------
    node : rclpy.node.Node
    period_s : float
        Sleep between two takes when nothing needs a prompt sample.
    period_of : callable, optional
        ``period_of()`` -> s: the period to use now (e.g. shorter near a window's end).
    on_error : callable, optional
        ``on_error(exception)`` when a handler raises (the thread goes on).
    after_poll : callable, optional
        ``after_poll(count)`` after a pass that took ``count`` > 0 messages.

    """

    def __init__(self, node, period_s=0.002, period_of=None, on_error=None, after_poll=None,
                 max_batch=20000):
        self.node = node
        self.period_s = float(period_s)
        self.period_of = period_of
        self.on_error = on_error
        self.after_poll = after_poll
        self.max_batch = int(max_batch)
        self.group = _PolledGroup()
        self.entries = []                  # (subscription, handler)
        self.polls = 0
        self.taken = 0
        self._running = False
        self._thread = None

    def subscribe(self, msg_type, topic, handler, qos):
        """
        Subscribe to ``topic`` (raw); ``handler(raws, infos)`` gets each batch taken.

        ``infos`` are rmw message infos (dicts with 'source_timestamp' and 'received_timestamp',
        system clock ns).
        """
        subscription = self.node.create_subscription(
            msg_type, topic, lambda _msg: None, qos, raw=True, callback_group=self.group,
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        self.entries.append((subscription, handler))
        return subscription

    def start(self):
        """Start the polling thread."""
        self._running = True
        self._thread = threading.Thread(target=self._loop, name='sensor-poller', daemon=True)
        self._thread.start()

    def stop(self, timeout=2.0):
        """Stop the polling thread (after its current pass)."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout)

    def thread_times(self):
        """(CPU s, run-queue wait s) of the polling thread so far (nan when not running)."""
        from rotor_id.nodes.fit_process import thread_times
        thread = self._thread
        if thread is None or not thread.is_alive():
            return float('nan'), float('nan')
        return thread_times(thread.native_id)

    def _take(self, subscription):
        raws, infos = [], []
        try:
            with subscription.handle:
                while len(raws) < self.max_batch:
                    taken = subscription.handle.take_message(subscription.msg_type, True)
                    if taken is None:
                        break
                    raws.append(taken[0])
                    infos.append(taken[1])
        except Exception as exc:         # noqa: B902 - a destroyed handle at shutdown
            if self._running and self.on_error is not None:
                self.on_error(exc)
        return raws, infos

    def poll(self):
        """Take and hand over what every subscription queued; return how many messages."""
        count = 0
        for subscription, handler in self.entries:
            raws, infos = self._take(subscription)
            if not raws:
                continue
            count += len(raws)
            try:
                handler(raws, infos)
            except Exception as exc:     # noqa: B902 - a bad batch must not stop the node
                if self.on_error is None:
                    raise
                self.on_error(exc)
        self.polls += 1
        self.taken += count
        if count and self.after_poll is not None:
            try:
                self.after_poll(count)
            except Exception as exc:     # noqa: B902 - as a handler's
                if self.on_error is None:
                    raise
                self.on_error(exc)
        return count

    def _loop(self):
        while self._running:
            period = self.period_s
            try:
                if self.period_of is not None:
                    period = self.period_of()
                time.sleep(max(period, 1e-5))
                if self._running:
                    self.poll()
            except Exception as exc:     # noqa: B902 - the thread must go on taking samples
                if self.on_error is not None:
                    self.on_error(exc)
                time.sleep(self.period_s)


def incompatible_publishers(node, subscription, qos):
    """
    Return the publishers of a subscription's topic whose offer it cannot match.

    A list of (endpoint gid, policy name).

    Reliability is the policy that can fail for a volatile, keep-last subscription with the
    default deadline and liveliness (which every offer matches): a reliable request receives
    nothing from a best-effort publisher.
    """
    from rclpy.qos import ReliabilityPolicy
    if qos.reliability != ReliabilityPolicy.RELIABLE:
        return []
    return [(tuple(info.endpoint_gid), 'RELIABILITY')
            for info in node.get_publishers_info_by_topic(subscription.topic_name)
            if info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT]


def checked_joint_batch(raws, expected, last_stamp_ns, max_abs_rad=None):
    """
    Decode and check a batch of serialized JointState samples of one sensor topic.

    Returns (stamps (n,), values (n, len(expected))) when every message decodes with one
    layout and :func:`~rotor_id.nodes.live.check_joint_sample` would accept each in turn
    (other joints in the message allowed, as on a sensor topic); None otherwise: the caller
    then takes the batch one message at a time, so that each refusal keeps its reason.
    """
    batch = decode_batch(raws)
    if batch.kept.size != len(raws):
        return None
    values, accepted = check_joint_batch(batch.names, batch.position, expected,
                                         batch.stamps_ns, last_stamp_ns, max_abs_rad,
                                         extra_joints=True)
    return (batch.stamps_ns, values) if accepted.all() else None


def checked_azimuth_batch(raws, joint, last_stamp_ns, convention):
    """As :func:`checked_joint_batch` for the azimuth: (stamps, ψ in [0, 2π), Ω) or None."""
    batch = decode_batch(raws)
    if batch.kept.size != len(raws):
        return None
    psi, omega, accepted = check_azimuth_batch(batch.names, batch.position, batch.velocity,
                                               joint, batch.stamps_ns, last_stamp_ns,
                                               convention)
    return (batch.stamps_ns, psi, omega) if accepted.all() else None


def one_by_one(raws, diagnostics):
    """
    Decode serialized JointStates one at a time: yield (stamp, names, position, velocity).

    What does not decode is counted on ``diagnostics`` ('undecodable') and skipped.
    """
    for raw in raws:
        try:
            decoded = decode_one(raw)
        except ValueError as exc:
            diagnostics.count('undecodable', f'not a JointState: {exc}')
            continue
        yield decoded
