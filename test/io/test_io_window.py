"""Memory follows the window: a window of a long MCAP is read from its chunk index alone."""

import tracemalloc
import warnings

from io_helpers import make_record, STAMP0
import numpy as np
import pytest
from rotor_id.io import bag as bag_module
from rotor_id.io.bag import BagWarning, read_record, write_record_bag

WINDOW = (10.0, 11.0)


@pytest.fixture(scope='module', params=['mcap', 'sqlite3'])
def bags(request, tmp_path_factory):
    """Write a 20 s and a 60 s bag at 1 kHz (the same first 20 s)."""
    root = tmp_path_factory.mktemp('window')
    long = make_record(n=60_000, seed=4)
    short = long.window(0.0, 19.9995)
    storage = request.param
    return (write_record_bag(root / 'short', short, storage=storage),
            write_record_bag(root / 'long', long, storage=storage), long)


def read_quietly(path, **kwargs):
    """Read with the summary BagWarning caught."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', BagWarning)
        return read_record(path, **kwargs)


def read_traced(path, **kwargs):
    """Read quietly; return (record, peak traced memory in bytes)."""
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', BagWarning)
            record = read_record(path, **kwargs)
        return record, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_window_read_equals_the_full_read(bags, monkeypatch):
    _, long_bag, truth = bags
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
    got, _ = read_traced(long_bag, window_s=WINDOW)
    assert 'around window_s only' in got.source
    assert got.stamp0_ns == STAMP0                 # the recording's origin, not the part's
    margin = bag_module.WINDOW_READ_MARGIN_S + bag_module.WINDOW_READ_CLOCK_TOLERANCE_S
    assert got.time_s[0] == pytest.approx(WINDOW[0] - margin, abs=2e-3)
    assert got.time_s[-1] == pytest.approx(WINDOW[1] + margin, abs=2e-3)
    want = truth.window(got.time_s[0], got.time_s[-1])
    np.testing.assert_allclose(got.time_s, want.time_s, atol=1e-12)
    np.testing.assert_array_equal(got.blade_flap, want.blade_flap)
    np.testing.assert_allclose(got.blade_pitch, want.blade_pitch, atol=1e-15)
    # t is the unwrapped azimuth: the same up to whole revolutions
    turns = (got.t - want.t) / (2 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns[0]), atol=1e-9)


def test_memory_and_reading_follow_the_window_not_the_bag(bags, monkeypatch):
    """
    A 3x longer bag costs the same to read a window of; a whole read grows with the bag.

    The whole read is of the 20 s bag, 2.9 times the 7 s the window read returns: its peak
    must be at least twice the window read's of the 60 s bag (tracing the 60 s bag's whole
    read, the same claim, costs three times as much).
    """
    short_bag, long_bag, _ = bags
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
    short, short_peak = read_traced(short_bag, window_s=WINDOW)
    long, long_peak = read_traced(long_bag, window_s=WINDOW)
    assert len(short) == len(long) == 7001
    assert long_peak < 1.3 * short_peak
    whole, whole_peak = read_traced(short_bag)
    assert len(whole) == 20_000
    assert whole_peak > 2 * long_peak, (whole_peak, long_peak)


def test_small_bags_and_clock_trouble_are_read_whole(bags, tmp_path, monkeypatch):
    """Below the size limit, or when the stamps drift from the receive times, read it all."""
    _, long_bag, truth = bags
    got = read_quietly(long_bag, window_s=WINDOW)            # 60 s bag: under the limit
    assert 'around window_s' not in got.source and len(got) == 60_000
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
    drifting = truth.window(0.0, 59.0)
    drifting.time_s = drifting.time_s * (1 + 1e-4)           # the rig's clock runs 100 ppm fast
    skewed = write_record_bag(tmp_path / 'skewed', drifting,
                              storage='sqlite3' if '.db3' in got.source else 'mcap')
    got = read_quietly(skewed, window_s=WINDOW)
    assert 'around window_s' in got.source                     # 6 ms over a minute: fine


@pytest.mark.parametrize('compression', ['ZSTD', 'LZ4'])
def test_compressed_chunks_are_read_one_by_one(tmp_path, monkeypatch, compression):
    """MCAP chunks compressed as ros2 bag record -s mcap writes them (zstd, lz4)."""
    from mcap.writer import CompressionType, Writer
    from io_helpers import record_streams
    from rotor_id.io.jointstate_cdr import encode_batch, JOINT_STATE
    truth = make_record(n=30_000, seed=8)
    path = tmp_path / 'bag.mcap'
    with open(path, 'wb') as stream:
        writer = Writer(stream, chunk_size=256 * 1024,
                        compression=getattr(CompressionType, compression))
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema(JOINT_STATE, 'ros2msg', b'')
        streams = record_streams(truth)
        channels = {topic: writer.register_channel(topic, 'cdr', schema) for topic in streams}
        encoded = {topic: list(zip(stamps.tolist(), encode_batch(stamps, names, p, v)))
                   for topic, (stamps, names, p, v) in streams.items()}
        for i in range(len(truth)):
            for topic, messages in encoded.items():
                stamp, data = messages[i]
                writer.add_message(channels[topic], log_time=stamp, data=data,
                                   publish_time=stamp)
        writer.finish()
    monkeypatch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
    got, _ = read_traced(path, window_s=WINDOW)
    assert 'around window_s only' in got.source
    want = truth.window(got.time_s[0], got.time_s[-1])
    assert len(got) == 7001
    np.testing.assert_array_equal(got.blade_flap, want.blade_flap)
