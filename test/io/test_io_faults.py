"""Rig faults on the input side: runs, clock glitches, several publishers, azimuth glitches."""

from pathlib import Path
import warnings

from io_helpers import BLADES, make_record, record_streams, STAMP0, write_streams
import numpy as np
import pytest
from rosbags.rosbag2.writer import CompressionFormat, CompressionMode, Writer
from rosbags.typesys import get_typestore, Stores
from rotor_id.io.bag import (
    BagError, BagWarning, BagWriter, read_record, read_run, STORAGES, write_record_bag,
)
from rotor_id.io.jointstate_cdr import encode_batch, JOINT_STATE
from rotor_id.io.run_description import parse_run_description
import yaml

PITCH, FLAP, AZIMUTH = '/rotor/blade_pitch', '/rotor/blade_flap', '/rotor/azimuth'
MS = 1_000_000


def read_quietly(path, **kwargs):
    """read_record with its summary BagWarning caught (checked through record.warnings)."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', BagWarning)
        return read_record(path, **kwargs)


def messages_of(record, stamp0=STAMP0, log0=None):
    """(receive time, topic, CDR bytes) of a Record's three topics, in recording order."""
    streams = record_streams(record)
    stamps = stamp0 + np.round(record.time_s * 1e9).astype(np.int64)
    log0 = stamp0 if log0 is None else log0
    out = []
    encoded = {topic: encode_batch(stamps, names, position, velocity, frame_id='rotor')
               for topic, (_, names, position, velocity) in streams.items()}
    for i, stamp in enumerate(stamps.tolist()):
        for topic in (PITCH, FLAP, AZIMUTH):
            out.append((log0 + stamp - stamp0, topic, encoded[topic][i]))
    return out


def write_in_order(path, messages, storage='mcap'):
    """Write (receive time, topic, bytes) messages in the given order (receive time kept)."""
    writer = Writer(path, version=9, storage_plugin=STORAGES[storage])
    writer.open()
    with BagWriter(writer, get_typestore(Stores.ROS2_JAZZY)) as bag:
        for topic in (PITCH, FLAP, AZIMUTH):
            bag.add_topic(topic, JOINT_STATE)
        for log_ns, topic, data in messages:
            bag.write_raw(topic, log_ns, data)
    return Path(path)


# --------------------------------------------------------------------------- compression

@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_per_message_compression_is_read(tmp_path, storage):
    """rosbag2 compression_mode: message (zstd per message) reads like the plain bag."""
    record = make_record(n=400)
    writer = Writer(tmp_path / 'bag', version=9, storage_plugin=STORAGES[storage])
    writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    writer.open()
    with BagWriter(writer, get_typestore(Stores.ROS2_JAZZY)) as bag:
        for topic in (PITCH, FLAP, AZIMUTH):
            bag.add_topic(topic, JOINT_STATE)
        for log_ns, topic, data in messages_of(record):
            bag.write_raw(topic, log_ns, data)
    meta = yaml.safe_load((tmp_path / 'bag' / 'metadata.yaml').read_text())
    assert meta['rosbag2_bagfile_information']['compression_mode'] == 'message'
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        got = read_record(tmp_path / 'bag')
    np.testing.assert_array_equal(got.blade_flap, record.blade_flap)
    np.testing.assert_allclose(got.t, record.t, atol=1e-9)
    # the storage file alone (no metadata.yaml): the zstd frames are recognised
    if storage == 'mcap':
        alone = read_quietly(tmp_path / 'bag' / 'bag.mcap')
        np.testing.assert_array_equal(alone.blade_flap, record.blade_flap)


def test_unsupported_compression_format_is_refused_by_name(tmp_path):
    bag = write_record_bag(tmp_path / 'bag', make_record(n=50))
    meta_path = bag / 'metadata.yaml'
    meta = yaml.safe_load(meta_path.read_text())
    meta['rosbag2_bagfile_information'].update(compression_mode='message',
                                               compression_format='lz4')
    meta_path.write_text(yaml.safe_dump(meta))
    with pytest.raises(BagError, match=r"message-level compression with format 'lz4'") as err:
        read_record(bag)
    assert 'corrupt' not in str(err.value)


