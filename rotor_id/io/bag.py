"""
Read and write rosbag2 recordings of the test stand (MCAP or sqlite3) with ``rosbags``.

The recording convention (docs/run_description.md): three ``sensor_msgs/msg/JointState`` topics,
``header.stamp`` = acquisition time,

* /rotor/blade_pitch: joints blade_1..blade_N, position = blade pitch, rad;
* /rotor/blade_flap: joints blade_1..blade_N, position = flap angle (up positive), rad;
* /rotor/azimuth: joint 'rotor', position = ψ of blade_1 wrapped to [0, 2π), velocity = Ω.

:func:`read_record` turns such a bag into a :class:`~rotor_id.io.record.Record` on the flap
stamps. Damaged input raises :class:`BagError` with a message that says what to do; what can be
repaired (NaN samples, out-of-order or repeated stamps, a recording cut short) is repaired,
counted in ``record.warnings`` and announced once as a :class:`BagWarning`; each reading
replaced is listed in ``record.repairs``.

Every read goes through the rosbags Reader: a bag directory of one or several storage files
(a split bag: ``ros2 bag record --max-bag-duration/--max-bag-size``), MCAP or sqlite3, and a
window of a long bag as a receive-time range from rosbag2's own index (the MCAP chunk index,
the sqlite3 timestamp index). Two parts stay hand-written, each because a measurement shows
the library cannot do its job (bench/results/bag_reading.md, ``python bench/bag_reading.py``):

* decoding JointState messages into arrays (:func:`rotor_id.io.jointstate_cdr.decode_batch`,
  vectorised): 22× less CPU than rosbags' ``deserialize_cdr`` one message at a time, which
  would take most of a 10-minute bag's 200×-real-time budget;
* salvaging a damaged MCAP (:func:`rotor_id.io.mcap_recover.scan_mcap`): of a recording cut
  at 60 % of its bytes, rosbags reads 0 messages ("File end magic is invalid"), the scan
  108 177 of the 180 000.

(The ``mcap`` package reads the same window 4.4× slower than rosbags, so rosbags is the one
library used.)
"""

from contextlib import suppress
from dataclasses import dataclass, field
from io import BytesIO
import os
from pathlib import Path
import re
from types import TracebackType
from typing import Any, cast, Iterable, Literal, Mapping, Sequence, TYPE_CHECKING
import warnings
import xml.etree.ElementTree as ElementTree

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import Channel, McapWriter, write_channel, write_string
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from rotor_id.io.errors import BagError, BagWarning
from rotor_id.io.jointstate_cdr import decode_batch, encode_batch, JOINT_STATE
from rotor_id.io.mcap_recover import scan_mcap, zstd
from rotor_id.io.record import Record, Repair
from rotor_id.io.run_description import (DEFAULT_AZIMUTH_JOINT, DEFAULT_TOPICS,
                                         normalize_joint_names, recorded_topic, RunDescription,
                                         validate_window)
from rotor_id.io.streams import (
    interleaved_streams, phase_outliers, repair_value_spikes, spikes, split_runs,
    stuck_channels,
)
from rotor_id.io.timebase import interpolate_columns, nondimensional_time, TWO_PI, wrap_azimuth
from rotor_id.numpy_compat import trapezoid
import yaml

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.typesys.store import Typestore

__all__ = [
    'BagError', 'BagWarning', 'BagWriter', 'DEFAULT_TOPICS', 'open_writer', 'read_messages',
    'read_record', 'read_run', 'register_msg_dir', 'typestore_with_custom_types',
    'write_record_bag',
]

MAX_ANGLE_RAD = 1.0     # |flap| or |pitch| above this: the recording is taken to be in degrees
GAP_FACTOR = 1.5        # a step longer than this many median sample periods is a gap
RATE_TOLERANCE = 0.05   # relative disagreement allowed between Ω and the azimuth's rate
SHARED_STAMP_FRACTION = 0.05  # more samples than this sharing a stamp with other values: 2 sources
SPEED_SPIKE_FRACTION = 0.05   # a rotor-speed sample this far (relative) from its neighbours: spike
PHASE_FLOOR_FRACTION = 0.25   # azimuth off its predicted phase by this much of a sample's advance
# Reading only the window of a long MCAP (memory follows the window, not the bag):
WINDOW_READ_MIN_BYTES = 64_000_000   # smaller bags are read whole, with every check
WINDOW_READ_HEAD_S = 0.5             # receive time read at the start to find the first stamp
WINDOW_READ_MARGIN_S = 2.0           # read this much either side of the window
WINDOW_READ_CLOCK_TOLERANCE_S = 1.0  # stamp-to-receive offset drift allowed over the bag
WINDOW_READ_MAX_FRACTION = 0.5       # a window needing more of the bag reads it all
WINDOW_READ_TAIL_S = 1.0             # receive time read at the end to check the clock
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
SUFFIXES = {'.mcap': 'mcap', '.db3': 'sqlite3'}
COMPRESSION_FORMATS = ('zstd',)    # what rosbag2's file/message compression may use here
_ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'
_NS = 1_000_000_000


# --------------------------------------------------------------------------- locating the bag

@dataclass
class _Bag:
    """A located bag: what rosbags opens, its storage files and what metadata.yaml says."""

    open_path: Path             # the directory (with metadata.yaml) or the storage file
    storage: str                # 'mcap' or 'sqlite3'
    files: list                 # storage files, in recording order
    counts: dict = field(default_factory=dict)   # topic -> messages listed in metadata.yaml
    facts: dict = field(default_factory=dict)    # 'compression', 'publishers'

    @property
    def label(self):
        """Name the storage file, or the directory and its number of files (split bags)."""
        if len(self.files) == 1:
            return self.files[0]
        return f'{self.open_path} ({len(self.files)} {self.storage} files)'

    @property
    def size(self):
        """Bytes of all storage files."""
        return sum(f.stat().st_size for f in self.files)

    @property
    def compressed_whole(self):
        """Tell whether the storage files are compressed whole (rosbag2 file compression)."""
        return any('.zstd' in f.suffixes for f in self.files)


def _resolve(bag_path):
    """Locate the bag (a directory with metadata.yaml, its metadata.yaml, or one file)."""
    path = Path(bag_path)
    if not path.exists():
        raise BagError(f'bag {path} does not exist; give a bag directory (with metadata.yaml) '
                       'or its .mcap / .db3 file')
    if path.is_file() and path.name == 'metadata.yaml':
        path = path.parent
    if path.is_dir():
        if (path / 'metadata.yaml').is_file():
            return _resolve_metadata(path)
        files = sorted(p for p in path.iterdir() if p.suffix in SUFFIXES)
        if len(files) != 1:
            raise BagError(
                f'{path} is not a bag: no metadata.yaml and {len(files)} .mcap/.db3 files '
                f'({[p.name for p in files]}); give the bag directory written by ros2 bag '
                'record (a split bag needs its metadata.yaml) or the storage file itself')
        path = files[0]
    if path.suffix not in SUFFIXES:
        raise BagError(f'{path} is not a bag: expected a directory, metadata.yaml, or a '
                       f'.mcap / .db3 file, got suffix {path.suffix!r}')
    if path.stat().st_size == 0:
        raise BagError(f'bag file {path} is empty (0 bytes); the recording wrote nothing')
    return _Bag(path, SUFFIXES[path.suffix], [path])


def _publisher_count(topic_metadata):
    """Count the publishers the recorder saw on a topic (one offered QoS profile each)."""
    profiles = topic_metadata.get('offered_qos_profiles') or []
    if isinstance(profiles, str):           # metadata versions before 9 hold a YAML string
        with suppress(yaml.YAMLError):
            profiles = yaml.safe_load(profiles) or []
    return len(profiles) if isinstance(profiles, list) else 0


