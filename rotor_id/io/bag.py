"""
Read and write rosbag2 recordings of the test stand (MCAP or sqlite3) with ``rosbags``.

The convention (recordings/README.md): three ``sensor_msgs/msg/JointState`` topics,
``header.stamp`` = acquisition time,

* /rotor/blade_pitch: joints blade_1..blade_N, position = blade pitch, rad;
* /rotor/blade_flap: joints blade_1..blade_N, position = flap angle (up positive), rad;
* /rotor/azimuth: joint 'rotor', position = ψ of blade_1 wrapped to [0, 2π), velocity = Ω.

:func:`read_record` turns such a bag into a :class:`~rotor_id.io.record.Record` on the flap
stamps. Damaged input raises :class:`BagError` with a message that says what to do; what can be
repaired (NaN samples, out-of-order or repeated stamps, a recording cut short) is repaired,
counted in ``record.warnings`` and announced once as a :class:`BagWarning`.
"""

from contextlib import suppress
from pathlib import Path
import re
import struct
import warnings
import xml.etree.ElementTree as ElementTree

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from rotor_id.io.errors import BagError, BagWarning
from rotor_id.io.jointstate_cdr import decode_batch, encode_batch, JOINT_STATE
from rotor_id.io.mcap_recover import read_indexed_mcap, scan_mcap
from rotor_id.io.record import Record
from rotor_id.io.run_description import DEFAULT_TOPICS, normalize_joint_names, validate_window
from rotor_id.io.timebase import interpolate_columns, nondimensional_time, TWO_PI
import yaml

__all__ = [
    'BagError', 'BagWarning', 'BagWriter', 'DEFAULT_TOPICS', 'open_writer', 'read_record',
    'read_run', 'register_msg_dir', 'write_record_bag',
]

MAX_ANGLE_RAD = 1.0     # |flap| or |pitch| above this: the recording is taken to be in degrees
GAP_FACTOR = 1.5        # a step longer than this many median sample periods is a gap
RATE_TOLERANCE = 0.05   # relative disagreement allowed between Ω and the azimuth's rate
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
SUFFIXES = {'.mcap': 'mcap', '.db3': 'sqlite3'}
_NS = 1_000_000_000


# --------------------------------------------------------------------------- locating the bag

def _resolve(bag_path):
    """Return (path to open with rosbags, storage id, storage file, expected message counts)."""
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
                'record or the storage file itself')
        path = files[0]
    if path.suffix not in SUFFIXES:
        raise BagError(f'{path} is not a bag: expected a directory, metadata.yaml, or a '
                       f'.mcap / .db3 file, got suffix {path.suffix!r}')
    if path.stat().st_size == 0:
        raise BagError(f'bag file {path} is empty (0 bytes); the recording wrote nothing')
    return path, SUFFIXES[path.suffix], path, {}


def _resolve_metadata(directory):
    meta_path = directory / 'metadata.yaml'
    try:
        info = yaml.safe_load(meta_path.read_text(encoding='utf-8'))['rosbag2_bagfile_information']
        storage = info['storage_identifier']
        files = [directory / Path(name).name for name in info['relative_file_paths']]
        counts = {t['topic_metadata']['name']: int(t['message_count'])
                  for t in info.get('topics_with_message_count') or []}
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError, ValueError) as err:
        raise BagError(f'{meta_path} is not rosbag2 metadata ({type(err).__name__}: {err}); '
                       'repair it, or give the .mcap / .db3 file instead of the directory') \
            from None
    if storage not in STORAGES:
        raise BagError(f'{meta_path}: storage {storage!r} is not supported; use mcap or sqlite3')
    missing = [str(f) for f in files if not f.is_file()]
    if missing or len(files) != 1:
        raise BagError(f'{meta_path} lists storage files {[f.name for f in files]}; '
                       f'missing: {missing}. Only complete single-file bags are read: give '
                       'the directory holding the file(s) listed in metadata.yaml')
    if files[0].stat().st_size == 0:
        raise BagError(f'bag file {files[0]} is empty (0 bytes); the recording wrote nothing')
    return directory, storage, files[0], counts


# -------------------------------------------------------------------------- raw messages

class _Raw:
    """Raw CDR messages of the wanted topics, plus what was found in the bag."""

    def __init__(self):
        self.available = {}   # topic -> message type
        self.data = {}        # topic -> list of bytes
        self.log_ns = {}      # topic -> list of receive times
        self.notes = []