# --------------------------------------------------------------------------- runs

def two_runs(tmp_path, second_start_s, storage='mcap'):
    """Write run 1 (1.5 s), then run 2 (1.2 s) whose clock restarted at second_start_s."""
    first = make_record(n=1500, psi0=0.3, seed=1)
    second = make_record(n=1200, psi0=2.1, seed=2)
    start2 = STAMP0 + int(second_start_s * 1e9)
    messages = messages_of(first) + messages_of(second, stamp0=start2,
                                                log0=STAMP0 + 2_000 * MS)
    return write_in_order(tmp_path / f'runs_{storage}', messages, storage), first, second


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_clock_reset_is_reported_with_its_place_and_a_run_is_selected(tmp_path, storage):
    """A second run whose clock restarted 100 s before run 1 ended is neither merged nor used."""
    bag, first, second = two_runs(tmp_path, 1.5 - 100.0, storage)
    with pytest.raises(BagError) as err:
        read_record(bag)
    text = str(err.value)
    assert '\n' not in text
    assert 'jump back 99.999 s' in text and 'message 1501 of 2700' in text
    assert 'received 2.000 s into the bag' in text
    assert 'run 1: 1500 samples' in text and 'run 2: 1200 samples' in text
    assert '`run: K`' in text
    got1 = read_quietly(bag, run=1)
    np.testing.assert_array_equal(got1.blade_flap, first.blade_flap)
    np.testing.assert_allclose(got1.t, first.t, atol=1e-9)
    got2 = read_quietly(bag, run=2)
    assert got2.stamp0_ns == STAMP0 - 98_500 * MS
    np.testing.assert_array_equal(got2.blade_flap, second.blade_flap)
    np.testing.assert_allclose(got2.t, second.t, atol=1e-9)
    with pytest.raises(BagError, match='run 3 asked for.*holds 2 runs'):
        read_record(bag, run=3)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_reset_is_found_when_only_the_window_would_be_read(tmp_path, monkeypatch, storage):
    """The window read checks the clock offset at the end and reads it all when it moved."""
    from rotor_id.io import bag as bag_module
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
    bag, _, _ = two_runs(tmp_path, 1.5 - 100.0, storage)
    with pytest.raises(BagError, match='jump back 99.999 s.*`run: K`'):
        read_record(bag, window_s=(0.2, 0.3))


def test_overlapping_runs_are_separated(tmp_path):
    bag, first, second = two_runs(tmp_path, 0.5)       # run 2's stamps overlap run 1's
    with pytest.raises(BagError, match='jump back 0.999 s.*run 2: 1200 samples, stamps '
                                       r'\+0.500 to \+1.699 s'):
        read_record(bag)
    np.testing.assert_array_equal(read_quietly(bag, run=2).blade_flap, second.blade_flap)


def test_run_key_of_the_run_description_selects_the_run(tmp_path):
    bag, _, second = two_runs(tmp_path, -100.0)
    text = ('rotor: {blades: 4, advance_ratio: 0.0, flap_frequency: 1.1, tip_loss: 0.97}\n'
            'model: multiblade\nunknowns: [gamma]\nwindow_s: [0.1, 1.0]\nrun: 2\n')
    description = parse_run_description(text)
    assert description.run == 2
    got = read_run(description, bag)
    np.testing.assert_array_equal(got.blade_flap, second.blade_flap)
    assert 'run 2' in got.source


def test_run_asked_of_a_bag_with_one_run(tmp_path):
    bag = write_record_bag(tmp_path / 'bag', make_record(n=100))
    assert len(read_quietly(bag, run=1)) == 100
    with pytest.raises(BagError, match='run 2 asked for, but the bag holds one run'):
        read_record(bag, run=2)