def _resolve_metadata(directory):
    meta_path = directory / 'metadata.yaml'
    try:
        info = yaml.safe_load(meta_path.read_text(encoding='utf-8'))['rosbag2_bagfile_information']
        storage = info['storage_identifier']
        files = [directory / Path(name).name for name in info['relative_file_paths']]
        listed = info.get('topics_with_message_count') or []
        counts = {t['topic_metadata']['name']: int(t['message_count']) for t in listed}
        facts = {
            'compression': (str(info.get('compression_mode') or '').lower(),
                            str(info.get('compression_format') or '').lower()),
            'publishers': {t['topic_metadata']['name']: _publisher_count(t['topic_metadata'])
                           for t in listed},
        }
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError, ValueError) as err:
        raise BagError(f'{meta_path} is not rosbag2 metadata ({type(err).__name__}: {err}); '
                       'repair it, or give the .mcap / .db3 file instead of the directory') \
            from None
    if storage not in STORAGES:
        raise BagError(f'{meta_path}: storage {storage!r} is not supported; use mcap or sqlite3')
    mode, fmt = facts['compression']
    if mode and mode != 'none' and fmt not in COMPRESSION_FORMATS:
        raise BagError(f'{meta_path}: rosbag2 {mode}-level compression with format {fmt!r} is '
                       f'not supported (only {", ".join(COMPRESSION_FORMATS)}); decompress the '
                       'bag first, e.g. ros2 bag convert with an output without compression')
    missing = [f.name for f in files if not f.is_file()]
    if missing or not files:
        raise BagError(f'{meta_path} lists storage files {[f.name for f in files]}; '
                       f'missing: {missing}. Copy the whole bag directory (every file a split '
                       'recording wrote), or give one storage file to read it alone')
    empty = [f.name for f in files if f.stat().st_size == 0]
    if empty:
        raise BagError(f'bag file(s) {empty} of {directory} are empty (0 bytes); the recording '
                       'wrote nothing there')
    return _Bag(directory, storage, files, counts, facts)


# -------------------------------------------------------------------------- raw messages

class _Raw:
    """Raw CDR messages of the wanted topics, plus what was found in the bag."""

    def __init__(self):
        self.available = {}   # topic -> message type
        self.data = {}        # topic -> list of bytes
        self.log_ns = {}      # topic -> list of receive times
        self.notes = []
        self.bag_start_ns = None   # first receive time of the bag, when only a part is read


def _read_raw(bag, wanted, omega_rad_s):
    """
    Read every message of the wanted topics with rosbags (all files of a split bag).

    A damaged MCAP (cut short, bad checksums) is salvaged by scanning its files
    (:mod:`rotor_id.io.mcap_recover`) when that recovers more than rosbags read.
    """
    raw = _Raw()
    try:
        reader = Reader(bag.open_path)
        reader.open()
    except Exception as err:  # noqa: B902 - rosbags/apsw raise many types for bad files
        if bag.storage == 'mcap':
            return _recover_mcap(bag, wanted, err, omega_rad_s)
        raise BagError(f'{bag.label} cannot be opened as a {bag.storage} bag '
                       f'({type(err).__name__}: {err}); the file is not a rosbag2 recording '
                       'or is damaged (a damaged .db3 may be salvaged into a new file with the '
                       '.recover command of the sqlite3 shell)') from None
    try:
        raw.available = {c.topic: c.msgtype for c in reader.connections}
        _check_topics(raw, wanted, bag.label, omega_rad_s)
        connections = [c for c in reader.connections if c.topic in wanted.values()]
        buckets = {c.id: raw.data.setdefault(c.topic, []) for c in connections}
        times = {c.id: raw.log_ns.setdefault(c.topic, []) for c in connections}
        count = 0
        try:
            for connection, log_ns, data in reader.messages(connections):
                buckets[connection.id].append(data)
                times[connection.id].append(log_ns)
                count += 1
        except Exception as err:  # noqa: B902 - damaged storage; keep what was read
            if bag.storage == 'mcap':
                recovered = _recover_mcap(bag, wanted, err, omega_rad_s)
                if sum(map(len, recovered.data.values())) > count:
                    return recovered
            raw.notes.append(
                f'{bag.label} is damaged after {count} messages ({type(err).__name__}: '
                f'{err}); the {count} messages read before the damage are used')
    finally:
        with suppress(Exception):
            reader.close()
    return raw


#: rosbag2 receive times are signed 64-bit nanoseconds; a larger one is a damaged record.
_LAST_RECEIVE_NS = 2**63 - 1


def _drop_impossible_receive_times(raw, storage_file):
    """Drop messages whose receive time cannot be a time (damaged records), with a note."""
    for topic, times in raw.log_ns.items():
        bad = [k for k, ns in enumerate(times)
               if not isinstance(ns, int) or not 0 <= ns <= _LAST_RECEIVE_NS]
        if not bad:
            continue
        keep = sorted(set(range(len(times))) - set(bad))
        raw.log_ns[topic] = [times[k] for k in keep]
        raw.data[topic] = [raw.data[topic][k] for k in keep]
        raw.notes.append(
            f'{storage_file}: {len(bad)} message(s) on {topic} carry no receive time or one '
            f'outside the 64-bit range (first at message {bad[0]}): damaged records, dropped')


def _recover_mcap(bag, wanted, error, omega_rad_s):
    """Read what a damaged MCAP still holds, file by file (:mod:`rotor_id.io.mcap_recover`)."""
    scans = []
    for storage_file in bag.files:
        try:
            scans.append(scan_mcap(storage_file))
        except (OSError, ValueError) as err:
            raise BagError(f'{bag.label} cannot be opened as an MCAP bag ({error}) and '
                           f'{storage_file.name} is not recoverable ({err}); the file is not a '
                           'rosbag2 recording') from None
    raw = _Raw()
    for scan in scans:
        raw.available.update(scan.topics())
    _check_topics(raw, wanted, bag.label, omega_rad_s)
    for topic in wanted.values():
        messages = [m for scan in scans for m in scan.topic_messages(topic)]
        raw.log_ns[topic] = [m[0] for m in messages]
        raw.data[topic] = [m[1] for m in messages]
    problems = '; '.join(f'{f.name}: {scan.problem}' for f, scan in zip(bag.files, scans)
                         if scan.problem) or 'no index'
    if not any(raw.data.values()):
        raise BagError(f'{bag.label} is damaged ({error}; {problems}) and no message of '
                       f'{sorted(wanted.values())} could be recovered') from None
    skipped = sum(scan.skipped_chunks for scan in scans)
    raw.notes.append(
        f'{bag.label} is damaged ({error}); {problems}: recovered '
        f'{sum(map(len, raw.data.values()))} messages by scanning the file'
        + (f', skipped {skipped} chunk(s) with bad checksums' if skipped else ''))
    return raw


class _WantedTopics:
    """``topic in wanted``: a relative name matches in the root or any namespace."""

    def __init__(self, names):
        self.names = set(names)

    def __contains__(self, topic):
        return topic in self.names or any(
            not name.startswith('/') and (topic == '/' + name or topic.endswith('/' + name))
            for name in self.names)


def _check_topics(raw, wanted, storage_file, omega_rad_s):
    """Check that the wanted topics are JointState; without azimuth, fall back on Ω."""
    available = raw.available
    for role, topic in wanted.items():       # relative names: root, else the one namespace
        wanted[role] = recorded_topic(topic, available) or topic
    if 'azimuth' in wanted and wanted['azimuth'] not in available and omega_rad_s is not None:
        raw.notes.append(f'azimuth topic {wanted.pop("azimuth", None)} not in the bag')
    for role, topic in wanted.items():
        if topic not in available:
            hint = ' (or pass omega_rad_s if no azimuth was recorded)' if role == 'azimuth' else ''
            raise BagError(
                f'topic {topic} ({role}) is not in {storage_file}; topics there: '
                f'{sorted(available) or "none"}. Set topics.{role} in the run description{hint}')
        if available[topic] != JOINT_STATE:
            raise BagError(
                f'topic {topic} ({role}) has message type {available[topic]}, expected '
                f'{JOINT_STATE}; check topics.{role} in the run description')


# --------------------------------------------------------------------------- cleaning

@dataclass
class _Context:
    """What one read of a bag collects while it cleans the topics."""

    raw: _Raw
    issues: list
    run: object = None                  # 1-based run asked for, or None
    publishers: dict = field(default_factory=dict)
    several_runs: bool = False
    faults: list = field(default_factory=list)   # (stamp_ns, message): judged by the window
    frame_ids: dict = field(default_factory=dict)  # topic -> {header.frame_id: messages}
    origin_ns: object = None            # first flap stamp, for times in messages
    repairs: list = field(default_factory=list)  # (topic, joint, stamp_ns, old, new, why)

    def when(self, stamp_ns):
        """Format a stamp as seconds of record time (after the first flap stamp)."""
        if self.origin_ns is None:
            return f'stamp {stamp_ns / _NS:.6f} s'
        return f'{(stamp_ns - self.origin_ns) / _NS:.4f} s'

    def message(self, topic, index):
        """'message i of n, received x s into the bag' of a topic's message number."""
        log = self.raw.log_ns.get(topic)
        n = len(self.raw.data.get(topic, ()))
        partial = self.raw.bag_start_ns is not None
        text = 'the message' if partial else f'message {index + 1} of {n}'
        if log is not None and len(log) > index:
            start = self.raw.bag_start_ns if partial else min(
                int(v[0]) for v in self.raw.log_ns.values() if len(v))
            text += f', received {(int(log[index]) - start) / _NS:.3f} s into the bag'
        return text


