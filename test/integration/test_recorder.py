"""
The recorder loses nothing and survives being stopped (CI-sized; pins #7).

This process publishes the test-stand topics (JointState, best effort, ~1 kHz) and every
rotor_id_msgs type plus a latched topic to a recorder running as its own process. Stopped with
SIGINT after the last message, the bag must hold exactly what was published (both storages);
stopped with SIGINT or SIGTERM in the middle of a stream, it must hold every message published
before the signal, gap-free, and open in ``rotor_id.io.bag.read_record`` and the independent
mcap reader. The 10-minute version is bench/live_latency.py.
"""

import math
import signal
import time

from live_helpers import domain_id, mcap_messages, require_workspace, RosClient
import numpy as np
import pytest
import yaml

OMEGA = 30 * math.pi
BLADES = ['blade_1', 'blade_2', 'blade_3', 'blade_4']


class Stand:
    """Publishers of a fake test stand and of every rotor_id_msgs type, in this process."""

    def __init__(self, node):
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from rotor_id.nodes.common import SENSOR_QOS, STATE_QOS
        from rotor_id_msgs.msg import (IdentificationProgress, ParameterEstimate, StateEstimate,
                                       StirringCommand)
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        self.node = node
        self.sensors = {name: node.create_publisher(JointState, f'/rotor/{name}', SENSOR_QOS)
                        for name in ('blade_flap', 'blade_pitch', 'azimuth')}
        self.custom = {
            '/rotor_id/estimate': (node.create_publisher(ParameterEstimate, '/rotor_id/estimate',
                                                         STATE_QOS), ParameterEstimate),
            '/rotor_id/state': (node.create_publisher(StateEstimate, '/rotor_id/state',
                                                      STATE_QOS), StateEstimate),
            '/rotor/stirring': (node.create_publisher(StirringCommand, '/rotor/stirring',
                                                      STATE_QOS), StirringCommand),
            '/rotor_id/progress': (node.create_publisher(IdentificationProgress,
                                                         '/rotor_id/progress', STATE_QOS),
                                   IdentificationProgress),
        }
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.latched = node.create_publisher(String, '/rotor/config', latched)
        self.latched.publish(String(data='rotor: {blades: 4}'))
        self.count = 0

    def publishers(self):
        """Every publisher (to wait until the recorder has subscribed to each)."""
        return list(self.sensors.values()) + [p for p, _ in self.custom.values()] + \
            [self.latched]

    def publish_sample(self):
        """One 1 kHz sample on the three sensor topics (sequence number in flap[0], µrad)."""
        from rotor_id.nodes.common import joint_state
        k = self.count
        stamp = 10**18 + k * 1_000_000
        psi = math.fmod(OMEGA * k * 1e-3, 2 * math.pi)
        self.sensors['blade_flap'].publish(joint_state(stamp, BLADES, [k * 1e-6, 0.0, 0.0, 0.0]))
        self.sensors['blade_pitch'].publish(joint_state(stamp, BLADES, [0.03] * 4))
        self.sensors['azimuth'].publish(joint_state(stamp, ['rotor'], [psi], [OMEGA]))
        if k % 50 == 0:
            for publisher, cls in self.custom.values():
                msg = cls()
                if hasattr(msg, 'names'):
                    msg.names = ['A', 'AL_over_tau']
                if hasattr(msg, 'values'):
                    msg.values = [0.5, float(k)]
                publisher.publish(msg)
        self.count += 1


def _start(tmp, storage):
    from rotor_id.nodes.processes import isolated_env, NodeProcesses
    domain = domain_id()
    ros = RosClient(domain)
    stand = Stand(ros.node)
    procs = NodeProcesses(isolated_env(domain, tmp / 'ros_log'), tmp / 'logs')
    procs.start('recorder', params={'output': str(tmp / 'bag'), 'storage': storage,
                                    'discovery_period_s': 0.1})
    import rclpy
    deadline = time.monotonic() + 60.0
    while not all(p.get_subscription_count() >= 1 for p in stand.publishers()):
        assert time.monotonic() < deadline and not procs.dead(), procs.log('recorder')
        rclpy.spin_once(ros.node, timeout_sec=0.05)
    time.sleep(0.5)
    return ros, stand, procs


