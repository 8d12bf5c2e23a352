"""
Sensor samples taken in batches (the identifier's poller): same verdicts as one at a time.

What it proves: :func:`rotor_id.nodes.live.check_joint_batch` and ``check_azimuth_batch`` accept
exactly the samples that ``check_joint_sample`` / ``check_azimuth_sample`` accept when applied one
after the other (each accepted stamp becoming the last), on batches with non-finite values,
degrees, repeated and out-of-order stamps and bad rotor speeds mixed in; and, through DDS in this
process, that the :class:`rotor_id.nodes.polling.SensorPoller` hands over every message with its
send and receive times and keeps the executor asleep (its subscriptions are not in any wait
set), and that :func:`incompatible_publishers` names a best-effort publisher of a reliable
subscription.
"""

import math
import threading
import time

import numpy as np
import pytest
from ros_domains import next_domain
from rotor_id.nodes.live import (BadSample, check_azimuth_batch, check_azimuth_sample,
                                 check_joint_batch, check_joint_sample)

BLADES = ['blade_1', 'blade_2', 'blade_3', 'blade_4']


def _one_by_one(check, rows, last):
    """Apply a per-sample check in order; return the accepted mask and the last stamp."""
    accepted = []
    for stamp, args in rows:
        try:
            check(stamp, last, *args)
        except BadSample:
            accepted.append(False)
            continue
        accepted.append(True)
        last = stamp
    return np.array(accepted), last


@pytest.mark.parametrize('seed', range(6))
def test_joint_batch_accepts_what_one_at_a_time_accepts(seed):
    rng = np.random.default_rng(seed)
    n = 300
    stamps = np.cumsum(rng.integers(1, 3, n)) * 1_000_000
    # repeated and out-of-order stamps, NaN, degrees
    stamps[rng.integers(0, n, 20)] -= rng.integers(0, 5, 20) * 1_000_000
    values = rng.normal(0, 0.05, (n, 4))
    values[rng.integers(0, n, 8), rng.integers(0, 4, 8)] = np.nan
    values[rng.integers(0, n, 8), rng.integers(0, 4, 8)] = 20.0
    names = ['blade_3', 'blade_1', 'blade_4', 'blade_2']        # message order != wanted order
    order = [names.index(b) for b in BLADES]
    positions = np.empty_like(values)
    positions[:, order] = values
    last = int(stamps[5]) if seed % 2 else None
    got, accepted = check_joint_batch(names, positions, BLADES, stamps, last, 0.7)
    want, _ = _one_by_one(
        lambda stamp, last_, row: check_joint_sample(names, row, BLADES, stamp, last_, 0.7),
        [(int(s), (p,)) for s, p in zip(stamps, positions)], last)
    assert want.sum() > n // 2 and (~want).sum() > 10
    np.testing.assert_array_equal(accepted, want)
    np.testing.assert_array_equal(got[accepted], values[accepted])


def test_joint_batch_of_other_joints_accepts_none():
    stamps = np.arange(1, 6) * 1_000_000
    for names in (['blade_1', 'blade_2', 'blade_3'], ['a', 'b', 'c', 'd']):
        _, accepted = check_joint_batch(names, np.zeros((5, len(names))), BLADES, stamps, None)
        assert not accepted.any()