@dataclass
class _Samples:
    """One topic's cleaned samples, sorted by stamp."""

    stamps: np.ndarray
    names: tuple
    position: np.ndarray
    velocity: object             # (n, k) or None
    message: np.ndarray          # message number of each sample, in recording order
    frame_ids: dict | None = None  # header.frame_id -> messages


def _topic_samples(ctx, topic, role, with_velocity):
    """
    Decode one topic, drop what cannot be used, select the run, sort and check the stream.

    Returns
    -------
    _Samples.

    """
    raw, issues = ctx.raw, ctx.issues
    messages = raw.data.get(topic, [])
    if not len(messages):
        raise BagError(f'topic {topic} ({role}) has no messages in the bag: the recording is '
                       'empty; record the test again')
    batch = decode_batch(messages)
    for reason, count in batch.dropped.items():
        issues.append(f'{topic}: dropped {count} message(s): {reason}')
    if not len(batch.stamps_ns):
        raise BagError(f'topic {topic} ({role}): none of its {len(messages)} messages could be '
                       'decoded as sensor_msgs/msg/JointState (CDR); the messages are damaged '
                       'or were written as another type under this topic name')
    stamps, position, velocity = batch.stamps_ns, batch.position, batch.velocity
    sent, message = batch.velocity_sent, batch.kept
    unfilled = stamps == 0
    if np.count_nonzero(unfilled) > len(stamps) // 2:
        issues.append(f'{topic}: header.stamp is not filled (zero); the receive time is used '
                      'instead, which adds transport jitter: fill header.stamp at acquisition')
        stamps = np.asarray(raw.log_ns[topic], dtype=np.int64)[batch.kept]
    elif unfilled.any():
        issues.append(f'{topic}: dropped {np.count_nonzero(unfilled)} sample(s) whose '
                      'header.stamp is not filled (zero)')
        keep = ~unfilled
        stamps, position, velocity, sent, message = (
            a[keep] for a in (stamps, position, velocity, sent, message))
    finite = np.isfinite(position).all(axis=1)
    if not finite.all():
        issues.append(f'{topic}: dropped {np.count_nonzero(~finite)} sample(s) whose position '
                      'is NaN/inf')
        stamps, position, velocity, sent, message = (
            a[finite] for a in (stamps, position, velocity, sent, message))
    if not len(stamps):
        raise BagError(f'topic {topic} ({role}): the position of every sample is NaN or inf; '
                       'check the sensor')
    if with_velocity:
        usable = sent & np.isfinite(velocity).all(axis=1)
        if not usable.any():
            with_velocity = False
        else:
            if not sent.all():
                issues.append(f'{topic}: {np.count_nonzero(~sent)} message(s) carry no velocity '
                              '(rotor speed); it is interpolated there from the neighbouring '
                              'samples')
            if (sent & ~usable).any():
                issues.append(f'{topic}: {np.count_nonzero(sent & ~usable)} sample(s) have a '
                              'NaN/inf velocity (rotor speed); it is interpolated there from '
                              'the neighbouring samples')
            velocity = np.where(usable[:, None], velocity, np.nan)
    stamps, position, velocity, message = _select_run(
        ctx, topic, role, stamps, position, velocity, message)
    backwards = np.count_nonzero(np.diff(stamps) < 0)
    if backwards:
        order = np.argsort(stamps, kind='stable')
        stamps, position, velocity, message = (a[order] for a in
                                               (stamps, position, velocity, message))
        issues.append(f'{topic}: {backwards} stamp(s) out of order; samples sorted by '
                      'header.stamp')
    ctx.frame_ids[topic] = batch.frame_ids or {}
    stamps, position, velocity, message = _repeated_stamps(
        ctx, topic, role, stamps, position, velocity, message)
    if role in ('blade_flap', 'blade_pitch'):
        _repair_value_spikes(ctx, topic, role, stamps, position, batch.names)
    _check_one_stream(ctx, topic, role, stamps, position)
    if with_velocity:
        missing = np.isnan(velocity).any(axis=1)
        if missing.all():
            with_velocity = False
        elif missing.any():
            for column in range(velocity.shape[1]):
                velocity[missing, column] = np.interp(stamps[missing], stamps[~missing],
                                                      velocity[~missing, column])
    return _Samples(stamps, batch.names, position, velocity if with_velocity else None, message)


def _select_run(ctx, topic, role, stamps, position, velocity, message):
    """Drop clock glitches; with several runs (clock resets), keep the one asked for."""
    received = ctx.raw.log_ns.get(topic)
    split = split_runs(stamps, None if received is None or not len(received)
                       else np.asarray(received, dtype=np.int64)[message])
    keep = split.labels >= 0
    glitches = split.glitches()
    if glitches.size:
        first = int(glitches[0])
        neighbour = int(np.flatnonzero(keep)[np.searchsorted(np.flatnonzero(keep), first) - 1]) \
            if first > 0 and keep[:first].any() else int(np.flatnonzero(keep)[0])
        off = (int(stamps[first]) - int(stamps[neighbour])) / _NS
        ctx.issues.append(
            f'{topic}: dropped {glitches.size} sample(s) whose header.stamp jumps away from its '
            f'neighbours and back (a clock glitch), the first at '
            f'{ctx.message(topic, message[first])} with its stamp {off:+.6g} s off')
    if split.n_runs > 1:
        ctx.several_runs = True
        if ctx.run is None:
            raise BagError(_runs_message(ctx, topic, role, split, stamps, message))
        if ctx.run > split.n_runs:
            raise BagError(f'{topic} ({role}): run {ctx.run} asked for, but the topic holds '
                           f'{split.n_runs} runs; choose run 1..{split.n_runs}')
        keep &= split.labels == ctx.run - 1
    if keep.all():
        return stamps, position, velocity, message
    return stamps[keep], position[keep], velocity[keep], message[keep]


def _runs_message(ctx, topic, role, split, stamps, message):
    """One line: where the runs of a topic are, and how to choose one."""
    reference = int(stamps[split.labels == 0].min())
    runs = []
    for run in range(split.n_runs):
        own = stamps[split.labels == run]
        runs.append(f'run {run + 1}: {own.size} samples, stamps '
                    f'{(own.min() - reference) / _NS:+.3f} to '
                    f'{(own.max() - reference) / _NS:+.3f} s')
    jump = int(split.jumps[0])
    real = np.flatnonzero(split.labels[:jump] >= 0)
    step = (int(stamps[jump]) - int(stamps[real[-1]])) / _NS if real.size else 0.0
    where = ctx.message(topic, message[jump])
    if split.interleaved():
        cause = (f'the stamps switch between {split.n_runs} clocks {split.jumps.size} times, the '
                 f'first at {where} (several publishers with different clocks on one topic)')
    elif step > 0:
        cause = (f'the stamps jump forward {step:.6g} s at {where} while the receive times '
                 'do not (the clock stepped: the time base is broken there)')
    else:
        cause = (f'the stamps jump back {-step:.6g} s at {where} and continue from there (a '
                 f'clock reset: {split.n_runs} runs in one bag)')
    return (f'{topic} ({role}): {cause}; {"; ".join(runs)} (stamps relative to the first of '
            'run 1). Sorted by stamp they would merge: choose one with `run: K` in the run '
            f'description (K = 1..{split.n_runs} in recording order; window_s then counts from '
            'the first flap stamp of that run)')


def _repeated_stamps(ctx, topic, role, stamps, position, velocity, message):
    """Drop repeated stamps; refuse when a second publisher stamps the same instants."""
    repeated = np.concatenate([[False], np.diff(stamps) == 0])
    if not repeated.any():
        return stamps, position, velocity, message
    differ = repeated & np.any(position != np.roll(position, 1, axis=0), axis=1)
    largest = float(np.max(np.abs(position - np.roll(position, 1, axis=0))[differ])) \
        if differ.any() else 0.0
    count = np.count_nonzero(repeated)
    if np.count_nonzero(differ) > SHARED_STAMP_FRACTION * len(stamps):
        raise BagError(
            f'{topic} ({role}): {count} of {len(stamps)} stamps come twice with different '
            f'values (up to {largest:.4g} apart): two publishers stamp the same instants on '
            f'this topic{_publishers_note(ctx, topic)}. Record one publisher per topic (remap '
            f'the other to its own topic) and set topics.{role}')
    keep = ~repeated
    what = (f'; their values differ by up to {largest:.4g}' if differ.any()
            else ' (exact duplicates)')
    ctx.issues.append(f'{topic}: dropped {count} sample(s) with a repeated stamp{what}; the '
                      'first of each is kept')
    return stamps[keep], position[keep], velocity[keep], message[keep]