def test_clock_stepping_forward_is_not_a_gap(tmp_path):
    """Stamps jump 30 s ahead while the messages keep arriving every 1 ms: two runs."""
    record = make_record(n=1000)
    later = make_record(n=1000, psi0=1.0, seed=3)
    messages = messages_of(record) + messages_of(later, stamp0=STAMP0 + 31_000 * MS,
                                                 log0=STAMP0 + 1_000 * MS)
    bag = write_in_order(tmp_path / 'bag', messages)
    with pytest.raises(BagError, match='jump forward 30.001 s at message 1001 of 2000.*while '
                                       'the receive times do not.*`run: K`'):
        read_record(bag)
    np.testing.assert_array_equal(read_quietly(bag, run=2).blade_flap, later.blade_flap)


def test_forward_gap_is_not_a_second_run(tmp_path):
    """Stamps that jump forward (samples lost) continue the run: a gap, reported in rev."""
    record = make_record(n=1000)
    keep = np.r_[0:400, 700:1000]
    streams = {topic: (s[keep], names, p[keep], None if v is None else v[keep])
               for topic, (s, names, p, v) in record_streams(record).items()}
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert len(got) == 700
    assert any('gap' in w and '301 ms' in w for w in got.warnings)


@pytest.mark.parametrize('jump_s', [-37.0, 5.0, -0.2])
def test_clock_glitch_sample_is_dropped(tmp_path, jump_s):
    """One flap message whose stamp is far off while the next continue: dropped, said where."""
    record = make_record(n=800)
    messages = messages_of(record)
    index = 3 * 400 + 1                                 # flap message of sample 400
    log_ns, topic, _ = messages[index]
    assert topic == FLAP
    stamp = STAMP0 + 400 * MS + int(jump_s * 1e9)
    glitch = encode_batch([stamp], BLADES, record.blade_flap[400:401], frame_id='rotor')[0]
    messages[index] = (log_ns, topic, glitch)
    got = read_quietly(write_in_order(tmp_path / 'bag', messages))
    assert len(got) == 799
    assert not np.any(np.isin(got.time_s, [0.4]))
    assert any('clock glitch' in w and 'message 401 of 800' in w for w in got.warnings)


# --------------------------------------------------------------------------- publishers

def interleaved(record, shift_ns, flap_b):
    """Flap topic carrying the record's flap and a second stream flap_b, shift_ns later."""
    streams = record_streams(record)
    stamps = streams[FLAP][0]
    both = np.concatenate([stamps, stamps + shift_ns])
    values = np.concatenate([record.blade_flap, flap_b])
    streams[FLAP] = (both, BLADES, values, None)
    return streams


CALIBRATION = np.radians([0.3, -0.2, 0.4, 0.1])      # per-blade offsets, a few tenths of a degree


@pytest.mark.parametrize('shift_ms', [0.5, 0.3])
def test_raw_and_calibrated_streams_on_one_topic_are_refused(tmp_path, shift_ms):
    record = make_record(n=2000)
    streams = interleaved(record, int(shift_ms * MS), record.blade_flap + CALIBRATION)
    bag = write_streams(tmp_path / 'bag', streams)
    meta_path = bag / 'metadata.yaml'
    meta = yaml.safe_load(meta_path.read_text())
    for entry in meta['rosbag2_bagfile_information']['topics_with_message_count']:
        if entry['topic_metadata']['name'] == FLAP:
            entry['topic_metadata']['offered_qos_profiles'] = [{'depth': 10}, {'depth': 10}]
    meta_path.write_text(yaml.safe_dump(meta))
    with pytest.raises(BagError) as err:
        read_record(bag)
    text = str(err.value)
    assert text.startswith(f'{FLAP} (blade_flap): the samples are two streams merged')
    assert 'alternate samples differ by' in text and '2000 Hz' in text
    assert 'metadata.yaml lists 2 publishers' in text
    if shift_ms != 0.5:
        assert 'stamp steps alternate 0.3 ms / 0.7 ms' in text


