"""Helpers of the input-layer tests: where the shared recordings are, small synthetic bags."""

from pathlib import Path

import numpy as np
from rotor_id.io.bag import DEFAULT_TOPICS, open_writer
from rotor_id.io.jointstate_cdr import encode_batch, JOINT_STATE
from rotor_id.io.record import Record

RECORDING_NAMES = (
    'id_wake_progressing', 'id_multiblade_mu04', 'dx_none_wake', 'dx_dynamic_inflow',
    'dx_sensor_lag', 'dx_periodic_coefficients',
)
BLADES = ['blade_1', 'blade_2', 'blade_3', 'blade_4']
OMEGA = 94.24777960769379  # rad/s, 900 rpm as on the test stand
STAMP0 = 1_763_700_000_000_000_000


def make_record(n=1200, omega=OMEGA, psi0=0.3, rate_hz=1000.0, seed=0):
    """Return a synthetic 4-blade Record: collective + lateral cyclic pitch, flap response."""
    rng = np.random.default_rng(seed)
    time_s = np.arange(n) / rate_hz
    speed = omega * (1.0 + 0.002 * np.sin(2.0 * time_s))   # slightly varying Ω
    t = psi0 + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1])
                                                * np.diff(time_s))])
    azimuths = t[:, None] + np.arange(4) * np.pi / 2
    pitch = 0.035 + 0.026 * np.cos(azimuths) + 1e-4 * rng.normal(size=(n, 4))
    flap = 0.01 + 0.008 * np.sin(azimuths - 0.4) + 1e-3 * rng.normal(size=(n, 4))
    return Record(time_s=time_s, t=t, rotor_speed_rad_s=speed, blade_flap=flap,
                  blade_pitch=pitch, blade_names=BLADES, source='synthetic', stamp0_ns=STAMP0)


def record_streams(record):
    """Return {topic: (stamps_ns, names, position, velocity)} of the convention for a Record."""
    stamps = STAMP0 + np.round(record.time_s * 1e9).astype(np.int64)
    psi = np.mod(record.t, 2 * np.pi)[:, None]
    return {
        DEFAULT_TOPICS['blade_pitch']: (stamps, BLADES, record.blade_pitch, None),
        DEFAULT_TOPICS['blade_flap']: (stamps, BLADES, record.blade_flap, None),
        DEFAULT_TOPICS['azimuth']: (stamps, ['rotor'], psi,
                                    record.rotor_speed_rad_s[:, None]),
    }


def write_streams(path, streams, storage='mcap', extra=None):
    """
    Write JointState topics into a new bag.

    Parameters
    ----------
    path
        New bag directory.
    streams
        topic -> (stamps_ns, names, position, velocity or None), or topic -> list of
        (stamp_ns, CDR bytes) for hand-made messages.
    storage
        'mcap' or 'sqlite3'.
    extra
        topic -> list of (stamp_ns, rosbags message) of other types.

    Returns
    -------
    The bag directory.

    """
    with open_writer(path, storage) as writer:
        messages = []
        for topic, stream in streams.items():
            writer.add_topic(topic, JOINT_STATE)
            if isinstance(stream, tuple):
                stamps, names, position, velocity = stream
                stream = list(zip(np.asarray(stamps).tolist(),
                                  encode_batch(stamps, names, position, velocity,
                                               frame_id='rotor')))
            messages += [(stamp, topic, data) for stamp, data in stream]
        for stamp, topic, data in sorted(messages, key=lambda m: m[0]):
            writer.write_raw(topic, max(stamp, 0), data)
        for topic, items in (extra or {}).items():
            for stamp, message in items:
                writer.write(topic, stamp, message)
    return Path(path)


def split_bag(source, target, parts):
    """
    Copy a bag into ``parts`` storage files of equal receive-time spans, as rosbag2 splits.

    ``ros2 bag record --max-bag-duration`` writes NAME/NAME_0.mcap, NAME_1.mcap, ... and one
    metadata.yaml listing them (``relative_file_paths``, ``files`` with each file's start,
    duration and message count) with the topics' counts summed. Each part is written by
    rosbags' Writer, its file moved into ``target``, and the parts' metadata merged.
    """
    import shutil
    from rosbags.rosbag2 import Reader
    import yaml
    source, target = Path(source), Path(target)
    storage = 'mcap' if any(source.glob('*.mcap')) else 'sqlite3'
    with Reader(source) as reader:
        messages = list(reader.messages())
        start, end = reader.start_time, reader.end_time
        topics = [(c.topic, c.msgtype) for c in reader.connections]
    edges = np.linspace(start, end, parts + 1).astype(np.int64)
    edges[-1] = end + 1
    target.mkdir()
    infos = []
    for k in range(parts):
        name = f'{target.name}_{k}'
        part = target.parent / f'{name}.part'
        with open_writer(part, storage) as writer:
            for topic, msgtype in topics:
                writer.add_topic(topic, msgtype)
            for connection, stamp, data in messages:
                if edges[k] <= stamp < edges[k + 1]:
                    writer.write_raw(connection.topic, stamp, data)
        stored = next(p for p in part.iterdir() if p.name != 'metadata.yaml')
        stored.rename(target / f'{name}{stored.suffix}')
        info = yaml.safe_load((part / 'metadata.yaml').read_text())
        infos.append((f'{name}{stored.suffix}', info['rosbag2_bagfile_information']))
        shutil.rmtree(part)
    merged = dict(infos[0][1])
    merged['relative_file_paths'] = [name for name, _ in infos]
    merged['files'] = [{**info['files'][0], 'path': name} for name, info in infos]
    merged['message_count'] = sum(info['message_count'] for _, info in infos)
    first = min(info['starting_time']['nanoseconds_since_epoch'] for _, info in infos)
    last = max(info['starting_time']['nanoseconds_since_epoch']
               + info['duration']['nanoseconds'] for _, info in infos)
    merged['starting_time'] = {'nanoseconds_since_epoch': first}
    merged['duration'] = {'nanoseconds': last - first}
    counts = {}
    for _, info in infos:
        for entry in info['topics_with_message_count']:
            name = entry['topic_metadata']['name']
            counts.setdefault(name, dict(entry, message_count=0))
            counts[name]['message_count'] += entry['message_count']
    merged['topics_with_message_count'] = list(counts.values())
    (target / 'metadata.yaml').write_text(
        yaml.safe_dump({'rosbag2_bagfile_information': merged}, sort_keys=False))
    return target