def _publishers_note(ctx, topic):
    notes = []
    count = ctx.publishers.get(topic, 0)
    if count > 1:
        notes.append(f'metadata.yaml lists {count} publishers on it')
    frames = ctx.frame_ids.get(topic, {})
    if len(frames) > 1:
        notes.append('header.frame_id ' + ', '.join(f'{name!r} in {number} messages'
                                                    for name, number in frames.items()))
    return f' ({"; ".join(notes)})' if notes else ''


def _repair_value_spikes(ctx, topic, role, stamps, position, names):
    """Replace isolated flap/pitch samples far from their neighbours (in place), and say where."""
    repairs = repair_value_spikes(stamps, position)
    if not repairs:
        return
    said = []
    for repair in repairs:
        joint = names[repair.column] if repair.column < len(names) else f'column {repair.column}'
        said.append(f'{joint}: {repair.count}, e.g. {repair.value:.4g} rad '
                    f'among {repair.neighbours:.4g} at {ctx.when(int(stamps[repair.index]))}')
        ctx.repairs.extend((topic, joint, int(stamps[i]), float(old), float(new), 'value_spike')
                           for i, old, new in zip(repair.indices, repair.old, repair.new))
    ctx.issues.append(
        f'{topic} ({role}): sample(s) of one blade jump away from their neighbours and back (a '
        f'spike: a bit flip or a dropped reading) in {"; ".join(said)}; replaced by the cubic '
        'through their neighbours (listed in repairs). Check the sensor if this recurs')


def _check_one_stream(ctx, topic, role, stamps, position):
    """Refuse a topic whose samples are two streams merged (see :mod:`.streams`)."""
    values = np.unwrap(position, axis=0) if role == 'azimuth' else position
    evidence = interleaved_streams(stamps, values)
    if evidence is None:
        if ctx.publishers.get(topic, 0) > 1:
            ctx.issues.append(
                f'{topic}: metadata.yaml lists {ctx.publishers[topic]} publishers on this topic; '
                'the samples show no sign of two interleaved streams (e.g. a restarted node)')
        return
    rate = (len(stamps) - 1) * _NS / max(int(stamps[-1] - stamps[0]), 1)   # mean rate
    raise BagError(
        f'{topic} ({role}): the samples are two streams merged, not one sensor: '
        f'{evidence.describe()}, in {len(stamps)} samples at {rate:.4g} Hz'
        f'{_publishers_note(ctx, topic)}. Several publishers on one topic cannot be told apart '
        f'message by message: record one publisher per topic (remap the other, e.g. to '
        f'{topic}_raw) and set topics.{role}')


def _blade_columns(names, topic, role, joint_names):
    """Column of each blade (blade 1 first) in a message with joint ``names``."""
    if joint_names is not None:
        wanted = joint_names[role]
        missing = [name for name in wanted if name not in names]
        if missing:
            raise BagError(f'{topic}: joints {missing} named in joint_names are not in the '
                           f'messages, which have {list(names)}; fix joint_names')
        return [names.index(name) for name in wanted], list(wanted)
    if not names:
        raise BagError(f'{topic}: the messages have no joint names; name the joints '
                       'blade_1..blade_N or give joint_names in the run description')
    numbers = [re.fullmatch(r'blade_?(\d+)', name, re.IGNORECASE) for name in names]
    blades = [int(m.group(1)) for m in numbers if m]
    if len(blades) != len(names) or sorted(blades) != list(range(1, len(names) + 1)):
        raise BagError(f'{topic}: cannot tell the blade of joints {list(names)}; the '
                       'convention names them blade_1..blade_N, or give joint_names (blade 1 '
                       'first) in the run description')
    columns = [blades.index(k) for k in range(1, len(names) + 1)]
    return columns, [names[c] for c in columns]


def _check_radians(values, topic):
    largest = float(np.max(np.abs(values)))
    if largest > MAX_ANGLE_RAD:
        raise BagError(f'{topic}: |angle| reaches {largest:.4g}, more than {MAX_ANGLE_RAD} rad; '
                       'the values look like degrees. The convention is radians: convert the '
                       'recording (multiply by pi/180)')


def _gaps(stamps_ns, omega, topic, issues, what):
    """Report steps longer than GAP_FACTOR sample periods, in revolutions."""
    if len(stamps_ns) < 3:
        return
    steps = np.diff(stamps_ns)
    period = np.median(steps)
    gaps = np.flatnonzero(steps > GAP_FACTOR * period)
    if len(gaps):
        largest = gaps[np.argmax(steps[gaps])]
        seconds = steps[largest] / _NS
        revs = seconds * omega / TWO_PI
        issues.append(f'{topic}: {len(gaps)} gap(s) in the samples; the largest is '
                      f'{seconds * 1e3:.4g} ms = {revs:.3g} rev at '
                      f'{(stamps_ns[largest] - stamps_ns[0]) / _NS:.4f} s; {what}')


# --------------------------------------------------------------------------- reading

def read_record(bag_path: str | os.PathLike, topics: Mapping[str, str | None] | None = None,
                joint_names: object = None, *, n_blades: int | None = None,
                omega_rad_s: float | None = None, run: int | None = None,
                window_s: Sequence[float] | None = None,
                azimuth_joint: str = DEFAULT_AZIMUTH_JOINT, azimuth_convention: str = 'wrapped',
                check_dead_flap: bool = True) -> Record:
    """
    Read a test-stand recording into a Record on the flap stamps.

    Parameters
    ----------
    bag_path
        Bag directory (with metadata.yaml), its metadata.yaml, or the .mcap / .db3
        file itself.
    topics
        Role -> topic, roles 'blade_pitch', 'blade_flap', 'azimuth'; missing roles use
        the convention (:data:`DEFAULT_TOPICS`). ``azimuth: None`` means no azimuth was
        recorded; then ``omega_rad_s`` is needed and t = Ω·time.
    joint_names
        Joint of each blade, blade 1 first, in any form accepted by
        :func:`~rotor_id.io.run_description.normalize_joint_names`; default: the message's
        names blade_1..blade_N.
    n_blades
        Expected number of blades (e.g. the run description's rotor.blades).
    omega_rad_s
        Rotor speed, rad/s, used when no azimuth topic is given or the bag has
        none (then t = Ω·time from 0, with a warning).
    run
        1-based run to read when the bag holds several (the stamps jump back: a clock
        reset, or publishers with different clocks), in recording order; None: the bag
        must hold one run.
    window_s
        (t0, t1) seconds after the first flap stamp that will be analysed, or None. A fault
        that cannot be repaired (an azimuth slip) is an error inside it (or with no window)
        and a warning outside it.
    azimuth_joint, azimuth_convention
        Joint name on the azimuth topic, and 'wrapped' ([0, 2π)) or 'unwrapped' position
        (the run description's; :meth:`RunDescription.record_options` gives all of these).
    check_dead_flap
        Refuse a blade whose flap reads one exact value throughout ``window_s`` (a dead
        sensor). False when ``window_s`` only says which part of a long bag to read and the
        caller checks each window it fits (a long bag's slices:
        :meth:`Record.stuck_flap_blades`).

    Returns
    -------
    Record. Its ``warnings`` list every repair, once each (also announced once as a
    BagWarning).

    Raises
    ------
    BagError
        The bag cannot be read, does not follow the convention, or holds several runs or
        streams on one topic that must be told apart.

    """
    topics = {**DEFAULT_TOPICS, **(topics or {})}
    if joint_names is not None:
        try:
            joint_names = normalize_joint_names(joint_names, n_blades)
        except ValueError as err:
            raise BagError(f'joint_names: {err}') from None
    if run is not None and (isinstance(run, bool) or not isinstance(run, (int, np.integer))
                            or run < 1):
        raise BagError(f'run must be a positive integer (1 = the first run), got {run!r}')
    bag = _resolve(bag_path)
    wanted = {role: topic for role, topic in topics.items() if topic}
    if 'azimuth' not in wanted and omega_rad_s is None:
        raise BagError('no azimuth topic given: pass omega_rad_s (the rotor speed) so that the '
                       'nondimensional time can be formed')
    raw = origin_ns = None
    if window_s is not None and run is None and not bag.compressed_whole:
        raw, origin_ns = _read_window(bag, wanted, window_s)
    if raw is None:
        raw = _read_raw(bag, wanted, omega_rad_s)
        _decompress_messages(raw)
    _drop_impossible_receive_times(raw, bag.label)
    ctx = _Context(raw=raw, issues=list(raw.notes), run=run,
                   publishers=bag.facts.get('publishers', {}), origin_ns=origin_ns)
    for topic, expected in ({} if origin_ns is not None else bag.counts).items():
        got = len(raw.data.get(topic, []))
        if topic in raw.data and got < expected:
            ctx.issues.append(f'{topic}: {got} of the {expected} messages listed in '
                              'metadata.yaml were read')

    record = _assemble(ctx, wanted, joint_names, n_blades, omega_rad_s, window_s,
                       (azimuth_joint, azimuth_convention), check_dead_flap)
    part = ''
    record.read_around_window = origin_ns is not None
    if origin_ns is not None:
        part = (f', read {record.time_s[0]:.3f}-{record.time_s[-1]:.3f} s around window_s '
                'only')
    record.source = (f'{bag.label} ({bag.storage}; flap {wanted["blade_flap"]}, pitch '
                     f'{wanted["blade_pitch"]}, azimuth {wanted.get("azimuth")}'
                     + (f', run {run}' if run is not None else '') + part + ')')
    if record.warnings:
        warnings.warn(f'{bag.label}: ' + '; '.join(record.warnings), BagWarning,
                      stacklevel=2)
    return record


