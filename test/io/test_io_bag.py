"""Reading and writing bags: round trips, independent decoding, and the bad-input catalogue."""

import math
from pathlib import Path
import re
import shutil
import warnings

from io_helpers import BLADES, make_record, OMEGA, record_streams, STAMP0, write_streams
import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores
from rotor_id.io.bag import (
    BagError, BagWarning, message_with_defaults, open_writer, read_record, register_msg_dir,
    typestore_with_custom_types, write_record_bag,
)
from rotor_id.io.jointstate_cdr import encode_batch, JOINT_STATE

PITCH, FLAP, AZIMUTH = '/rotor/blade_pitch', '/rotor/blade_flap', '/rotor/azimuth'
MSG_DIR = Path(__file__).resolve().parents[2] / 'msg_defs' / 'msg'
FIXTURE_MSGS = Path(__file__).resolve().parent / 'fixtures' / 'probe_msgs' / 'msg'


def read_quietly(path, **kwargs):
    """read_record with its summary BagWarning caught (checked through record.warnings)."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', BagWarning)
        return read_record(path, **kwargs)


def assert_same_record(got, want, t_tol=1e-9):
    np.testing.assert_allclose(got.time_s, want.time_s, atol=1e-12)
    np.testing.assert_allclose(got.t, want.t, atol=t_tol)
    np.testing.assert_array_equal(got.blade_flap, want.blade_flap)
    np.testing.assert_allclose(got.blade_pitch, want.blade_pitch, atol=1e-15)
    np.testing.assert_allclose(got.rotor_speed_rad_s, want.rotor_speed_rad_s, rtol=1e-15)
    assert got.blade_names == want.blade_names


# --------------------------------------------------------------------------- round trips

@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_record_round_trip(tmp_path, storage):
    record = make_record(n=1500, psi0=5.9)
    bag = write_record_bag(tmp_path / 'bag', record, storage=storage)
    meta = (bag / 'metadata.yaml').read_text()
    assert 'version: 9' in meta and f'storage_identifier: {storage}' in meta
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        got = read_record(bag)
    assert got.warnings == []
    assert got.stamp0_ns == STAMP0
    assert got.t[0] == pytest.approx(5.9)
    assert_same_record(got, record)


def test_mcap_written_bag_decodes_with_independent_mcap_ros2_reader(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    record = make_record(n=40)
    bag = write_record_bag(tmp_path / 'bag', record, storage='mcap')
    flap = []
    with open(bag / 'bag.mcap', 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        for schema, channel, _, msg in reader.iter_decoded_messages():
            assert schema.name == JOINT_STATE and schema.encoding == 'ros2msg'
            assert channel.message_encoding == 'cdr'
            if channel.topic == FLAP:
                assert list(msg.name) == BLADES
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                flap.append((stamp, list(msg.position)))
    assert [s for s, _ in flap] == [STAMP0 + i * 1_000_000 for i in range(40)]
    np.testing.assert_array_equal([p for _, p in flap], record.blade_flap)


def _generated_type_hash(type_name):
    """Return the RIHS01 hash rosidl generated for a type (share/PKG/msg/NAME.json), or None."""
    import json
    from ament_index_python.packages import get_package_share_directory
    package, _, name = type_name.split('/')
    try:
        path = Path(get_package_share_directory(package)) / 'msg' / f'{name}.json'
        hashes = json.loads(path.read_text())['type_hashes']
    except (LookupError, OSError, ValueError, KeyError):
        return None
    return next(h['hash_string'] for h in hashes if h['type_name'] == type_name)


@pytest.mark.ros
def test_mcap_channels_carry_the_type_hash_as_rosbag2_writes(tmp_path):
    """
    Each MCAP channel's metadata holds ``offered_qos_profiles`` and ``topic_type_hash``.

    The hash is the one rosidl generated for the type at its package's build (REP-2011,
    share/PKG/msg/NAME.json) and the one metadata.yaml gives as ``type_description_hash``.
    """
    from mcap.reader import make_reader
    import yaml
    store = typestore_with_custom_types()
    estimate = message_with_defaults(store, 'rotor_id_msgs/msg/ParameterEstimate')
    bag = write_record_bag(tmp_path / 'bag', make_record(n=20),
                           extra=[('/rotor_id/estimate', STAMP0, estimate)], typestore=store)
    with open(bag / 'bag.mcap', 'rb') as stream:
        channels = {c.topic: c.metadata
                    for c in make_reader(stream).get_summary().channels.values()}
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    listed = {t['topic_metadata']['name']: t['topic_metadata']
              for t in info['topics_with_message_count']}
    assert set(channels) == {FLAP, PITCH, AZIMUTH, '/rotor_id/estimate'}
    checked = 0
    for topic, metadata in channels.items():
        assert set(metadata) == {'offered_qos_profiles', 'topic_type_hash'}
        assert metadata['topic_type_hash'] == listed[topic]['type_description_hash']
        assert re.fullmatch(r'RIHS01_[0-9a-f]{64}', metadata['topic_type_hash'])
        generated = _generated_type_hash(listed[topic]['type'])
        if generated is not None:
            assert metadata['topic_type_hash'] == generated, topic
            checked += 1
    assert checked >= 3, 'sensor_msgs (in the venv) must give the generated hash'


def test_custom_messages_are_written_with_embedded_definitions(tmp_path):
    """A custom type registered from a .msg directory decodes from the MCAP schema alone."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    typestore = get_typestore(Stores.ROS2_JAZZY)
    assert register_msg_dir(typestore, FIXTURE_MSGS) == ['probe_msgs/msg/Probe',
                                                         'probe_msgs/msg/Sample']
    probe, sample = typestore.types['probe_msgs/msg/Probe'], typestore.types[
        'probe_msgs/msg/Sample']
    header = typestore.types['std_msgs/msg/Header'](
        stamp=typestore.types['builtin_interfaces/msg/Time'](sec=5, nanosec=7), frame_id='hub')
    msg = probe(header=header, samples=[sample(index=3, value=0.25)],
                gains=np.array([1.0, 2.0, 3.0, 4.0]), note='stirring')
    record = make_record(n=20)
    bag = write_record_bag(tmp_path / 'bag', record, extra=[('/probe', STAMP0 + 5, msg)],
                           typestore=typestore)
    with open(bag / 'bag.mcap', 'rb') as stream:
        decoded = [(schema, m) for schema, channel, _, m in make_reader(
            stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=['/probe'])]
    assert len(decoded) == 1
    schema, got = decoded[0]
    assert schema.encoding == 'ros2msg'
    assert 'MSG: probe_msgs/Sample' in schema.data.decode()
    assert 'MSG: std_msgs/Header' in schema.data.decode()
    assert got.note == 'stirring' and list(got.gains) == [1.0, 2.0, 3.0, 4.0]
    assert (got.samples[0].index, got.samples[0].value) == (3, 0.25)
    assert got.header.frame_id == 'hub'
    assert_same_record(read_record(bag), record)   # the extra topic does not disturb reading


