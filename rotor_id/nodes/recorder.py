"""
recorder: every topic of the run into a rosbag2 bag (``ros2 run rotor_id recorder``).

A ``ros2 bag record`` for this workspace (rosbag2 itself is not a wheel): raw (serialized)
subscriptions to every discovered topic (or the configured list), QoS adapted to the publishers
as rosbag2 does (reliable / transient-local only if every publisher offers it,
docs/ros_interfaces.md) but KEEP_ALL, the publishers' offered QoS stored in the bag, messages
written with :func:`rotor_id.io.bag.open_writer` (rosbags; MCAP by default, sqlite3 on request)
with every message definition embedded, rotor_id_msgs included, so mcap + mcap-ros2-support
decode it, and each topic's type hash (RIHS01, as the publishers advertise it) in metadata.yaml
and in the MCAP channel's ``topic_type_hash``, as rosbag2 writes them.

With a run description (parameter ``run_description``, docs/run_description.md) it records the
rig's topics (resolved in its namespace, so a recorder under ``/rig2`` records rig 2 only) and
/diagnostics, and copies the description beside the bag (``NAME/`` and ``NAME.yaml``, the
recording convention), so that ``rotor-id identify NAME/ NAME.yaml`` reads it the same way.
Without one, every topic discovered (or the ``topics`` list).

SIGINT and SIGTERM stop the recording: the node takes every message already delivered to it
(until the topics are quiet for ``drain_s``), then finalises the bag.
"""

import importlib
import os
from pathlib import Path
import sys
import time

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
try:
    from rclpy.experimental import EventsExecutor
except ImportError:          # rclpy without the events executor
    EventsExecutor = None
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rotor_id.io.bag import open_writer, typestore_with_custom_types
from rotor_id.nodes.common import (declare, Diagnostics, node_run_description, resolve_config,
                                   RUN_DESCRIPTION_HELP, spin_node)

_INFINITE_NS = 2**63 - 1