def may_read_by_parts(bag_path: str | os.PathLike) -> bool:
    """
    Say whether :func:`read_record` may read only the part of this bag around a window.

    True for a bag of at least WINDOW_READ_MIN_BYTES whose storage files are not compressed
    whole (it may still read it all: clocks that disagree, a damaged file); False: every read
    takes the whole bag, whatever the window.
    """
    bag = _resolve(bag_path)
    return bag.size >= WINDOW_READ_MIN_BYTES and not bag.compressed_whole


class _Parts:
    """
    The bag read by receive time through rosbags (every file of a split bag).

    rosbags reads a receive-time range from rosbag2's own indexes: the chunk index of an
    MCAP file (only the chunks that overlap are read and decompressed), the timestamp index of
    a sqlite3 file.
    """

    def __init__(self, bag, topics):
        self.reader = Reader(bag.open_path)
        self.reader.open()
        self.available = {c.topic: c.msgtype for c in self.reader.connections}
        self.connections = [c for c in self.reader.connections if c.topic in topics]
        if not self.connections:
            raise ValueError('none of the topics is in the bag')
        self.start_ns, self.end_ns = self.reader.start_time, self.reader.end_time

    def read(self, topics, first, last):
        """Return (topic -> type, topic -> (receive times, messages)) received in [first, last]."""
        found = {}
        wanted = [c for c in self.connections if c.topic in topics]
        for connection, log_ns, data in self.reader.messages(wanted, start=int(first),
                                                             stop=int(last) + 1):
            log, messages = found.setdefault(connection.topic, ([], []))
            log.append(log_ns)
            messages.append(data)
        return self.available, found

    def last(self, topic):
        """Return topic -> (receive times, messages) of the last WINDOW_READ_TAIL_S of it."""
        return self.read({topic}, self.end_ns - WINDOW_READ_TAIL_S * _NS, self.end_ns)[1]

    def close(self):
        """Close the reader."""
        self.reader.close()


def _read_window(bag, wanted, window_s):
    """
    Read only the part of a long bag around the window (memory follows the window).

    window_s counts from the first flap stamp, so the first WINDOW_READ_HEAD_S of receive
    time give that origin and the offset from stamps to receive times; the last
    WINDOW_READ_TAIL_S check that the offset holds to the end (no clock reset, no second run).
    Then only the messages received within the window (plus WINDOW_READ_MARGIN_S) are read
    (:class:`_Parts`: rosbags on the bag's index).

    Returns
    -------
    (_Raw, origin ns) or (None, None): the bag is small, cannot be read by parts, or its
    clocks disagree; then the whole bag is read with every check.

    """
    none = None, None
    if bag.size < WINDOW_READ_MIN_BYTES:
        return none
    tolerance = WINDOW_READ_CLOCK_TOLERANCE_S * _NS
    parts = None
    try:
        parts = _Parts(bag, _WantedTopics(wanted.values()))
        for role, topic in wanted.items():     # relative names: root, else the one namespace
            wanted[role] = recorded_topic(topic, parts.available) or topic
        topics = set(wanted.values())
        flap_topic = wanted['blade_flap']

        def offsets(found, topic=flap_topic):
            """(stamps, receive − stamp) of a topic's decodable, stamped messages."""
            log, messages = found.get(topic, ([], []))
            if not len(messages):
                return np.empty(0, np.int64), np.empty(0, np.int64)
            raw = _Raw()
            raw.data[topic] = messages
            _decompress_messages(raw)
            batch = decode_batch(raw.data[topic])
            keep = batch.stamps_ns != 0
            received = np.asarray(log, np.int64)[batch.kept]
            return batch.stamps_ns[keep], (received - batch.stamps_ns)[keep]

        _, head = parts.read(topics, parts.start_ns, parts.start_ns + WINDOW_READ_HEAD_S * _NS)
        head_stamps, head_offset = offsets(head)
        _, tail_offset = offsets(parts.last(flap_topic))
        if not head_stamps.size or not tail_offset.size:
            return none
        offset = int(np.median(head_offset))
        if abs(int(np.median(tail_offset)) - offset) > tolerance:
            return none                       # clocks disagree: the full read finds out why
        # the origin as the full read takes it: the first flap stamp inside the other
        # topics' span (stamps off the steady offset, e.g. glitches, left out)
        steady = np.abs(head_offset - offset) <= tolerance
        starts = [int(head_stamps[steady].min())]
        for topic in topics - {flap_topic}:
            stamps, other = offsets(head, topic)
            good = np.abs(other - offset) <= tolerance
            if not good.any():
                return none
            starts.append(int(stamps[good].min()))
        flap_head = np.sort(head_stamps[steady])
        if flap_head[-1] < max(starts):
            return none
        origin = int(flap_head[np.searchsorted(flap_head, max(starts))])
        margin = (WINDOW_READ_MARGIN_S + WINDOW_READ_CLOCK_TOLERANCE_S) * _NS
        first = origin + offset + int(window_s[0] * _NS) - margin
        last = origin + offset + int(window_s[1] * _NS) + margin
        if last - first > WINDOW_READ_MAX_FRACTION * (parts.end_ns - parts.start_ns):
            return none                       # most of the bag anyway: read it all
        available, found = parts.read(topics, first, last)
        _, part_offset = offsets(found)
        if part_offset.size and abs(int(np.median(part_offset)) - offset) > tolerance:
            return none
    except Exception:  # noqa: B902 - any trouble with the index: the full read decides
        return none
    finally:
        with suppress(Exception):
            parts.close()
    raw = _Raw()
    raw.available = available
    raw.bag_start_ns = parts.start_ns
    _check_topics(raw, wanted, bag.label, None)
    for topic in wanted.values():
        raw.log_ns[topic], raw.data[topic] = found.get(topic, ([], []))
    _decompress_messages(raw)
    return raw, origin


def _decompress_messages(raw):
    """Decompress messages written with rosbag2's per-message compression (zstd frames)."""
    for topic, messages in raw.data.items():
        if not len(messages) or bytes(messages[0][:4]) != _ZSTD_MAGIC:
            continue
        out = []
        for number, message in enumerate(messages):
            try:
                out.append(zstd.decompress(bytes(message)))
            except zstd.ZstdError as err:
                raise BagError(f'{topic}: message {number + 1} is compressed per message '
                               f'(rosbag2 compression_mode: message, zstd) but does not '
                               f'decompress ({err}); the file is damaged at that message') \
                    from None
        raw.data[topic] = out