def _read_raw(open_path, storage, storage_file, wanted, omega_rad_s):
    if storage == 'mcap':
        # A healthy chunked MCAP is read vectorised from its message index (no Python step per
        # message); anything unusual (unindexed, no footer, bad checksum) goes through rosbags
        # and, if that fails, the recovery scan.
        try:
            indexed = read_indexed_mcap(storage_file, set(wanted.values()))
        except (OSError, ValueError, IndexError, struct.error):
            indexed = None          # not readable this way: the general readers decide
        if indexed is not None:
            raw = _Raw()
            raw.available, found = indexed
            _check_topics(raw, wanted, storage_file, omega_rad_s)
            for topic in wanted.values():
                raw.log_ns[topic], raw.data[topic] = found.get(topic, ([], []))
            return raw
    raw = _Raw()
    try:
        reader = Reader(open_path)
        reader.open()
    except Exception as err:  # noqa: B902 - rosbags/apsw raise many types for bad files
        if storage == 'mcap':
            return _recover_mcap(storage_file, wanted, err, omega_rad_s)
        raise BagError(f'{storage_file} cannot be opened as a {storage} bag '
                       f'({type(err).__name__}: {err}); the file is not a rosbag2 recording '
                       'or is damaged (a damaged .db3 may be salvaged into a new file with the '
                       '.recover command of the sqlite3 shell)') from None
    try:
        raw.available = {c.topic: c.msgtype for c in reader.connections}
        _check_topics(raw, wanted, storage_file, omega_rad_s)
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
            if storage == 'mcap':
                recovered = _recover_mcap(storage_file, wanted, err, omega_rad_s)
                if sum(map(len, recovered.data.values())) > count:
                    return recovered
            raw.notes.append(
                f'{storage_file} is damaged after {count} messages ({type(err).__name__}: '
                f'{err}); the {count} messages read before the damage are used')
    finally:
        with suppress(Exception):
            reader.close()
    return raw


def _recover_mcap(storage_file, wanted, error, omega_rad_s):
    """Read what a damaged MCAP still holds (see :mod:`rotor_id.io.mcap_recover`)."""
    try:
        scan = scan_mcap(storage_file)
    except (OSError, ValueError) as err:
        raise BagError(f'{storage_file} cannot be opened as an MCAP bag ({error}) and is not '
                       f'recoverable ({err}); the file is not a rosbag2 recording') from None
    raw = _raw_from_scan(scan, wanted, storage_file, omega_rad_s)
    if not any(raw.data.values()):
        raise BagError(f'{storage_file} is damaged ({error}; {scan.problem}) and no message of '
                       f'{sorted(wanted.values())} could be recovered') from None
    raw.notes.append(
        f'{storage_file} is damaged ({error}); {scan.problem or "no index"}: recovered '
        f'{sum(map(len, raw.data.values()))} messages by scanning the file'
        + (f', skipped {scan.skipped_chunks} chunk(s) with bad checksums'
           if scan.skipped_chunks else ''))
    return raw


def _raw_from_scan(scan, wanted, storage_file, omega_rad_s):
    """Return the wanted topics' raw messages from a linear MCAP scan."""
    raw = _Raw()
    raw.available = scan.topics()
    _check_topics(raw, wanted, storage_file, omega_rad_s)
    for topic in wanted.values():
        messages = scan.topic_messages(topic)
        raw.log_ns[topic] = [m[0] for m in messages]
        raw.data[topic] = [m[1] for m in messages]
    return raw


def _check_topics(raw, wanted, storage_file, omega_rad_s):
    """Check that the wanted topics are JointState; without azimuth, fall back on Ω."""
    available = raw.available
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