def _publish(stand, n, rate_hz=1000.0):
    start = time.monotonic()
    for _ in range(n):
        stand.publish_sample()
        delay = start + stand.count / rate_hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def mcap_type_hashes(bag):
    """Return topic -> the ``topic_type_hash`` of its MCAP channel (the mcap package reads it)."""
    from mcap.reader import make_reader
    with open(next(bag.glob('*.mcap')), 'rb') as stream:
        channels = make_reader(stream).get_summary().channels.values()
        return {c.topic: c.metadata.get('topic_type_hash') for c in channels}


def _bag_counts(bag):
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    return meta, {t['topic_metadata']['name']: t['message_count']
                  for t in meta['topics_with_message_count']}


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_recorder_loses_nothing(tmp_path, storage):
    require_workspace()
    from rotor_id.io.bag import read_record
    ros, stand, procs = _start(tmp_path, storage)
    try:
        _publish(stand, 1500)
        time.sleep(0.5)
        advertised = {topic: str(ros.node.get_publishers_info_by_topic(topic)[0]
                                 .topic_type_hash)
                      for topic in ('/rotor/blade_flap', '/rotor_id/estimate', '/rotor/config')}
        code = procs.stop('recorder', signal.SIGINT)
    finally:
        procs.stop_all(last=())
        ros.close()
    assert code == 0, procs.log('recorder')
    meta, counts = _bag_counts(tmp_path / 'bag')
    assert meta['storage_identifier'] == storage
    for topic in ('/rotor/blade_flap', '/rotor/blade_pitch', '/rotor/azimuth'):
        assert counts[topic] == 1500, (topic, counts)
    for topic in ('/rotor_id/estimate', '/rotor_id/state', '/rotor/stirring',
                  '/rotor_id/progress'):
        assert counts[topic] == 30, (topic, counts)
    assert counts['/rotor/config'] == 1
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
           for t in meta['topics_with_message_count']}
    assert qos['/rotor/blade_flap'][0]['reliability'] == 'best_effort'
    assert qos['/rotor/config'][0]['durability'] == 'transient_local'
    assert qos['/rotor_id/estimate'][0]['reliability'] == 'reliable'
    # the type hash the publishers advertise, as rosbag2 stores it (metadata and MCAP channel)
    hashes = {t['topic_metadata']['name']: t['topic_metadata']['type_description_hash']
              for t in meta['topics_with_message_count']}
    assert all(h.startswith('RIHS01_') and len(h) == 7 + 64 for h in advertised.values())
    assert {topic: hashes[topic] for topic in advertised} == advertised
    if storage == 'mcap':
        assert {topic: h for topic, h in mcap_type_hashes(tmp_path / 'bag').items()
                if topic in advertised} == advertised
    record = read_record(tmp_path / 'bag')
    assert len(record) == 1500
    assert np.array_equal(np.round(record.blade_flap[:, 0] * 1e6), np.arange(1500))
    if storage == 'mcap':
        decoded = mcap_messages(tmp_path / 'bag')
        assert len(decoded['/rotor_id/estimate']) == 30
        assert list(decoded['/rotor_id/estimate'][-1].names) == ['A', 'AL_over_tau']
        assert decoded['/rotor_id/state'][-1].values[1] == 1450.0


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_signal_mid_run_keeps_every_message_up_to_the_stop(tmp_path, signum):
    require_workspace()
    from rotor_id.io.bag import read_record
    ros, stand, procs = _start(tmp_path, 'mcap')
    try:
        _publish(stand, 1000)
        published_before = stand.count
        procs.procs['recorder'].send_signal(signum)
        _publish(stand, 300)                       # the stream goes on after the signal
        code = procs.stop('recorder', signum)
    finally:
        procs.stop_all(last=())
        ros.close()
    assert code == 0, procs.log('recorder')
    decoded = mcap_messages(tmp_path / 'bag')
    seq = np.round([m.position[0] * 1e6 for m in decoded['/rotor/blade_flap']]).astype(int)
    assert seq.size >= published_before, (seq.size, published_before)
    assert np.array_equal(seq, np.arange(seq.size)), 'messages missing or out of order'
    record = read_record(tmp_path / 'bag')
    assert len(record) == seq.size