def _assemble(ctx, wanted, joint_names, n_blades, omega_rad_s, window_s,
              azimuth=(DEFAULT_AZIMUTH_JOINT, 'wrapped'), check_dead_flap=True):
    issues = ctx.issues
    flap_topic, pitch_topic = wanted['blade_flap'], wanted['blade_pitch']
    flap_s = _topic_samples(ctx, flap_topic, 'blade_flap', False)
    origin_ns = ctx.origin_ns                   # known when only the window was read
    if origin_ns is None:
        ctx.origin_ns = int(flap_s.stamps[0])
    pitch_s = _topic_samples(ctx, pitch_topic, 'blade_pitch', False)
    flap_ns, flap, pitch_ns, pitch = flap_s.stamps, flap_s.position, pitch_s.stamps, \
        pitch_s.position
    flap_cols, blade_names = _blade_columns(flap_s.names, flap_topic, 'blade_flap', joint_names)
    pitch_cols, _ = _blade_columns(pitch_s.names, pitch_topic, 'blade_pitch', joint_names)
    if len(flap_cols) != len(pitch_cols):
        raise BagError(f'{flap_topic} has {len(flap_cols)} blades but {pitch_topic} has '
                       f'{len(pitch_cols)}; both must carry every blade')
    if n_blades is not None and len(flap_cols) != n_blades:
        raise BagError(f'{flap_topic} has {len(flap_cols)} blades, the run description says '
                       f'rotor.blades = {n_blades}; fix one of them')
    flap, pitch = flap[:, flap_cols], pitch[:, pitch_cols]
    _check_radians(flap, flap_topic)
    _check_radians(pitch, pitch_topic)

    spans = [pitch_ns]
    if 'azimuth' in wanted:
        az_ns, psi_u, omega, az_sampled_ns = _azimuth(ctx, wanted['azimuth'], *azimuth)
        spans.append(az_ns)
    if ctx.run is not None and ctx.run > 1 and not ctx.several_runs:
        raise BagError(f'run {ctx.run} asked for, but the bag holds one run (the stamps of '
                       f'{", ".join(wanted.values())} never jump back); remove run')
    # Flap samples outside the span of the other channels cannot be interpolated: drop them.
    inside = (flap_ns >= max(s[0] for s in spans)) & (flap_ns <= min(s[-1] for s in spans))
    if not inside.any():
        raise BagError(f'{flap_topic} does not overlap in time with '
                       f'{", ".join(t for r, t in wanted.items() if r != "blade_flap")}; '
                       'the stamps of the topics must come from one clock')
    if not inside.all():
        issues.append(f'{flap_topic}: dropped {np.count_nonzero(~inside)} sample(s) outside the '
                      'time span of the pitch/azimuth topics')
        flap_ns, flap = flap_ns[inside], flap[inside]

    stamp0 = int(flap_ns[0]) if origin_ns is None else origin_ns
    time_s = (flap_ns - stamp0) / _NS
    pitch = interpolate_columns(time_s, (pitch_ns - stamp0) / _NS, pitch)
    if 'azimuth' in wanted:
        az_time = (az_ns - stamp0) / _NS
        t = np.interp(time_s, az_time, psi_u)
        speed = np.interp(time_s, az_time, omega)
    else:
        speed = np.full(len(time_s), float(omega_rad_s))
        if not speed[0] > 0:
            raise BagError(f'omega_rad_s must be positive, got {omega_rad_s}')
        t = nondimensional_time(time_s, None, speed)
        issues.append('no azimuth topic: t = Ω·time from 0, blade-1 azimuth at the first stamp '
                      'taken as 0')
    omega_mean = float(np.mean(speed))
    _judge_faults(ctx, stamp0, window_s, omega_mean)
    if check_dead_flap:
        _dead_flap_sensors(time_s, flap, blade_names, flap_topic, window_s)
    _check_increasing(ctx, t, time_s, wanted.get('azimuth'), window_s)
    _gaps(flap_ns, omega_mean, flap_topic, issues, 'flap samples there are missing')
    _gaps(pitch_ns, omega_mean, pitch_topic, issues, 'pitch is interpolated across')
    if 'azimuth' in wanted:
        # (samples dropped as glitches were sampled: they are no gap)
        _gaps(az_sampled_ns, omega_mean, wanted['azimuth'], issues,
              'azimuth is interpolated across')
    repairs = [Repair(topic, joint, (stamp - stamp0) / _NS, old, new, why)
               for topic, joint, stamp, old, new, why in ctx.repairs]
    return Record(time_s=time_s, t=t, rotor_speed_rad_s=speed, blade_flap=flap,
                  blade_pitch=pitch, blade_names=blade_names,
                  warnings=list(dict.fromkeys(issues)), stamp0_ns=stamp0,
                  flap_joints=flap_s.names, pitch_joints=pitch_s.names, repairs=repairs)


def _in_window(time_s, window_s, margin_s):
    return window_s is None or window_s[0] - margin_s <= time_s <= window_s[1] + margin_s


def _dead_flap_sensors(time_s, flap, blade_names, topic, window_s):
    """
    Refuse a blade whose flap reads one exact value throughout the window.

    A flap sensor always shows its noise and the blade's response to the stirring; a reading
    that never changes is a dead or disconnected sensor (0.0 from an unplugged amplifier, a
    held last value), and a fit would take it for a blade that does not flap. Only with a
    window (identification: run descriptions require window_s); a record read whole may be
    anything (a recorder's test pattern).
    """
    if window_s is None:
        return
    inside = (time_s >= window_s[0]) & (time_s <= window_s[1])
    if np.count_nonzero(inside) < 2:
        return
    values = flap[inside]
    dead = stuck_channels(values)
    if dead:
        where = f'window_s [{window_s[0]}, {window_s[1]}] s'
        raise BagError(
            f'{topic}: the flap of {", ".join(blade_names[k] for k in dead)} reads exactly '
            f'{", ".join(f"{values[0, k]:.6g}" for k in dead)} rad in every one of its '
            f'{len(values)} samples in {where}: a dead or disconnected sensor (a real reading '
            'shows noise and the stirring response); check the sensor and its wiring')


def _judge_faults(ctx, stamp0, window_s, omega_mean):
    """Faults that cannot be repaired: an error in (or near) the window, a warning outside."""
    margin = 2 * TWO_PI / omega_mean      # identification uses a revolution either side
    for stamp, text in ctx.faults:
        at = (stamp - stamp0) / _NS
        if _in_window(at, window_s, margin):
            raise BagError(f'{text}; choose window_s clear of {at:.4f} s'
                           + (' (the record is read without a window)' if window_s is None
                              else f' (window_s is [{window_s[0]}, {window_s[1]}] s)'))
        ctx.issues.append(f'{text} (outside window_s, not used)')


def _check_increasing(ctx, t, time_s, azimuth_topic, window_s):
    """
    Check that the nondimensional time increases; say where it does not.

    In (or near) the window, or without a window, that is an error; outside it a warning.
    """
    back = np.flatnonzero(np.diff(t) <= 0)
    if not back.size:
        return
    margin = 2 * TWO_PI / max(float(np.median(np.diff(t) / np.diff(time_s))), 1e-9)
    inside = [i for i in back if window_s is None
              or (time_s[i + 1] >= window_s[0] - margin and time_s[i] <= window_s[1] + margin)]
    i = int(inside[0] if inside else back[0])
    text = (f'{azimuth_topic or "rotor speed"}: the rotor azimuth goes back by '
            f'{t[i] - t[i + 1]:.4g} rad between {time_s[i]:.4f} and {time_s[i + 1]:.4f} s '
            f'(record time), in {back.size} place(s): the nondimensional time t = azimuth must '
            'increase')
    if inside:
        raise BagError(f'{text}; check the azimuth sensor there, or choose window_s (and run) '
                       'to avoid it')
    ctx.issues.append(f'{text} (outside window_s, not used)')


