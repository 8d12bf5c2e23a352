"""Helpers of the input-layer tests: where the shared recordings are, small synthetic bags."""

from pathlib import Path

import numpy as np
from rotor_id.io.bag import DEFAULT_TOPICS, open_writer
from rotor_id.io.jointstate_cdr import encode_batch, JOINT_STATE
from rotor_id.io.record import Record

# /work/main/test/io/io_helpers.py -> /work/shared/recordings
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
