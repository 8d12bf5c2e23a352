"""
Fast CDR codec for ``sensor_msgs/msg/JointState``, vectorized over many messages.

A rosbag2 recording at 1 kHz holds hundreds of thousands of JointState messages per topic, and
deserializing them one by one costs a few microseconds each in Python. The messages of one topic
nearly always share one byte layout (same frame_id, same joint names, same array lengths): only
the stamp and the float64 values differ. :func:`decode_batch` parses the layout of one message,
checks with numpy that every other message of that length has the same fixed bytes, and reads the
stamps and values of all of them as array views. Messages that do not fit the layout are decoded
one at a time (:func:`decode_one`).

CDR layout of JointState (after the 4-byte encapsulation header; alignment is relative to the end
of that header, float64 arrays are 8-aligned only when they are not empty)::

    int32 sec, uint32 nanosec, string frame_id, string[] name,
    float64[] position, float64[] velocity, float64[] effort
"""

from dataclasses import dataclass
import struct
from typing import Sequence

import numpy as np
import numpy.typing as npt

JOINT_STATE = 'sensor_msgs/msg/JointState'
FIELDS = ('position', 'velocity', 'effort')
_HEADER = 4  # CDR encapsulation header
_ENCAPSULATION = {0: False, 1: True}  # CDR_BE, CDR_LE -> little endian?
_MAX_TRAILING = 7  # serializers may pad the end of the message
# rclpy's serialize_message (Fast CDR's size bound) also leaves the 4 bytes that would align an
# empty float64[] to 8 at the end: a position-only message written to a bag by a Python script
# ends 8 bytes after its effort[] count
_EMPTY_SEQUENCE_SLACK = 4


@dataclass(frozen=True)
class JointStateLayout:
    """
    Byte layout of one serialized JointState message.

    Attributes
    ----------
    size
        Message length in bytes, encapsulation header included.
    little
        True for little-endian CDR.
    frame_id
        ``header.frame_id``.
    names
        Joint names, in message order.
    offsets
        Byte offset and element count of each float64 array, keyed by field name.

    """

    size: int
    little: bool
    frame_id: str
    names: tuple
    offsets: dict

    def count(self, field: str) -> int:
        """Return the number of elements of ``field`` ('position', 'velocity', 'effort')."""
        return self.offsets[field][1]

    def value_mask(self) -> np.ndarray:
        """Return a bool mask (size,) that is True at the bytes of the stamp and the values."""
        mask = np.zeros(self.size, dtype=bool)
        mask[_HEADER:_HEADER + 8] = True
        for offset, count in self.offsets.values():
            mask[offset:offset + 8 * count] = True
        return mask


@dataclass
class JointStateBatch:
    """
    Decoded messages of one topic, in the order they were given.

    Attributes
    ----------
    stamps_ns
        (n,) int64 ``header.stamp`` in nanoseconds.
    names
        Joint names shared by all messages (message order).
    position
        (n, k) float64.
    velocity
        (n, k) float64, NaN where a message had no velocity.
    velocity_sent
        (n,) bool, True where the message carried a velocity array.
    frame_ids
        ``header.frame_id`` -> number of decoded messages carrying it (a second publisher
        often names another frame).
    dropped
        Reason -> number of messages that could not be decoded or did not match
        ``names``.
    kept
        (n,) int64 indices of the decoded messages in the input list.

    """

    stamps_ns: np.ndarray
    names: tuple
    position: np.ndarray
    velocity: np.ndarray
    dropped: dict
    kept: np.ndarray
    velocity_sent: np.ndarray | None = None
    frame_ids: dict | None = None


def _align(pos, alignment):
    return pos + (-(pos - _HEADER)) % alignment


def parse_layout(raw: bytes | bytearray | memoryview) -> JointStateLayout:
    """
    Parse the layout of one serialized JointState.

    Parameters
    ----------
    raw
        The CDR bytes of the message, encapsulation header included.

    Returns
    -------
    JointStateLayout.

    Raises
    ------
    ValueError
        The bytes are not a well-formed JointState.

    """
    raw = bytes(raw)
    size = len(raw)
    if size < _HEADER + 8 + 4 or raw[0] != 0 or raw[1] not in _ENCAPSULATION:
        raise ValueError('not a CDR JointState: bad length or encapsulation header')
    little = _ENCAPSULATION[raw[1]]
    u32 = struct.Struct('<I' if little else '>I').unpack_from

    def read_u32(pos):
        pos = _align(pos, 4)
        if pos + 4 > size:
            raise ValueError('JointState message is truncated')
        return u32(raw, pos)[0], pos + 4

    def read_string(pos):
        length, pos = read_u32(pos)
        if length < 1 or pos + length > size or raw[pos + length - 1] != 0:
            raise ValueError('malformed string in JointState message')
        return raw[pos:pos + length - 1].decode('utf-8'), pos + length

    frame_id, pos = read_string(_HEADER + 8)
    count, pos = read_u32(pos)
    if count > size:
        raise ValueError('malformed name[] in JointState message')
    names = []
    for _ in range(count):
        name, pos = read_string(pos)
        names.append(name)
    offsets = {}
    for field in FIELDS:
        count, pos = read_u32(pos)
        if count:
            pos = _align(pos, 8)
        if pos + 8 * count > size:
            raise ValueError(f'JointState {field}[] runs past the end of the message')
        offsets[field] = (pos, count)
        pos += 8 * count
    empty = sum(1 for _, count in offsets.values() if count == 0)
    if size - pos > _MAX_TRAILING + _EMPTY_SEQUENCE_SLACK * empty:
        raise ValueError(f'{size - pos} unexpected bytes after the JointState fields')
    return JointStateLayout(size, little, frame_id, tuple(names), offsets)