def test_project_messages_register(tmp_path):
    if not list(MSG_DIR.glob('*.msg')):
        pytest.skip(f'no custom messages at {MSG_DIR}')
    typestore = get_typestore(Stores.ROS2_JAZZY)
    names = register_msg_dir(typestore, MSG_DIR)
    assert names == sorted(f'rotor_id_msgs/msg/{p.stem}' for p in MSG_DIR.glob('*.msg'))
    with open_writer(tmp_path / 'bag', 'sqlite3', typestore) as writer:
        for i, name in enumerate(names):
            writer.add_topic(f'/custom_{i}', name)
    assert all(name in (tmp_path / 'bag' / 'metadata.yaml').read_text() for name in names)


def test_open_writer_refuses_existing_path_and_unknown_storage(tmp_path):
    with pytest.raises(BagError, match='exists already'):
        open_writer(tmp_path, 'mcap')
    with pytest.raises(BagError, match='unknown storage'):
        open_writer(tmp_path / 'new', 'rosbag1')


# --------------------------------------------------------------------------- locating the bag

def test_missing_path(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        read_record(tmp_path / 'nope')


def test_not_a_bag(tmp_path):
    (tmp_path / 'notes.txt').write_text('hello')
    with pytest.raises(BagError, match='not a bag'):
        read_record(tmp_path)
    with pytest.raises(BagError, match='not a bag'):
        read_record(tmp_path / 'notes.txt')
    (tmp_path / 'fake.mcap').write_bytes(b'this is not mcap at all' * 10)
    with pytest.raises(BagError, match='cannot be opened as an MCAP bag'):
        read_record(tmp_path / 'fake.mcap')
    (tmp_path / 'fake.db3').write_bytes(b'this is not sqlite' * 10)
    with pytest.raises(BagError, match='cannot be opened as a sqlite3 bag'):
        read_record(tmp_path / 'fake.db3')


def test_empty_storage_file(tmp_path):
    (tmp_path / 'empty.mcap').write_bytes(b'')
    with pytest.raises(BagError, match='empty'):
        read_record(tmp_path / 'empty.mcap')


def test_bag_without_messages(tmp_path):
    empty = np.empty((0, 4))
    bag = write_streams(tmp_path / 'bag', {
        PITCH: (np.empty(0, np.int64), BLADES, empty, None),
        FLAP: (np.empty(0, np.int64), BLADES, empty, None),
        AZIMUTH: (np.empty(0, np.int64), ['rotor'], np.empty((0, 1)), np.empty((0, 1))),
    })
    with pytest.raises(BagError, match='no messages.*empty'):
        read_record(bag)


def test_directory_holding_only_the_storage_file(tmp_path):
    record = make_record(n=30)
    bag = write_record_bag(tmp_path / 'bag', record)
    (bag / 'metadata.yaml').unlink()
    assert_same_record(read_record(bag), record)


def test_broken_metadata_names_the_file(tmp_path):
    bag = write_record_bag(tmp_path / 'bag', make_record(n=30))
    (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: [1, 2]')
    with pytest.raises(BagError, match='metadata.yaml is not rosbag2 metadata'):
        read_record(bag)


# --------------------------------------------------------------------------- damaged storage

def test_truncated_mcap_recovers_the_readable_messages(tmp_path, recordings):
    source = recordings / 'id_wake_progressing'
    bag = tmp_path / 'cut'
    shutil.copytree(source, bag)
    storage = bag / 'id_wake_progressing.mcap'
    data = storage.read_bytes()
    storage.chmod(0o644)
    storage.write_bytes(data[:len(data) // 2])
    full = read_record(source)
    with pytest.warns(BagWarning, match='damaged'):
        cut = read_record(bag)
    assert 0.4 * len(full) < len(cut) < 0.6 * len(full)
    assert any('recovered' in w for w in cut.warnings)
    assert any('of the 1065 messages listed in metadata.yaml' in w for w in cut.warnings)
    n = len(cut)
    np.testing.assert_array_equal(cut.blade_flap, full.blade_flap[:n])
    np.testing.assert_array_equal(cut.t, full.t[:n])


def test_mcap_without_footer_is_recovered_completely(tmp_path):
    record = make_record(n=300)
    bag = write_record_bag(tmp_path / 'bag', record)
    storage = bag / 'bag.mcap'
    data = storage.read_bytes()
    # cut right after the data section: everything recorded is there, the index is not
    data_end = data.index(b'\x0f\x04\x00\x00\x00\x00\x00\x00\x00')
    storage.write_bytes(data[:data_end])
    got = read_quietly(bag)
    assert_same_record(got, record)
    assert any('recovered' in w for w in got.warnings)


def test_truncated_sqlite3_is_a_clear_error(tmp_path, recordings):
    bag = tmp_path / 'cut'
    shutil.copytree(recordings / 'id_multiblade_mu04', bag)
    storage = bag / 'id_multiblade_mu04.db3'
    data = storage.read_bytes()
    storage.chmod(0o644)
    storage.write_bytes(data[:len(data) // 2])
    with pytest.raises(BagError, match='damaged.*recover'):
        read_record(bag)


# --------------------------------------------------------------------------- topics and types

def test_missing_topic_names_the_topics_there(tmp_path):
    bag = write_record_bag(tmp_path / 'bag', make_record(n=30))
    with pytest.raises(BagError) as err:
        read_record(bag, topics={'blade_flap': '/rotor/flap'})
    message = str(err.value)
    assert '/rotor/flap' in message and 'blade_flap' in message
    assert all(topic in message for topic in (PITCH, FLAP, AZIMUTH))


def test_wrong_message_type(tmp_path):
    typestore = get_typestore(Stores.ROS2_JAZZY)
    float64 = typestore.types['std_msgs/msg/Float64']
    streams = record_streams(make_record(n=30))
    del streams[AZIMUTH]
    bag = write_streams(tmp_path / 'bag', streams,
                        extra={AZIMUTH: [(STAMP0, float64(data=1.0))]})
    with pytest.raises(BagError, match='azimuth.*has message type std_msgs/msg/Float64'):
        read_record(bag)


def test_no_azimuth_topic_uses_the_given_speed(tmp_path):
    record = make_record(n=200)
    streams = record_streams(record)
    del streams[AZIMUTH]
    bag = write_streams(tmp_path / 'bag', streams)
    with pytest.raises(BagError, match='omega_rad_s'):
        read_record(bag, topics={'azimuth': None})
    got = read_quietly(bag, topics={'azimuth': None}, omega_rad_s=OMEGA)
    np.testing.assert_allclose(got.t, OMEGA * got.time_s)
    assert any('no azimuth topic' in w for w in got.warnings)
    # the convention's azimuth topic absent from the bag: same fallback, said so
    with pytest.raises(BagError, match='or pass omega_rad_s'):
        read_record(bag)
    got = read_quietly(bag, omega_rad_s=OMEGA)
    np.testing.assert_allclose(got.t, OMEGA * got.time_s)
    assert f'azimuth topic {AZIMUTH} not in the bag' in got.warnings


# --------------------------------------------------------------------------- joints

def test_joint_names_missing_or_unknown(tmp_path):
    record = make_record(n=30)
    streams = record_streams(record)
    stamps = streams[FLAP][0]
    streams[FLAP] = (stamps, [], np.empty((30, 0)), None)
    with pytest.raises(BagError, match='no joint names'):
        read_record(write_streams(tmp_path / 'a', streams))
    odd = ['front', 'left', 'back', 'right']
    streams[FLAP] = (stamps, odd, record.blade_flap, None)
    streams[PITCH] = (stamps, odd, record.blade_pitch, None)
    with pytest.raises(BagError, match='cannot tell the blade.*joint_names'):
        read_record(write_streams(tmp_path / 'b', streams))
    got = read_record(tmp_path / 'b', joint_names={'blade_1': 'front', 'blade_2': 'left',
                                                   'blade_3': 'back', 'blade_4': 'right'})
    np.testing.assert_array_equal(got.blade_flap, record.blade_flap)
    with pytest.raises(BagError, match=r"joints \['rear'\] named in joint_names"):
        read_record(tmp_path / 'b', joint_names=['front', 'left', 'rear', 'right'])


def test_joints_in_any_order_are_put_in_blade_order(tmp_path):
    record = make_record(n=30)
    streams = record_streams(record)
    order = [2, 0, 3, 1]
    stamps = streams[FLAP][0]
    streams[FLAP] = (stamps, [BLADES[i] for i in order], record.blade_flap[:, order], None)
    got = read_record(write_streams(tmp_path / 'bag', streams))
    np.testing.assert_array_equal(got.blade_flap, record.blade_flap)
    assert got.blade_names == BLADES


def test_blade_count_differs_between_pitch_and_flap(tmp_path):
    record = make_record(n=30)
    streams = record_streams(record)
    streams[PITCH] = (streams[PITCH][0], BLADES[:3], record.blade_pitch[:, :3], None)
    with pytest.raises(BagError, match='has 4 blades but /rotor/blade_pitch has 3'):
        read_record(write_streams(tmp_path / 'bag', streams))
    with pytest.raises(BagError, match='rotor.blades = 3'):
        read_record(write_record_bag(tmp_path / 'ok', record), n_blades=3)


def test_record_tells_the_joints_the_bag_carries(tmp_path):
    """The joints seen on the flap and pitch topics stay on the Record, whatever was selected."""
    record = make_record(n=30)
    got = read_quietly(write_record_bag(tmp_path / 'four', record))
    assert got.flap_joints == got.pitch_joints == tuple(BLADES)
    assert got.bag_blade_count == 4
    assert got.window(0.0, 0.01).bag_blade_count == 4
    streams = record_streams(record)
    stamps = streams[FLAP][0]
    five = BLADES + ['blade_5']
    extra = np.hstack([record.blade_flap, record.blade_flap[:, :1]])
    streams[FLAP] = (stamps, five, extra, None)
    streams[PITCH] = (stamps, five, np.hstack([record.blade_pitch, record.blade_pitch[:, :1]]),
                      None)
    got = read_quietly(write_streams(tmp_path / 'five', streams), joint_names=BLADES)
    assert got.n_blades == 4 and got.flap_joints == tuple(five) and got.bag_blade_count == 5
    assert make_record(n=5).bag_blade_count is None


# --------------------------------------------------------------------------- samples

def test_nan_and_inf_samples_are_dropped_and_counted(tmp_path):
    record = make_record(n=300)
    streams = record_streams(record)
    flap = record.blade_flap.copy()
    flap[[10, 20, 30], 1] = np.nan
    flap[40, 3] = np.inf
    streams[FLAP] = (streams[FLAP][0], BLADES, flap, None)
    pitch = record.blade_pitch.copy()
    pitch[50, 0] = np.nan
    streams[PITCH] = (streams[PITCH][0], BLADES, pitch, None)
    with pytest.warns(BagWarning, match='NaN/inf'):
        got = read_record(write_streams(tmp_path / 'bag', streams))
    assert len(got) == 296
    assert f'{FLAP}: dropped 4 sample(s) whose position is NaN/inf' in got.warnings
    assert f'{PITCH}: dropped 1 sample(s) whose position is NaN/inf' in got.warnings
    # the pitch sample is interpolated from its neighbours
    i = int(np.flatnonzero(got.time_s == record.time_s[50])[0])
    assert got.blade_pitch[i, 0] == pytest.approx(
        0.5 * (record.blade_pitch[49, 0] + record.blade_pitch[51, 0]))


def test_out_of_order_and_repeated_stamps_are_sorted_and_dropped(tmp_path):
    record = make_record(n=200)
    streams = record_streams(record)
    stamps, _, flap, _ = streams[FLAP]
    raw = encode_batch(stamps, BLADES, flap, frame_id='rotor')
    order = list(range(200))
    order[50], order[51] = 51, 50                     # one pair swapped in arrival order
    order[120:123] = [122, 120, 121]                  # two late, one early
    received = [(int(stamps[0]) + k * 1_000_000, raw[i]) for k, i in enumerate(order)]
    received.insert(100, (int(stamps[0]) + 99_500_000, raw[99]))   # duplicate of sample 99
    received.insert(10, (int(stamps[0]) + 9_500_000, raw[9]))
    streams[FLAP] = received
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert_same_record(got, record)
    assert f'{FLAP}: 2 stamp(s) out of order; samples sorted by header.stamp' in got.warnings
    assert any('dropped 2 sample(s) with a repeated stamp' in w for w in got.warnings)


def test_gap_is_reported_in_revolutions(tmp_path):
    record = make_record(n=600)
    keep = np.ones(600, dtype=bool)
    keep[200:240] = False                             # 41 ms without flap samples
    streams = record_streams(record)
    stamps, names, flap, _ = streams[FLAP]
    streams[FLAP] = (stamps[keep], names, flap[keep], None)
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert len(got) == 560
    revs = 0.041 * record.omega_mean / (2 * math.pi)
    gap = [w for w in got.warnings if 'gap' in w]
    assert len(gap) == 1 and FLAP in gap[0] and f'{revs:.3g} rev' in gap[0]
    np.testing.assert_allclose(got.t, record.t[keep], atol=1e-9)


def test_pitch_gap_is_interpolated(tmp_path):
    record = make_record(n=600)
    keep = np.ones(600, dtype=bool)
    keep[300:310] = False
    streams = record_streams(record)
    stamps, names, pitch, _ = streams[PITCH]
    streams[PITCH] = (stamps[keep], names, pitch[keep], None)
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert len(got) == 600
    assert any(PITCH in w and 'interpolated' in w for w in got.warnings)
    expected = np.interp(record.time_s[305], record.time_s[[299, 310]],
                         record.blade_pitch[[299, 310], 2])
    assert got.blade_pitch[305, 2] == pytest.approx(expected)


@pytest.mark.parametrize('topic', [FLAP, PITCH])
def test_angles_in_degrees_are_refused(tmp_path, topic):
    record = make_record(n=50)
    streams = record_streams(record)
    stamps, names, values, _ = streams[topic]
    streams[topic] = (stamps, names, np.degrees(values), None)
    with pytest.raises(BagError, match=f'{topic}: .*look like degrees'):
        read_record(write_streams(tmp_path / 'bag', streams))


@pytest.mark.parametrize('speed', [0.0, -OMEGA])
def test_zero_or_negative_rotor_speed_is_refused(tmp_path, speed):
    record = make_record(n=50)
    streams = record_streams(record)
    stamps, names, psi, omega = streams[AZIMUTH]
    omega = omega.copy()
    omega[20:] = speed
    streams[AZIMUTH] = (stamps, names, psi, omega)
    with pytest.raises(BagError, match='zero or negative'):
        read_record(write_streams(tmp_path / 'bag', streams))


def test_azimuth_in_degrees_is_refused(tmp_path):
    record = make_record(n=300)
    streams = record_streams(record)
    stamps, names, psi, omega = streams[AZIMUTH]
    streams[AZIMUTH] = (stamps, names, np.degrees(psi), omega)
    with pytest.raises(BagError, match='degrees or rpm'):
        read_record(write_streams(tmp_path / 'bag', streams))


def test_unfilled_header_stamps_fall_back_to_receive_time(tmp_path):
    record = make_record(n=100)
    streams = record_streams(record)
    for topic, (stamps, names, position, velocity) in list(streams.items()):
        raw = encode_batch(np.zeros_like(stamps), names, position, velocity)
        streams[topic] = list(zip(stamps.tolist(), raw))
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert_same_record(got, record)
    assert any('header.stamp is not filled' in w for w in got.warnings)


def test_a_few_unfilled_stamps_are_dropped(tmp_path):
    record = make_record(n=100)
    streams = record_streams(record)
    stamps, names, position, _ = streams[FLAP]
    header = stamps.copy()
    header[[0, 40]] = 0
    streams[FLAP] = list(zip(stamps.tolist(), encode_batch(header, names, position)))
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    keep = np.ones(100, dtype=bool)
    keep[[0, 40]] = False
    assert got.time_s[0] == 0.0 and got.stamp0_ns == stamps[1]
    np.testing.assert_array_equal(got.blade_flap, record.blade_flap[keep])
    np.testing.assert_allclose(got.t, record.t[keep], atol=1e-9)
    assert f'{FLAP}: dropped 2 sample(s) whose header.stamp is not filled (zero)' in got.warnings


def test_velocity_missing_takes_speed_from_azimuth_rate(tmp_path):
    record = make_record(n=400)
    streams = record_streams(record)
    stamps, names, psi, _ = streams[AZIMUTH]
    streams[AZIMUTH] = (stamps, names, psi, None)
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    np.testing.assert_allclose(got.t, record.t, atol=1e-9)
    np.testing.assert_allclose(got.rotor_speed_rad_s, record.rotor_speed_rad_s, rtol=1e-4)
    assert any('no velocity' in w for w in got.warnings)