def test_gain_calibrated_second_stream_is_refused(tmp_path):
    """A calibration that is a gain (no offset) still leaves alternate samples apart."""
    record = make_record(n=2000)
    streams = interleaved(record, MS // 2, 1.03 * record.blade_flap)
    with pytest.raises(BagError, match='two streams merged'):
        read_record(write_streams(tmp_path / 'bag', streams))


def test_same_measurement_published_twice_is_refused(tmp_path):
    """The same samples republished 0.5 ms later: near-identical pairs."""
    record = make_record(n=2000)
    streams = interleaved(record, MS // 2, record.blade_flap + 1e-6)
    with pytest.raises(BagError, match='near-identical pairs'):
        read_record(write_streams(tmp_path / 'bag', streams))
    streams = interleaved(record, MS // 2, record.blade_flap)            # bit for bit
    with pytest.raises(BagError, match='samples come in identical pairs'):
        read_record(write_streams(tmp_path / 'exact', streams))


def test_publishers_naming_their_frames_are_named(tmp_path):
    record = make_record(n=1000)
    streams = record_streams(record)
    stamps = streams[FLAP][0]
    raw = encode_batch(stamps, BLADES, record.blade_flap, frame_id='flap_raw')
    calibrated = encode_batch(stamps + MS // 2, BLADES, record.blade_flap + CALIBRATION,
                              frame_id='flap_calibrated')
    streams[FLAP] = sorted([(int(s), m) for s, m in zip(stamps, raw)]
                           + [(int(s) + MS // 2, m) for s, m in zip(stamps, calibrated)])
    with pytest.raises(BagError, match="header.frame_id 'flap_raw' in 1000 messages, "
                                       "'flap_calibrated' in 1000 messages"):
        read_record(write_streams(tmp_path / 'bag', streams))


def test_second_publisher_with_the_same_stamps_is_refused(tmp_path):
    record = make_record(n=600)
    streams = interleaved(record, 0, record.blade_flap + CALIBRATION)
    with pytest.raises(BagError, match='600 of 1200 stamps come twice with different values'):
        read_record(write_streams(tmp_path / 'bag', streams))
    exact = interleaved(record, 0, record.blade_flap)      # a relay: exact duplicates
    got = read_quietly(write_streams(tmp_path / 'dup', exact))
    assert len(got) == 600
    assert f'{FLAP}: dropped 600 sample(s) with a repeated stamp (exact duplicates); the first ' \
        'of each is kept' in got.warnings


@pytest.mark.parametrize('seed', range(6))
def test_one_sensor_is_not_taken_for_two_streams(tmp_path, seed):
    """Clean recordings with a pitch step and fast flap content raise no interleaving alarm."""
    record = make_record(n=3000, seed=seed)
    pitch = record.blade_pitch.copy()
    pitch[1500:] += 0.02 * (seed % 2)                    # lateral cyclic stepped on
    streams = record_streams(record)
    streams[PITCH] = (streams[PITCH][0], BLADES, pitch, None)
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert len(got) == 3000


# --------------------------------------------------------------------------- azimuth

def with_azimuth(record, psi=None, speed=None):
    streams = record_streams(record)
    stamps, names, position, velocity = streams[AZIMUTH]
    streams[AZIMUTH] = (stamps, names, position if psi is None else psi[:, None],
                        velocity if speed is None else speed[:, None])
    return streams


def test_azimuth_sample_reading_zero_is_repaired(tmp_path):
    """A single azimuth sample reading 0.0 is dropped; t stays the measured azimuth."""
    record = make_record(n=1500)
    psi = np.mod(record.t, 2 * np.pi)
    psi[777] = 0.0
    got = read_quietly(write_streams(tmp_path / 'bag', with_azimuth(record, psi)))
    assert np.all(np.diff(got.t) > 0)
    np.testing.assert_allclose(got.t, record.t, atol=2e-5)
    assert any('dropped 1 azimuth sample(s)' in w and '0 rad at 0.7770 s' in w
               for w in got.warnings)
    assert not any('gap' in w for w in got.warnings)         # the sample was there, but wrong


def test_rotor_speed_sample_reading_zero_is_repaired(tmp_path):
    record = make_record(n=1500)
    speed = record.rotor_speed_rad_s.copy()
    speed[[300, 901, 902]] = 0.0
    got = read_quietly(write_streams(tmp_path / 'bag', with_azimuth(record, speed=speed)))
    np.testing.assert_allclose(got.rotor_speed_rad_s, record.rotor_speed_rad_s, rtol=1e-4)
    np.testing.assert_allclose(got.t, record.t, atol=1e-9)
    assert any('3 rotor-speed (velocity) sample(s)' in w for w in got.warnings)


def test_azimuth_slip_is_an_error_in_the_window_and_a_warning_outside(tmp_path):
    record = make_record(n=2000)
    psi = np.mod(record.t, 2 * np.pi)
    psi[1200:] = np.mod(psi[1200:] - 0.5, 2 * np.pi)      # encoder index error: lasting step
    bag = write_streams(tmp_path / 'bag', with_azimuth(record, psi))
    with pytest.raises(BagError, match=r'azimuth steps -0.5 rad .* at 1.2000 s and stays there.*'
                                       r'choose window_s clear of 1.2000 s'):
        read_record(bag, window_s=(0.9, 1.5))
    with pytest.raises(BagError, match='read without a window'):
        read_record(bag)
    got = read_quietly(bag, window_s=(0.1, 0.8))
    assert any('outside window_s' in w and 'steps -0.5 rad' in w for w in got.warnings)
    np.testing.assert_allclose(got.window(0.1, 0.8).t, record.window(0.1, 0.8).t, atol=1e-9)


def test_azimuth_that_goes_back_names_topic_time_and_cause(tmp_path):
    """A backward stretch that is no glitch: one line with topic and time, not an internal one."""
    record = make_record(n=1500)
    psi = np.mod(record.t, 2 * np.pi)
    psi[600:640] = psi[600]                                 # encoder stuck for 40 ms
    psi[640:] = np.mod(psi[640:] - 4.0, 2 * np.pi)           # ... then re-indexed backwards
    with pytest.raises(BagError) as err:
        read_record(write_streams(tmp_path / 'bag', with_azimuth(record, psi)))
    text = str(err.value)
    assert text.startswith(AZIMUTH) and 'strictly increasing' not in text
    assert '0.6' in text


def test_missing_velocity_is_named_as_such(tmp_path):
    """Messages with position but no velocity are not 'NaN/inf' samples and are not dropped."""
    record = make_record(n=500)
    streams = record_streams(record)
    stamps, names, position, velocity = streams[AZIMUTH]
    full = encode_batch(stamps, names, position, velocity, frame_id='rotor')
    bare = encode_batch(stamps, names, position, None, frame_id='rotor')
    streams[AZIMUTH] = [(int(s), bare[i] if i % 50 == 7 else full[i])
                        for i, s in enumerate(stamps)]
    got = read_quietly(write_streams(tmp_path / 'bag', streams))
    assert len(got) == 500
    assert f'{AZIMUTH}: 10 message(s) carry no velocity (rotor speed); it is interpolated ' \
        'there from the neighbouring samples' in got.warnings
    assert not any('NaN' in w for w in got.warnings)
    np.testing.assert_allclose(got.rotor_speed_rad_s, record.rotor_speed_rad_s, rtol=1e-6)


def test_warnings_are_listed_once(tmp_path):
    record = make_record(n=400)
    streams = record_streams(record)
    flap = record.blade_flap.copy()
    flap[[10, 20], 0] = np.nan
    streams[FLAP] = (streams[FLAP][0], BLADES, flap, None)
    with pytest.warns(BagWarning) as caught:
        got = read_record(write_streams(tmp_path / 'bag', streams))
    assert len(caught) == 1
    assert len(got.warnings) == len(set(got.warnings))