def _azimuth(ctx, topic, joint=DEFAULT_AZIMUTH_JOINT, convention='wrapped'):
    """Return (stamps_ns, unwrapped ψ of blade 1, Ω, stamps before repairs) of the azimuth."""
    issues = ctx.issues
    samples = _topic_samples(ctx, topic, 'azimuth', True)
    stamps, names, position, velocity = (samples.stamps, samples.names, samples.position,
                                         samples.velocity)
    if joint not in names:
        raise BagError(f'{topic}: expected the azimuth joint {joint!r}, got {list(names)}; '
                       'set joint_names.azimuth in the run description')
    column = names.index(joint)
    position = position[:, column]
    velocity = None if velocity is None else velocity[:, column].copy()
    if convention == 'unwrapped':
        position = wrap_azimuth(position)
    elif len(position) and -np.pi <= np.min(position) and np.max(position) < np.pi + 1e-9:
        position = wrap_azimuth(position)   # every sample in [-π, π): an encoder's wrapping
    elif len(position) and not 0.0 <= float(np.median(position)) < TWO_PI:
        raise BagError(f'{topic}: the azimuth is mostly outside [0, 2π) (median '
                       f'{float(np.median(position)):.4g} rad): degrees or rpm? position must be '
                       'ψ in rad; if it is continuous (an encoder), set azimuth_convention: '
                       'unwrapped in the run description')
    time_s = (stamps - stamps[0]) / _NS
    if velocity is None:
        issues.append(f'{topic}: no velocity (rotor speed); Ω is taken from the azimuth rate')
        if len(stamps) < 2:
            raise BagError(f'{topic}: one sample and no velocity: the rotor speed is unknown')
        steps = np.diff(np.unwrap(position))
        rate = np.full(len(stamps), float(np.median(steps / np.diff(time_s))))
    else:
        _repair_speed_spikes(ctx, topic, joint, stamps, velocity)
        rate = velocity
    if not (rate > 0).all():
        bad = rate[~(rate > 0)]
        raise BagError(f'{topic}: the rotor speed (velocity) is zero or negative in {len(bad)} '
                       f'sample(s), down to {bad.min():.4g} rad/s, the first at '
                       f'{ctx.when(int(stamps[np.argmax(~(rate > 0))]))}; t = ψ needs a turning '
                       'rotor in the positive sense: cut the recording to where the rotor turns')
    sampled = stamps
    stamps, position, rate, time_s = _repair_phase(ctx, topic, joint, stamps, position, rate,
                                                   time_s)
    if velocity is None:
        velocity = np.gradient(np.unwrap(position), time_s) if len(stamps) > 1 else rate
    else:
        velocity = rate
    psi_u = nondimensional_time(time_s, position, velocity)
    if len(stamps) > 1 and time_s[-1] > 0:
        rate = (psi_u[-1] - psi_u[0]) / time_s[-1]
        mean_speed = float(trapezoid(velocity, time_s) / time_s[-1])
        if abs(rate - mean_speed) > RATE_TOLERANCE * mean_speed:
            raise BagError(f'{topic}: the azimuth advances at {rate:.4g} rad/s but the rotor '
                           f'speed (velocity) says {mean_speed:.4g} rad/s; position must be '
                           'ψ in rad wrapped to [0, 2π) and velocity Ω in rad/s (degrees or '
                           'rpm?)')
    return stamps, psi_u, velocity, sampled


def _repair_speed_spikes(ctx, topic, joint, stamps, velocity):
    """Replace isolated rotor-speed samples far from their neighbours (in place)."""
    typical = float(np.median(np.abs(velocity)))
    spiky = spikes(velocity, SPEED_SPIKE_FRACTION * typical)
    if not spiky.size:
        return
    good = np.ones(len(velocity), dtype=bool)
    good[spiky] = False
    smooth = np.interp(stamps[spiky], stamps[good], velocity[good])
    worst = int(np.argmax(np.abs(velocity[spiky] - smooth)))
    ctx.repairs.extend((topic, joint, int(stamps[i]), float(velocity[i]), float(new),
                        'speed_spike') for i, new in zip(spiky, smooth))
    ctx.issues.append(
        f'{topic}: {spiky.size} rotor-speed (velocity) sample(s) jump away from their '
        f'neighbours and back (e.g. {velocity[spiky][worst]:.4g} rad/s among '
        f'{smooth[worst]:.4g} at {ctx.when(int(stamps[spiky][worst]))}); replaced by '
        'interpolation')
    velocity[spiky] = smooth


def _repair_phase(ctx, topic, joint, stamps, position, rate, time_s):
    """Drop azimuth samples off the phase the rotor speed predicts; record lasting slips."""
    if len(stamps) < 3:
        return stamps, position, rate, time_s
    predicted = 0.5 * (rate[1:] + rate[:-1]) * np.diff(time_s)
    residual = np.mod(np.diff(position) - predicted + np.pi, TWO_PI) - np.pi
    found = phase_outliers(residual, PHASE_FLOOR_FRACTION * float(np.median(predicted)))
    for index, size in found.slips:
        ctx.faults.append((int(stamps[index]), (
            f'{topic}: the azimuth steps {size:+.4g} rad ({np.degrees(size):+.3g} deg) off the '
            f'phase the rotor speed predicts at {ctx.when(int(stamps[index]))} and stays there '
            '(an encoder slip or a wrong index pulse): the time base is wrong across it')))
    bad = found.repaired
    if not bad.size:
        return stamps, position, rate, time_s
    good = np.ones(len(stamps), dtype=bool)
    good[bad] = False
    expected = np.interp(stamps[bad], stamps[good], np.unwrap(position[good]))
    off = np.mod(position[bad] - expected + np.pi, TWO_PI) - np.pi
    worst = int(np.argmax(np.abs(off)))
    ctx.repairs.extend((topic, joint, int(stamps[i]), float(position[i]),
                        float(np.mod(new, TWO_PI)), 'azimuth_glitch')
                       for i, new in zip(bad, expected))
    ctx.issues.append(
        f'{topic}: dropped {bad.size} azimuth sample(s) off the phase the rotor speed predicts '
        f'(e.g. {position[bad][worst]:.4g} rad at {ctx.when(int(stamps[bad][worst]))}, '
        f'{off[worst]:+.3g} rad off, threshold {found.threshold:.3g} rad); the azimuth is '
        'interpolated across them')
    return stamps[good], position[good], rate[good], time_s[good]


def read_run(description: RunDescription,
             bag_path: str | os.PathLike | None = None) -> Record:
    """
    Read the bag of a run description, and check its window against the record.

    Parameters
    ----------
    description
        RunDescription (its ``run``, if any, selects one of several runs in the bag).
    bag_path
        The bag; default NAME/ beside the description's NAME.yaml.

    Returns
    -------
    Record.

    Raises
    ------
    BagError
        Bag unreadable.
    RunDescriptionError
        The window is outside the record.

    """
    bag_path = description.bag_path() if bag_path is None else bag_path
    record = read_record(bag_path, n_blades=description.rotor.blades,
                         **description.record_options())
    validate_window(description, record)
    return record


def typestore_with_custom_types(msg_dirs: Iterable[str | os.PathLike] = ()) -> 'Typestore':
    """
    Jazzy's rosbags typestore plus rotor_id_msgs and the .msg files of ``msg_dirs``.

    rotor_id_msgs from its installed share when ament_index finds it, else the source tree's
    msg_defs/msg (so that a clone reads its bags without ROS).
    """
    store = get_typestore(Stores.ROS2_JAZZY)
    dirs = list(msg_dirs)
    try:
        from ament_index_python.packages import get_package_share_directory
        dirs.insert(0, Path(get_package_share_directory('rotor_id_msgs')) / 'msg')
    except (ImportError, LookupError, ValueError):
        dirs.insert(0, Path(__file__).resolve().parents[2] / 'msg_defs' / 'msg')
    for directory in dirs:
        register_msg_dir(store, directory)
    return store


def message_with_defaults(store: 'Typestore', name: str, **values: Any) -> Any:
    """
    Build a message of type ``name`` from ``store``: the fields given, every other at zero.

    Zero is 0, 0.0, False, '' or an empty sequence, and a nested message of zeros: what a
    test or a benchmark writes when only some fields matter (e.g. a StirringCommand's header
    and phase).
    """
    numpy_types = {'float64': float, 'float32': np.float32, 'uint32': np.uint32,
                   'uint8': np.uint8, 'int32': np.int32}
    fields = {}
    detail: Any                 # the field's type: (base type, ...) or a nested definition
    for name_, (kind, detail) in store.fielddefs[name][1]:
        if name_ in values:
            continue
        if kind == 2:                                   # a nested message
            fields[name_] = message_with_defaults(store, detail)
        elif kind == 1:                                 # a base type
            fields[name_] = {'string': '', 'bool': False}.get(
                detail[0], 0.0 if detail[0].startswith('float') else 0)
        else:                                           # a sequence or an array
            base = detail[0][1][0]
            fields[name_] = ([] if base == 'string'
                             else np.array([], dtype=numpy_types.get(base, float)))
    return store.types[name](**fields, **values)