def _topic_samples(raw, topic, role, issues, with_velocity):
    """
    Decode, then drop bad samples, sort and de-duplicate one topic.

    Returns
    -------
    (stamps_ns (n,), names, position (n, k), velocity (n, k)).

    """
    messages = raw.data.get(topic, [])
    if not messages:
        raise BagError(f'topic {topic} ({role}) has no messages in the bag: the recording is '
                       'empty; record the test again')
    batch = decode_batch(messages)
    for reason, count in batch.dropped.items():
        issues.append(f'{topic}: dropped {count} message(s): {reason}')
    if not len(batch.stamps_ns):
        raise BagError(f'topic {topic} ({role}): none of its {len(messages)} messages could be '
                       'decoded as JointState; the bag is corrupt')
    stamps, position, velocity = batch.stamps_ns, batch.position, batch.velocity
    unfilled = stamps == 0
    if np.count_nonzero(unfilled) > len(stamps) // 2:
        issues.append(f'{topic}: header.stamp is not filled (zero); the receive time is used '
                      'instead, which adds transport jitter: fill header.stamp at acquisition')
        stamps = np.asarray(raw.log_ns[topic], dtype=np.int64)[batch.kept]
    elif unfilled.any():
        issues.append(f'{topic}: dropped {np.count_nonzero(unfilled)} sample(s) whose '
                      'header.stamp is not filled (zero)')
        stamps, position, velocity = (a[~unfilled] for a in (stamps, position, velocity))
    if with_velocity and np.isnan(velocity).all():
        with_velocity = False
    values = np.hstack([position, velocity]) if with_velocity else position
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        issues.append(f'{topic}: dropped {np.count_nonzero(~finite)} sample(s) with NaN/inf '
                      'values')
        stamps, position, velocity = stamps[finite], position[finite], velocity[finite]
    if not len(stamps):
        raise BagError(f'topic {topic} ({role}): every sample is NaN or inf; check the sensor')
    backwards = np.count_nonzero(np.diff(stamps) < 0)
    if backwards:
        order = np.argsort(stamps, kind='stable')
        stamps, position, velocity = stamps[order], position[order], velocity[order]
        issues.append(f'{topic}: {backwards} stamp(s) out of order; samples sorted by '
                      'header.stamp')
    repeated = np.concatenate([[False], np.diff(stamps) == 0])
    if repeated.any():
        keep = ~repeated
        stamps, position, velocity = stamps[keep], position[keep], velocity[keep]
        issues.append(f'{topic}: dropped {np.count_nonzero(repeated)} sample(s) with a repeated '
                      'stamp (the first of each is kept)')
    if not with_velocity:
        velocity = None
    return stamps, batch.names, position, velocity


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

def read_record(bag_path, topics=None, joint_names=None, *, n_blades=None, omega_rad_s=None):
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

    Returns
    -------
    Record. Its ``warnings`` list every repair (also announced once as a BagWarning).

    Raises
    ------
    BagError
        The bag cannot be read or does not follow the convention.

    """
    topics = {**DEFAULT_TOPICS, **(topics or {})}
    if joint_names is not None:
        try:
            joint_names = normalize_joint_names(joint_names, n_blades)
        except ValueError as err:
            raise BagError(f'joint_names: {err}') from None
    open_path, storage, storage_file, counts = _resolve(bag_path)
    wanted = {role: topic for role, topic in topics.items() if topic}
    if 'azimuth' not in wanted and omega_rad_s is None:
        raise BagError('no azimuth topic given: pass omega_rad_s (the rotor speed) so that the '
                       'nondimensional time can be formed')
    raw = _read_raw(open_path, storage, storage_file, wanted, omega_rad_s)
    issues = list(raw.notes)
    for topic, expected in counts.items():
        got = len(raw.data.get(topic, []))
        if topic in raw.data and got < expected:
            issues.append(f'{topic}: {got} of the {expected} messages listed in metadata.yaml '
                          'were read')

    record = _assemble(raw, wanted, joint_names, n_blades, omega_rad_s, issues)
    record.source = (f'{storage_file} ({storage}; flap {wanted["blade_flap"]}, pitch '
                     f'{wanted["blade_pitch"]}, azimuth {wanted.get("azimuth")})')
    if issues:
        warnings.warn(f'{storage_file}: ' + '; '.join(issues), BagWarning, stacklevel=2)
    return record


def _assemble(raw, wanted, joint_names, n_blades, omega_rad_s, issues):
    flap_topic, pitch_topic = wanted['blade_flap'], wanted['blade_pitch']
    flap_ns, flap_names, flap, _ = _topic_samples(raw, flap_topic, 'blade_flap', issues, False)
    pitch_ns, pitch_names, pitch, _ = _topic_samples(raw, pitch_topic, 'blade_pitch', issues,
                                                     False)
    flap_cols, blade_names = _blade_columns(flap_names, flap_topic, 'blade_flap', joint_names)
    pitch_cols, _ = _blade_columns(pitch_names, pitch_topic, 'blade_pitch', joint_names)
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
        az_ns, psi_u, omega = _azimuth(raw, wanted['azimuth'], issues)
        spans.append(az_ns)
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

    stamp0 = int(flap_ns[0])
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
    _gaps(flap_ns, omega_mean, flap_topic, issues, 'flap samples there are missing')
    _gaps(pitch_ns, omega_mean, pitch_topic, issues, 'pitch is interpolated across')
    if 'azimuth' in wanted:
        _gaps(az_ns, omega_mean, wanted['azimuth'], issues, 'azimuth is interpolated across')
    return Record(time_s=time_s, t=t, rotor_speed_rad_s=speed, blade_flap=flap,
                  blade_pitch=pitch, blade_names=blade_names, warnings=list(issues),
                  stamp0_ns=stamp0, flap_joints=flap_names, pitch_joints=pitch_names)


def _azimuth(raw, topic, issues):
    """Return (stamps_ns, unwrapped ψ of blade 1, Ω) of the azimuth topic."""
    stamps, names, position, velocity = _topic_samples(raw, topic, 'azimuth', issues, True)
    if len(names) != 1:
        if 'rotor' not in names:
            raise BagError(f'{topic}: expected one joint named rotor, got {list(names)}')
        column = names.index('rotor')
        position = position[:, column]
        velocity = None if velocity is None else velocity[:, column]
    else:
        position = position[:, 0]
        velocity = None if velocity is None else velocity[:, 0]
    time_s = (stamps - stamps[0]) / _NS
    if velocity is None:
        issues.append(f'{topic}: no velocity (rotor speed); Ω is taken from the azimuth rate')
        if len(stamps) < 2:
            raise BagError(f'{topic}: one sample and no velocity: the rotor speed is unknown')
        velocity = np.gradient(np.unwrap(position), time_s)
    if not (velocity > 0).all():
        bad = velocity[~(velocity > 0)]
        raise BagError(f'{topic}: the rotor speed (velocity) is zero or negative in {len(bad)} '
                       f'sample(s), down to {bad.min():.4g} rad/s; t = ψ needs a turning rotor '
                       'in the positive sense: cut the recording to where the rotor turns')
    psi_u = nondimensional_time(time_s, position, velocity)
    if len(stamps) > 1 and time_s[-1] > 0:
        rate = (psi_u[-1] - psi_u[0]) / time_s[-1]
        mean_speed = float(np.trapezoid(velocity, time_s) / time_s[-1])
        if abs(rate - mean_speed) > RATE_TOLERANCE * mean_speed:
            raise BagError(f'{topic}: the azimuth advances at {rate:.4g} rad/s but the rotor '
                           f'speed (velocity) says {mean_speed:.4g} rad/s; position must be '
                           'ψ in rad wrapped to [0, 2π) and velocity Ω in rad/s (degrees or '
                           'rpm?)')
    return stamps, psi_u, velocity


def read_run(description, bag_path=None):
    """
    Read the bag of a run description, and check its window against the record.

    Parameters
    ----------
    description
        RunDescription.
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
    record = read_record(bag_path, description.topics, description.joint_names,
                         n_blades=description.rotor.blades)
    validate_window(description, record)
    return record