def _values(rows, layout, field):
    """Read float64 array ``field`` of every row of a (n, size) uint8 array."""
    offset, count = layout.offsets[field]
    block = np.ascontiguousarray(rows[:, offset:offset + 8 * count])
    values = block.view('<f8' if layout.little else '>f8').astype(np.float64)
    return values.reshape(len(rows), count)


def _same_fixed_bytes(rows, fixed):
    """
    Return, per row, whether its bytes where ``fixed`` is True equal those of row 0.

    Compared in the widest machine words that divide the row (XOR, then the mask), which
    is several times faster than gathering the fixed bytes one by one.
    """
    rows = np.ascontiguousarray(rows)
    width = rows.shape[1]
    word = next(w for w in (8, 4, 2, 1) if width % w == 0)
    dtype = np.dtype(f'u{word}')
    words = rows.view(dtype)
    mask = np.where(fixed, 0xFF, 0).astype(np.uint8).view(dtype)
    return ~((words ^ words[0]) & mask).any(axis=1)


def _stamps(rows, little):
    order = '<' if little else '>'
    sec = np.ascontiguousarray(rows[:, 4:8]).view(order + 'i4').astype(np.int64).ravel()
    nsec = np.ascontiguousarray(rows[:, 8:12]).view(order + 'u4').astype(np.int64).ravel()
    return sec * 1_000_000_000 + nsec


def decode_one(raw: bytes | bytearray | memoryview
               ) -> tuple[int, tuple, np.ndarray, np.ndarray]:
    """
    Decode one JointState.

    Returns
    -------
    Tuple ``(stamp_ns, names, position, velocity)``; ``velocity`` is empty if not sent.

    Raises
    ------
    ValueError
        The bytes are not a well-formed JointState.

    """
    layout = parse_layout(raw)
    rows = np.frombuffer(bytes(raw), dtype=np.uint8).reshape(1, -1)
    return (int(_stamps(rows, layout.little)[0]), layout.names,
            _values(rows, layout, 'position')[0], _values(rows, layout, 'velocity')[0])


def decode_batch(raws: Sequence[bytes | bytearray | memoryview]) -> JointStateBatch:
    """
    Decode many JointState messages of one topic.

    The joint names of the batch are those of the most common message length (its first
    message). A message with the same names in another order is reordered; one with other
    names, a position array that does not match its names, or bytes that do not parse, is
    dropped and counted in ``dropped``.

    Parameters
    ----------
    raws
        Sequence of CDR byte strings.

    Returns
    -------
    JointStateBatch (empty arrays if nothing decodes).

    """
    n = len(raws)
    lengths = np.fromiter((len(r) for r in raws), dtype=np.int64, count=n)
    stamps = np.zeros(n, dtype=np.int64)
    ok = np.zeros(n, dtype=bool)
    sent = np.zeros(n, dtype=bool)
    frame_ids: dict[str, int] = {}
    dropped: dict[str, int] = {}
    names = None
    position = velocity = None

    def drop(reason, count=1):
        dropped[reason] = dropped.get(reason, 0) + count

    def store(index, layout, rows):
        # Values of messages whose names equal (or are a permutation of) the batch names.
        nonlocal names, position, velocity
        k = layout.count('position')
        if k != len(layout.names):
            drop('position[] length differs from name[]', len(index))
            return
        nvel = layout.count('velocity')
        if nvel not in (0, k):
            drop('velocity[] length differs from name[]', len(index))
            return
        if names is None:
            names = layout.names
            position = np.full((n, k), np.nan)
            velocity = np.full((n, k), np.nan)
        if layout.names == names:
            order = slice(None)
        elif sorted(layout.names) == sorted(names) and len(set(names)) == len(names):
            order = [layout.names.index(name) for name in names]
        else:
            drop(f'joint names {list(layout.names)} differ from {list(names)}', len(index))
            return
        position[index] = _values(rows, layout, 'position')[:, order]
        if nvel:
            velocity[index] = _values(rows, layout, 'velocity')[:, order]
            sent[index] = True
        stamps[index] = _stamps(rows, layout.little)
        ok[index] = True
        frame_ids[layout.frame_id] = frame_ids.get(layout.frame_id, 0) + len(index)

    sizes, counts = np.unique(lengths, return_counts=True)
    for size in sizes[np.argsort(-counts, kind='stable')]:
        index = np.flatnonzero(lengths == size)
        rows = np.frombuffer(b''.join([bytes(raws[i]) for i in index.tolist()]), dtype=np.uint8)
        rows = rows.reshape(len(index), int(size))
        try:
            layout = parse_layout(rows[0].tobytes())
        except ValueError:
            fits = np.zeros(len(index), dtype=bool)
        else:
            fits = _same_fixed_bytes(rows, ~layout.value_mask())
            store(index[fits], layout, rows if fits.all() else rows[fits])
        # Messages that do not share the group's fixed bytes: one at a time.
        for i in index[~fits].tolist():
            try:
                layout = parse_layout(raws[i])
            except ValueError as err:
                drop(f'undecodable message ({err})')
                continue
            store(np.array([i]), layout, np.frombuffer(bytes(raws[i]), np.uint8)[None, :])

    kept = np.flatnonzero(ok)
    if names is None:
        names, position, velocity = (), np.empty((0, 0)), np.empty((0, 0))
    return JointStateBatch(stamps[kept], names, position[kept], velocity[kept], dropped, kept,
                           sent[kept], frame_ids)


