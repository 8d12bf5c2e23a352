"""The vectorized JointState codec agrees byte for byte with rosbags' typestore."""

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores
from rotor_id.io.jointstate_cdr import decode_batch, decode_one, encode_batch, JOINT_STATE

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
JointState = TYPESTORE.types[JOINT_STATE]
Header = TYPESTORE.types['std_msgs/msg/Header']
Time = TYPESTORE.types['builtin_interfaces/msg/Time']

names_strategy = st.lists(st.text('abc_12', min_size=0, max_size=9), min_size=0, max_size=5,
                          unique=True)


def message(stamp_ns, names, position, velocity=(), frame_id='rotor'):
    """Build a typestore JointState."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return JointState(header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=frame_id),
                      name=list(names), position=np.asarray(position, dtype=float),
                      velocity=np.asarray(velocity, dtype=float), effort=np.empty(0))


def serialize(msg):
    return bytes(TYPESTORE.serialize_cdr(msg, JOINT_STATE))


@settings(max_examples=60)
@given(names=names_strategy, frame_id=st.text('xyz/', max_size=7), with_velocity=st.booleans(),
       seed=st.integers(0, 2**16), stamp=st.integers(0, (2**31 - 1) * 10**9))
def test_encode_and_decode_match_typestore(names, frame_id, with_velocity, seed, stamp):
    rng = np.random.default_rng(seed)
    k, n = len(names), 3
    stamps = stamp + np.arange(n) * 1000
    position = rng.normal(size=(n, k))
    velocity = rng.normal(size=(n, k)) if with_velocity else None
    encoded = encode_batch(stamps, names, position, velocity, frame_id=frame_id)
    for i in range(n):
        reference = message(stamps[i], names, position[i],
                            velocity[i] if with_velocity else (), frame_id)
        assert encoded[i] == serialize(reference)
        decoded = TYPESTORE.deserialize_cdr(encoded[i], JOINT_STATE)
        assert decoded.name == list(names)
    batch = decode_batch(encoded)
    np.testing.assert_array_equal(batch.stamps_ns, stamps)
    np.testing.assert_array_equal(batch.position, position)
    assert batch.names == tuple(names)
    if with_velocity and k:
        np.testing.assert_array_equal(batch.velocity, velocity)
    else:
        assert np.isnan(batch.velocity).all()


def test_decode_batch_handles_mixed_layouts_and_drops_strangers():
    names = ['blade_1', 'blade_2']
    good = [serialize(message(10 + i, names, [i, -i])) for i in range(3)]
    swapped = serialize(message(20, names[::-1], [7.0, 8.0]))        # same joints, other order
    other_frame = serialize(message(30, names, [1.5, 2.5], frame_id='a_longer_frame'))
    stranger = serialize(message(40, ['hub', 'blade_2'], [0.0, 0.0]))  # other joints
    short = serialize(message(50, names, [1.0]))                        # position too short
    garbage = b'\x00\x01\x00\x00' + b'\xff' * 40
    batch = decode_batch(good + [swapped, other_frame, stranger, short, garbage])
    np.testing.assert_array_equal(batch.stamps_ns, [10, 11, 12, 20, 30])
    np.testing.assert_array_equal(batch.position[3], [8.0, 7.0])
    np.testing.assert_array_equal(batch.position[4], [1.5, 2.5])
    np.testing.assert_array_equal(batch.kept, [0, 1, 2, 3, 4])
    assert sum(batch.dropped.values()) == 3
    assert any('differ' in reason for reason in batch.dropped)
    assert any('undecodable' in reason for reason in batch.dropped)


def test_big_endian_message_decodes():
    little = serialize(message(1_500_000_000, ['rotor'], [1.25], [94.0]))
    # rebuild the same message big-endian by hand: header 00 00, numbers swapped
    big = bytearray(little)
    big[1] = 0
    for offset, size in ((4, 4), (8, 4), (12, 4), (24, 4), (28, 4), (40, 4), (44, 8),
                         (52, 4), (60, 8), (68, 4)):
        big[offset:offset + size] = big[offset:offset + size][::-1]
    stamp, names, position, velocity = decode_one(bytes(big))
    assert (stamp, names) == (1_500_000_000, ('rotor',))
    assert position.tolist() == [1.25] and velocity.tolist() == [94.0]


@pytest.mark.parametrize('raw', [b'', b'\x00\x01\x00\x00', b'\x01\x01\x00\x00' + b'\x00' * 30,
                                 b'\x00\x01\x00\x00' + b'\x00' * 8 + b'\xff\xff\xff\x7f'])
def test_malformed_bytes_raise_value_error(raw):
    with pytest.raises(ValueError):
        decode_one(raw)


@pytest.mark.ros
@pytest.mark.parametrize('fields', [('position',), ('position', 'velocity'),
                                    ('position', 'effort'), ('position', 'velocity', 'effort')])
@pytest.mark.parametrize('frame_id', ['', 'hub', 'a_longer_frame'])
def test_messages_serialized_by_rclpy_decode(fields, frame_id):
    """
    Read what rclpy's own serializer writes (a bag made by a Python script).

    serialize_message leaves up to 4 bytes per empty float64[] after the last field (12 with
    all three empty); a position-only flap message used to be refused for its 8.
    """
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    names = ['blade_1', 'blade_2', 'blade_3']
    raws = []
    for k in range(3):
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = 7, 1000 * k
        msg.header.frame_id = frame_id
        msg.name = names
        for field in fields:
            setattr(msg, field, [0.25 * k + j for j in range(3)])
        raws.append(serialize_message(msg))
    batch = decode_batch(raws)
    assert not batch.dropped
    np.testing.assert_array_equal(batch.stamps_ns, [7_000_000_000 + 1000 * k for k in range(3)])
    np.testing.assert_array_equal(batch.position[2], [0.5, 1.5, 2.5])
    stamp, got_names, position, velocity = decode_one(raws[1])
    assert got_names == tuple(names) and position.tolist() == [0.25, 1.25, 2.25]
    assert velocity.size == (3 if 'velocity' in fields else 0)