# --------------------------------------------------------------------------- writing

def register_msg_dir(typestore, msg_dir, package=None):
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

    def __init__(self, writer, typestore):
        self.writer = writer
        self.typestore = typestore
        self.connections = {}

    def add_topic(self, topic, msgtype):
        """Add (once) a topic of type ``msgtype``; its definition is embedded in the bag."""
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.typestore)
        return self.connections[topic]

    def write(self, topic, timestamp_ns, message):
        """Serialize ``message`` and write it on ``topic`` (added first if needed)."""
        self.add_topic(topic, message.__msgtype__)
        self.write_raw(topic, timestamp_ns,
                       self.typestore.serialize_cdr(message, message.__msgtype__))

    def write_raw(self, topic, timestamp_ns, data):
        """Write CDR bytes on ``topic`` (which must have been added)."""
        self.writer.write(self.connections[topic], int(timestamp_ns), data)

    def close(self):
        """Finish the bag (index, metadata.yaml)."""
        self.writer.close()

    def __enter__(self):
        """Return self."""
        return self

    def __exit__(self, exc_type, exc, traceback):
        """Close, or abort on an exception."""
        if exc_type is None:
            self.close()
        else:
            with suppress(Exception):
                self.writer.abort()
        return False


def open_writer(path, storage='mcap', typestore=None):
    """
    Create a rosbag2 bag as Jazzy writes it (metadata version 9).

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
    writer = Writer(path, version=9, storage_plugin=STORAGES[storage])
    writer.open()
    return BagWriter(writer, typestore or get_typestore(Stores.ROS2_JAZZY))


def write_record_bag(path, record, storage='mcap', topics=None, frame_id='rotor', extra=(),
                     typestore=None):
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
        (topics['blade_pitch'], encode_batch(stamps, record.blade_names, record.blade_pitch,
                                             frame_id=frame_id)),
        (topics['blade_flap'], encode_batch(stamps, record.blade_names, record.blade_flap,
                                            frame_id=frame_id)),
    ]
    if topics.get('azimuth'):
        streams.append((topics['azimuth'], encode_batch(
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