@pytest.mark.parametrize('convention', ['wrapped', 'unwrapped'])
def test_azimuth_batch_accepts_what_one_at_a_time_accepts(convention):
    rng = np.random.default_rng(7)
    n = 300
    stamps = np.cumsum(rng.integers(1, 3, n)) * 1_000_000
    stamps[rng.integers(0, n, 15)] -= rng.integers(0, 5, 15) * 1_000_000
    psi = 94.2 * stamps / 1e9 + 0.3
    if convention == 'wrapped':
        psi = np.mod(psi, 2 * math.pi)
        psi[rng.integers(0, n, 6)] = 200.0                          # degrees
    omega = np.full(n, 94.2)
    omega[rng.integers(0, n, 6)] = -1.0
    omega[rng.integers(0, n, 6)] = np.nan
    wrapped, speeds, accepted = check_azimuth_batch(['rotor'], psi[:, None], omega[:, None],
                                                    'rotor', stamps, None, convention)
    want, _ = _one_by_one(
        lambda stamp, last_, p, w: check_azimuth_sample(['rotor'], [p], [w], 'rotor', stamp,
                                                        last_, convention),
        [(int(s), (p, w)) for s, p, w in zip(stamps, psi, omega)], None)
    assert (~want).sum() > 10
    np.testing.assert_array_equal(accepted, want)
    expected = [check_azimuth_sample(['rotor'], [p], [w], 'rotor', 1, None, convention)
                for p, w in zip(psi[accepted], omega[accepted])]
    np.testing.assert_allclose(wrapped[accepted], [e[0] for e in expected], atol=1e-12)
    np.testing.assert_array_equal(speeds[accepted], [e[1] for e in expected])


def test_poller_takes_every_message_and_leaves_the_executor_asleep():
    rclpy = pytest.importorskip('rclpy', reason='rclpy not importable')
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rotor_id.io.jointstate_cdr import decode_batch
    from rotor_id.nodes.common import joint_state, SENSOR_OFFER_QOS
    from rotor_id.nodes.fit_process import thread_times
    from rotor_id.nodes.polling import incompatible_publishers, SensorPoller
    from sensor_msgs.msg import JointState

    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=next_domain(),
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('polled', context=context)
    test = rclpy.create_node('polling_test', context=context)
    batches = []
    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    poller = SensorPoller(node, 0.002)
    sub = poller.subscribe(JointState, 'polled_topic',
                           lambda raws, infos: batches.append((raws, infos)), reliable)
    pub = test.create_publisher(JointState, 'polled_topic', SENSOR_OFFER_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        poller.start()
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        sent_ns = time.time_ns()

        def publish():                                # 1 kHz for half a second
            for k in range(500):
                pub.publish(joint_state(1_000_000 * (k + 1), BLADES, [0.01 * k] * 4))
                time.sleep(0.001)
        publisher = threading.Thread(target=publish)
        cpu0, wall0 = thread_times()[0], time.monotonic()
        publisher.start()
        while sum(len(b[0]) for b in batches) < 500 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)       # nothing of the poller's wakes it
        spin_cpu, wall = thread_times()[0] - cpu0, time.monotonic() - wall0
        publisher.join()
        raws = [r for b in batches for r in b[0]]
        infos = [i for b in batches for i in b[1]]
        assert len(raws) == 500
        batch = decode_batch(raws)
        np.testing.assert_array_equal(batch.stamps_ns, 1_000_000 * np.arange(1, 501))
        np.testing.assert_allclose(batch.position[:, 0], 0.01 * np.arange(500))
        assert all(sent_ns - 1e9 < i['source_timestamp'] <= i['received_timestamp']
                   for i in infos)
        assert len(batches) < 500                     # taken in batches, not one by one
        # the executor slept through the messages (one woken by each, as by a subscription's
        # QoS event in its wait set, spun at 60-70 % of a core)
        assert spin_cpu < 0.2 * wall, f'executor thread: {spin_cpu:.2f} s CPU in {wall:.2f} s'
        assert incompatible_publishers(node, sub, reliable) == []
        test.create_publisher(JointState, 'polled_topic',
                              QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
        found = []
        while not found and time.monotonic() < deadline:
            time.sleep(0.05)
            found = incompatible_publishers(node, sub, reliable)
        assert [policy for _, policy in found] == ['RELIABILITY']
    finally:
        poller.stop()
        executor.shutdown()
        node.destroy_node()
        test.destroy_node()
        rclpy.try_shutdown(context=context)