def message_class(type_name):
    """Python class of a ROS type 'pkg/msg/Name' (ImportError if not installed)."""
    package, kind, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def adapted_qos(offers):
    """Subscription QoS matching every publisher (rosbag2's adapt_request_to_offers), KEEP_ALL."""
    reliable = bool(offers) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offers)
    latched = bool(offers) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                   for q in offers)
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def _qos_time(duration):
    ns = duration.nanoseconds
    ns = _INFINITE_NS if ns <= 0 or ns >= _INFINITE_NS else ns
    return QosTime(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def bag_qos(profile):
    """Return the rosbags Qos of an offered rclpy QoSProfile (for metadata.yaml and MCAP)."""
    return Qos(history=QosHistory(int(profile.history)), depth=int(profile.depth),
               reliability=QosReliability(int(profile.reliability)),
               durability=QosDurability(int(profile.durability)),
               deadline=_qos_time(profile.deadline), lifespan=_qos_time(profile.lifespan),
               liveliness=QosLiveliness(int(profile.liveliness)),
               liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def advertised_type_hash(infos):
    """
    Return the RIHS01 type hash the publishers advertise ('RIHS01_<sha256>'), or ''.

    What rosbag2 stores as the topic's ``type_description_hash`` (and, in MCAP, as the
    channel's ``topic_type_hash``): the hash of the type the publishers actually use. '' when
    no publisher gives one (version 0: an RMW or a distribution without type hashes).
    """
    for info in infos:
        type_hash = getattr(info, 'topic_type_hash', None)
        if type_hash is not None and int(getattr(type_hash, 'version', 0)) > 0:
            return str(type_hash)
    return ''


class Recorder(Node):
    """Raw subscriptions to the run's topics, written to a bag as they arrive."""

    def __init__(self, **node_options):
        super().__init__('recorder', **node_options)
        spec = [
            ('run_description', '', RUN_DESCRIPTION_HELP + ' (empty: record every topic)'),
            ('output', '', 'bag directory to create (empty: rotor_id_<date>-<time> here)'),
            ('storage', 'mcap', 'storage plugin: mcap or sqlite3'),
            ('topics', [''], 'topics to record (empty: every topic discovered)'),
            ('exclude_topics', ['/rosout', '/parameter_events'], 'topics never recorded'),
            ('msg_dirs', [''], 'extra directories of .msg files of custom types'),
            ('discovery_period_s', 0.2, 'look for new topics this often (s)', 0.01, 10.0),
            ('drain_s', 1.0, 'on stop, keep taking messages until quiet this long (s)',
             0.0, 10.0),
            ('drain_max_s', 10.0, 'but stop draining after this long (s): publishers that go '
             'on forever', 0.0, 600.0),
        ]
        self.d = {s[0]: declare(self, s[0], s[1], s[2], *s[3:]) for s in spec}
        output = self.d['output'] or time.strftime('rotor_id_%Y%m%d-%H%M%S')
        self.wanted = [self.resolve_topic_name(t) for t in self.d['topics'] if t]
        self.exclude = set(self.d['exclude_topics'])
        description = None
        if self.d['run_description']:
            description = node_run_description(self.d['run_description'])
            if not self.wanted:
                rig_topics = {**description.topics, **description.node_topics}
                self.wanted = [self.resolve_topic_name(t) for t in rig_topics.values() if t]
                self.wanted.append('/diagnostics')
        store = typestore_with_custom_types(
            [resolve_config(p) if not Path(p).is_dir() else p for p in self.d['msg_dirs'] if p])
        self.writer = open_writer(output, self.d['storage'], store)
        self.path = Path(output).resolve()
        self.counts = {}
        self.subscriptions_by_topic = {}
        self.skipped = {}
        self.last_message = time.monotonic()
        self.diagnostics = Diagnostics(self, 'bag recording')
        self.diagnostics.set_value('bag', str(self.path))
        if description is not None:
            self._copy_description(description)
            for role in ('blade_pitch', 'blade_flap', 'azimuth'):
                if description.topics.get(role):
                    topic = self.resolve_topic_name(description.topics[role])
                    self.diagnostics.watch(topic, topic)
        else:
            self.diagnostics.watch('messages', 'any topic')
        self.create_timer(self.d['discovery_period_s'], self.discover)
        self.discover()
        self.get_logger().info(f'recording to {self.path} ({self.d["storage"]}); '
                               f'topics: {", ".join(self.wanted) or "all"}')

    def discover(self):
        """Subscribe to every new wanted topic once it has a publisher."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subscriptions_by_topic or topic in self.exclude or \
                    topic in self.skipped or (self.wanted and topic not in self.wanted):
                continue
            infos = self.get_publishers_info_by_topic(topic)
            offers = [info.qos_profile for info in infos]
            if not offers:
                continue
            type_name = types[0]
            try:
                cls = message_class(type_name)
                if type_name not in self.writer.typestore.fielddefs:
                    raise KeyError(type_name)
            except (ImportError, AttributeError, KeyError, ValueError) as exc:
                self.skipped[topic] = type_name
                self.diagnostics.count('unknown_type', f'{topic} ({type_name}): {exc}')
                continue
            store = self.writer.typestore
            conn = self.writer.writer.add_connection(
                topic, type_name, msgdef=store.generate_msgdef(type_name, ros_version=2)[0],
                rihs01=advertised_type_hash(infos) or store.hash_rihs01(type_name),
                offered_qos_profiles=[bag_qos(q) for q in offers])
            self.writer.connections[topic] = conn
            self.counts[topic] = 0
            self.subscriptions_by_topic[topic] = self.create_subscription(
                cls, topic, self._writer_for(topic), adapted_qos(offers), raw=True)
        self.diagnostics.set_value('messages', sum(self.counts.values()))
        self.diagnostics.set_value('topics', len(self.counts))

    def _copy_description(self, description):
        """Put the run description beside the bag (NAME.yaml), never over an existing file."""
        target = self.path.with_suffix('.yaml')
        if target.exists():
            self.diagnostics.problem('description', DiagnosticStatus.WARN,
                                     f'{target} exists: the run description was not copied')
            return
        target.write_text(Path(description.path).read_text(encoding='utf-8'), encoding='utf-8')
        self.diagnostics.set_value('run_description', str(target))

    def _writer_for(self, topic):
        stream = topic if topic in self.diagnostics.streams else 'messages'
        watched = stream in self.diagnostics.streams

        def write(data):
            self.writer.write_raw(topic, self.get_clock().now().nanoseconds, data)
            self.counts[topic] += 1
            self.last_message = time.monotonic()
            if watched:
                self.diagnostics.received(stream)
        return write

    def close(self):
        """Finalise the bag (index, metadata.yaml) and print what it holds."""
        if self.writer is None:
            return
        self.writer.close()
        self.writer = None
        lines = [f'recorder: bag {self.path} finalised:'] + [
            f'  {topic}: {count} messages' for topic, count in sorted(self.counts.items())]
        print('\n'.join(lines), file=sys.stderr, flush=True)


def _events_executor():
    # the C++ events executor takes a message for a fraction of the Python executor's CPU:
    # what lets one Python process record 4 blades x 1 kHz on a busy machine
    return EventsExecutor() if EventsExecutor is not None else SingleThreadedExecutor()


def _drain(node, executor):
    """Take everything already delivered before finalising the bag."""
    # quiet = no message for drain_s since draining began, not since the last one before the
    # signal
    node.last_message = time.monotonic()
    deadline = node.last_message + node.d['drain_max_s']
    while time.monotonic() - node.last_message < node.d['drain_s'] and \
            time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)


def main(args=None):
    """Record until SIGINT/SIGTERM, then drain what was delivered and finalise the bag."""
    return spin_node(Recorder, args, executor_factory=_events_executor, after_stop=_drain,
                     runtime_errors=(ValueError, OSError))


if __name__ == '__main__':
    os.environ.setdefault('PYTHONUNBUFFERED', '1')
    raise SystemExit(main())
