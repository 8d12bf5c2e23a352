"""
Sensor intake of a live node: CPU per message, one executor callback each vs polled batches.

A publisher process sends ``--samples`` samples of the three sensor topics (4-blade flap and
pitch, azimuth) at 1 kHz; this process receives them in each mode, one after the other:

* callback: an rclpy subscription callback per message (deserialized JointState), as the
  identifier and the state estimator took them before;
* polled: :class:`rotor_id.nodes.polling.SensorPoller` every 2 ms, batches decoded and checked
  with :func:`rotor_id.nodes.polling.checked_joint_batch`, as they take them now;
* polled, 0.2 ms: the same at the identifier's period in a window's last 10 ms.

It measures this process's CPU per message (process_time from the first message to the last)
and, for the polled modes, the time from DDS reception to being taken. Writes
bench/results/sensor_intake.md.

    python bench/sensor_intake.py --samples 5000
"""

import argparse
import os
import subprocess
import sys
import time

from common import markdown_table, say, write_results
import numpy as np

BLADES = [f'blade_{k}' for k in range(1, 5)]
TOPICS = ('blade_flap', 'blade_pitch', 'azimuth')


def publish(samples):
    """Publish the three topics at 1 kHz, in 1 ms steps (the publisher process)."""
    import rclpy
    from rotor_id.nodes.common import joint_state, SENSOR_OFFER_QOS
    from sensor_msgs.msg import JointState
    rclpy.init()
    node = rclpy.create_node('intake_publisher')
    pubs = {t: node.create_publisher(JointState, f'intake/{t}', SENSOR_OFFER_QOS) for t in TOPICS}
    deadline = time.monotonic() + 20
    while (not all(p.get_subscription_count() for p in pubs.values())
           and time.monotonic() < deadline):
        time.sleep(0.05)
    time.sleep(0.5)
    start = time.monotonic()
    for k in range(samples):
        while time.monotonic() - start < k / 1000:
            time.sleep(0.0002)
        stamp = (k + 1) * 1_000_000
        pubs['blade_flap'].publish(joint_state(stamp, BLADES, [0.01] * 4))
        pubs['blade_pitch'].publish(joint_state(stamp, BLADES, [0.02] * 4))
        pubs['azimuth'].publish(joint_state(stamp, ['rotor'], [(k * 0.094) % 6.28], [94.2]))
    time.sleep(1.0)
    rclpy.try_shutdown()


def receive(mode, samples, domain):
    """Start a publisher, receive its messages in ``mode``; return the measurements."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rotor_id.nodes.common import SENSOR_BUFFER_QOS
    from rotor_id.nodes.polling import checked_joint_batch, SensorPoller
    from sensor_msgs.msg import JointState
    env = {**os.environ, 'ROS_DOMAIN_ID': str(domain)}
    publisher = subprocess.Popen([sys.executable, __file__, '--publish', str(samples)], env=env)
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('intake_receiver', context=context)
    got, delays = [0], []

    def batch(raws, infos):
        now = time.time_ns()
        checked_joint_batch(raws, BLADES if len(raws[0]) > 100 else ['rotor'], None)
        got[0] += len(raws)
        delays.extend((now - i['received_timestamp']) / 1e6 for i in infos)

    poller = None
    if mode == 'callback':
        for topic in TOPICS:
            node.create_subscription(JointState, f'intake/{topic}',
                                     lambda _m: got.__setitem__(0, got[0] + 1),
                                     SENSOR_BUFFER_QOS)
    else:
        poller = SensorPoller(node, 0.002 if mode == 'polled' else 0.0002)
        for topic in TOPICS:
            poller.subscribe(JointState, f'intake/{topic}', batch, SENSOR_BUFFER_QOS)
        poller.start()
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    deadline = time.monotonic() + 60
    while got[0] == 0 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    cpu0, wall0, first = time.process_time(), time.monotonic(), got[0]
    while got[0] < 3 * samples and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    cpu, wall, count = time.process_time() - cpu0, time.monotonic() - wall0, got[0] - first
    if poller is not None:
        poller.stop()
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)
    publisher.wait(30)
    delays = np.array(delays[100:]) if delays else np.array([np.nan])
    return {'mode': mode, 'messages': got[0], 'cpu_us': cpu / max(count, 1) * 1e6,
            'core': cpu / wall, 'delay_median': np.median(delays),
            'delay_p90': np.percentile(delays, 90)}


def main():
    """Measure each mode; write bench/results/sensor_intake.md."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--samples', type=int, default=5000)
    parser.add_argument('--publish', type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish is not None:
        publish(args.publish)
        return 0
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    domain = 111 + os.getpid() % 50
    rows = []
    for mode in ('callback', 'polled', 'polled_fast'):
        say(f'{mode}: {args.samples} samples x 3 topics at 1 kHz')
        r = receive(mode, args.samples, domain)
        rows.append([r['mode'], r['messages'], f'{r["cpu_us"]:.1f}', f'{100 * r["core"]:.0f}',
                     f'{r["delay_median"]:.2f}', f'{r["delay_p90"]:.2f}'])
    body = ('## Result\n\nOne receiving process, CPU from its first message to its last '
            '(process_time; the publisher is another process). *received -> taken*: from DDS '
            "reception (the message info's received_timestamp) to the poller's take (ms).\n\n"
            + markdown_table(['mode', 'messages', 'CPU per message (µs)', '% of a core',
                              'received -> taken median (ms)', 'p90 (ms)'], rows) + '\n')
    path = write_results('sensor_intake', 'Sensor intake: executor callbacks vs polled batches',
                         body, f'python bench/sensor_intake.py --samples {args.samples}')
    print(body)
    say(f'wrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