def _encode_template(frame_id, names, counts, little=True):
    """Serialize one JointState with zero stamp and values; return (bytes, layout)."""
    order = '<' if little else '>'
    out = bytearray(b'\x00\x01\x00\x00' if little else b'\x00\x00\x00\x00')
    out += b'\x00' * 8

    def pad(alignment):
        out.extend(b'\x00' * ((-(len(out) - _HEADER)) % alignment))

    def put_string(text):
        data = text.encode('utf-8') + b'\x00'
        pad(4)
        out.extend(struct.pack(order + 'I', len(data)))
        out.extend(data)

    put_string(frame_id)
    pad(4)
    out.extend(struct.pack(order + 'I', len(names)))
    for name in names:
        put_string(name)
    for count in counts:
        pad(4)
        out.extend(struct.pack(order + 'I', count))
        if count:
            pad(8)
        out.extend(b'\x00' * (8 * count))
    return bytes(out)


def encode_rows(stamps_ns: npt.ArrayLike, names: Sequence[str], position: npt.ArrayLike,
                velocity: npt.ArrayLike | None = None, effort: npt.ArrayLike | None = None,
                frame_id: str = '') -> np.ndarray:
    """
    Serialize many JointState messages that share names and array lengths, as one array.

    Parameters are those of :func:`encode_batch`.

    Returns
    -------
    (n, size) uint8 array: row i is message i's little-endian CDR bytes (a writer of many
    messages, e.g. a benchmark's hour-long bag, copies rows without a Python step each).

    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps_ns)
    arrays = []
    for values in (position, velocity, effort):
        values = np.empty((n, 0)) if values is None else np.asarray(values, dtype='<f8')
        if values.shape != (n, len(names)) and values.shape != (n, 0):
            raise ValueError(f'arrays must be (n, len(names)) = ({n}, {len(names)}) or (n, 0), '
                             f'got {values.shape}')
        arrays.append(values)
    template = _encode_template(frame_id, list(names), [a.shape[1] for a in arrays])
    layout = parse_layout(template)
    rows = np.tile(np.frombuffer(template, dtype=np.uint8), (n, 1))
    sec, nsec = np.divmod(stamps_ns, 1_000_000_000)
    rows[:, 4:8] = sec.astype('<i4').view(np.uint8).reshape(n, 4)
    rows[:, 8:12] = nsec.astype('<u4').view(np.uint8).reshape(n, 4)
    for field, values in zip(FIELDS, arrays):
        offset, count = layout.offsets[field]
        rows[:, offset:offset + 8 * count] = np.ascontiguousarray(values).view(np.uint8)
    return rows


def encode_batch(stamps_ns: npt.ArrayLike, names: Sequence[str], position: npt.ArrayLike,
                 velocity: npt.ArrayLike | None = None, effort: npt.ArrayLike | None = None,
                 frame_id: str = '') -> list[bytes]:
    """
    Serialize many JointState messages that share names and array lengths.

    Parameters
    ----------
    stamps_ns
        (n,) int ``header.stamp`` in nanoseconds (>= 0).
    names
        Joint names (length k).
    position
        (n, k) float64, or (n, 0) for none.
    velocity
        (n, k) float64 or None.
    effort
        (n, k) float64 or None.
    frame_id
        ``header.frame_id``.

    Returns
    -------
    List of n little-endian CDR byte strings, identical to what
    ``typestore.serialize_cdr`` produces.

    """
    rows = encode_rows(stamps_ns, names, position, velocity, effort, frame_id)
    buf = rows.tobytes()
    size = rows.shape[1]
    return [buf[i * size:(i + 1) * size] for i in range(rows.shape[0])]