def read_messages(bag_path: str | os.PathLike, topics: Iterable[str]
                  ) -> dict[str, tuple[str | None, list[tuple[int, Any]]]]:
    """
    Decode every message of some topics of a bag (any type rotor_id's typestore knows).

    Parameters
    ----------
    bag_path
        As for :func:`read_record`.
    topics
        Topic names; a relative one is matched as :func:`recorded_topic` says (the root
        namespace, else the one namespace that has it).

    Returns
    -------
    {name as given: (topic in the bag or None, [(receive ns, message), ...] in recording
    order)}; a topic not in the bag has None and an empty list.

    """
    bag = _resolve(bag_path)
    store = typestore_with_custom_types()
    out = {}
    try:
        reader = Reader(bag.open_path)
        reader.open()
    except Exception as err:  # noqa: B902 - rosbags/apsw raise many types for bad files
        raise BagError(f'{bag.label} cannot be opened ({type(err).__name__}: {err})'
                       ) from None
    try:
        available = {c.topic: c.msgtype for c in reader.connections}
        found = {name: recorded_topic(name, available) for name in topics}
        wanted = [c for c in reader.connections if c.topic in found.values()]
        messages: dict[str | None, list[tuple[int, Any]]] = {
            topic: [] for topic in found.values() if topic}
        try:
            for connection, log_ns, data in (reader.messages(wanted) if wanted else ()):
                messages[connection.topic].append(
                    (int(log_ns), store.deserialize_cdr(data, connection.msgtype)))
        except Exception as err:  # noqa: B902 - damaged storage or unknown type
            raise BagError(f'{bag.label}: {", ".join(m for m in found.values() if m)} '
                           f'cannot be read ({type(err).__name__}: {err})') from None
        for name, topic in found.items():
            out[name] = (topic, messages.get(topic, []))
    finally:
        with suppress(Exception):
            reader.close()
    return out


# --------------------------------------------------------------------------- writing

def register_msg_dir(typestore: 'Typestore', msg_dir: str | os.PathLike,
                     package: str | None = None) -> list[str]:
    """
    Register every .msg file of a directory in a typestore.

    Parameters
    ----------
    typestore
        rosbags Typestore to extend.
    msg_dir
        Directory of .msg files (e.g. msg_defs/msg of package rotor_id_msgs).
    package
        Package name; default the <name> in ``msg_dir/../package.xml``, else the name
        of msg_dir's parent.

    Returns
    -------
    Sorted list of the registered type names ('pkg/msg/Name').

    Raises
    ------
    FileNotFoundError
        ``msg_dir`` has no .msg file.

    """
    msg_dir = Path(msg_dir)
    files = sorted(msg_dir.glob('*.msg'))
    if not files:
        raise FileNotFoundError(f'no .msg files in {msg_dir}')
    if package is None:
        package_xml = msg_dir.parent / 'package.xml'
        if package_xml.is_file():
            package = ElementTree.parse(package_xml).getroot().findtext('name')
        package = (package or msg_dir.parent.name).strip()
    types = {}
    for path in files:
        types.update(get_types_from_msg(path.read_text(encoding='utf-8'),
                                        f'{package}/msg/{path.stem}'))
    typestore.register(types)
    return sorted(types)


class BagWriter:
    """
    An open rosbag2 writer that knows its typestore.

    Use as a context manager; on an exception inside the block the bag is aborted.
    """

    def __init__(self, writer: Writer, typestore: 'Typestore') -> None:
        self.writer = writer
        self.typestore = typestore
        self.connections: dict[str, 'Connection'] = {}

    def add_topic(self, topic: str, msgtype: str) -> 'Connection':
        """Add (once) a topic of type ``msgtype``; its definition is embedded in the bag."""
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore)
        return self.connections[topic]

    def write(self, topic: str, timestamp_ns: int, message: Any) -> None:
        """Serialize ``message`` and write it on ``topic`` (added first if needed)."""
        self.add_topic(topic, message.__msgtype__)
        self.write_raw(topic, timestamp_ns,
                       self.typestore.serialize_cdr(message, message.__msgtype__))

    def write_raw(self, topic: str, timestamp_ns: int, data: bytes | memoryview) -> None:
        """Write CDR bytes on ``topic`` (which must have been added)."""
        self.writer.write(self.connections[topic], int(timestamp_ns), data)

    def close(self) -> None:
        """Finish the bag (index, metadata.yaml)."""
        self.writer.close()

    def __enter__(self) -> 'BagWriter':
        """Return self."""
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> Literal[False]:
        """Close, or abort on an exception."""
        if exc_type is None:
            self.close()
        else:
            with suppress(Exception):
                self.writer.abort()
        return False


class _McapWriter(McapWriter):
    """
    rosbags' MCAP storage writer, with the channel metadata rosbag2 (Jazzy) writes.

    rosbag2_storage_mcap stores two keys in each channel's metadata: ``offered_qos_profiles``
    (the publishers' QoS, YAML) and ``topic_type_hash``, the RIHS01 hash of the message type
    (REP-2011: ``RIHS01_`` and the SHA-256 of the type description), which its reader takes
    back as the topic's ``type_description_hash``. rosbags writes the first only.
    """

    def add_connection(self, connection, offered_qos_profiles):
        """Add a channel whose metadata holds the QoS profiles and the type hash."""
        metadata = BytesIO()
        for key, value in (('offered_qos_profiles', offered_qos_profiles),
                           ('topic_type_hash', connection.digest)):
            write_string(metadata, key)
            write_string(metadata, value)
        self.channels.append(Channel(
            connection.id, connection.msgtype, connection.topic,
            connection.ext.serialization_format, metadata.getvalue()))
        self.channel_stats[connection.id] = 0
        write_channel(self.chunk.bio, self.channels[-1], self.schemas)


class _Writer(Writer):
    """rosbags' bag writer with :class:`_McapWriter` for MCAP."""

    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _McapWriter}


def open_writer(path: str | Path, storage: str = 'mcap',
                typestore: 'Typestore | None' = None) -> BagWriter:
    """
    Create a rosbag2 bag as Jazzy writes it (metadata version 9).

    MCAP channels carry their offered QoS profiles and ``topic_type_hash`` (see
    :class:`_McapWriter`).

    Parameters
    ----------
    path
        New bag directory (must not exist).
    storage
        'mcap' or 'sqlite3'.
    typestore
        rosbags Typestore with every type to be written; default Jazzy's.

    Returns
    -------
    BagWriter, open.

    Raises
    ------
    BagError
        Unknown storage or the path exists.

    """
    if storage not in STORAGES:
        raise BagError(f'unknown storage {storage!r}; use one of {sorted(STORAGES)}')
    if Path(path).exists():
        raise BagError(f'{path} exists already; rosbag2 bags are not overwritten, choose a '
                       'new path')
    writer = _Writer(path, version=9, storage_plugin=STORAGES[storage])
    writer.open()
    return BagWriter(writer, typestore or get_typestore(Stores.ROS2_JAZZY))


def write_record_bag(path: str | Path, record: Record, storage: str = 'mcap',
                     topics: Mapping[str, str | None] | None = None, frame_id: str = 'rotor',
                     extra: Iterable[tuple[str, int, Any]] = (),
                     typestore: 'Typestore | None' = None) -> Path:
    """
    Write a Record into a bag following the test-stand convention.

    The pitch, flap and azimuth messages of each sample share the stamp
    ``record.stamp0_ns + time_s``, used as header.stamp and receive time. Azimuth is t wrapped
    to [0, 2π); velocity is the rotor speed.

    Parameters
    ----------
    path
        New bag directory.
    record
        Record to write.
    storage
        'mcap' or 'sqlite3'.
    topics
        Role -> topic; default :data:`DEFAULT_TOPICS`.
    frame_id
        header.frame_id of all messages.
    extra
        Further messages, (topic, receive time ns, rosbags message) each, of any type in
        ``typestore`` (e.g. rotor_id_msgs registered with :func:`register_msg_dir`); their
        definitions are embedded in the bag.
    typestore
        Typestore of the extra messages; default Jazzy's.

    Returns
    -------
    Path of the bag directory.

    """
    topics = {**DEFAULT_TOPICS, **(topics or {})}
    stamps = record.stamp0_ns + np.round(record.time_s * _NS).astype(np.int64)
    psi = np.mod(record.t, TWO_PI)
    psi[psi >= TWO_PI] = 0.0  # np.mod of a tiny negative number rounds to 2π
    streams = [
        (cast(str, topics['blade_pitch']),
         encode_batch(stamps, record.blade_names, record.blade_pitch, frame_id=frame_id)),
        (cast(str, topics['blade_flap']),
         encode_batch(stamps, record.blade_names, record.blade_flap, frame_id=frame_id)),
    ]
    if topics.get('azimuth'):
        streams.append((cast(str, topics['azimuth']), encode_batch(
            stamps, ['rotor'], psi[:, None], record.rotor_speed_rad_s[:, None],
            frame_id=frame_id)))
    with open_writer(path, storage, typestore) as writer:
        for topic, _ in streams:
            writer.add_topic(topic, JOINT_STATE)
        for i, stamp in enumerate(stamps.tolist()):
            for topic, messages in streams:
                writer.write_raw(topic, stamp, messages[i])
        for topic, stamp, message in extra:
            writer.write(topic, stamp, message)
    return Path(path)
