"""
Recover the readable messages of a damaged MCAP file.

A recording cut short (power loss, full disk, copy interrupted) has no summary section and no
footer, so an indexed reader refuses it. The records before the damage are intact: this module
walks the data section record by record (MCAP spec: opcode u8, length u64, body) and returns
every message it can read, including those at the start of a truncated chunk.
"""

from binascii import crc32
from dataclasses import dataclass, field
import struct
import sys

if sys.version_info >= (3, 14):  # pragma: no cover
    from compression import zstd
else:
    from backports import zstd
import lz4.frame
import numpy as np

MAGIC = b'\x89MCAP0\r\n'
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_MESSAGE_INDEX = 0x07
_OP_CHUNK_INDEX = 0x08
_OP_DATA_END = 0x0F


@dataclass
class McapScan:
    """
    What a linear scan of an MCAP file found.

    Attributes
    ----------
    schemas
        Schema id -> schema name (the message type).
    channels
        Channel id -> (topic, schema id).
    messages
        Channel id -> list of (log_time_ns, CDR bytes).
    complete
        True if the scan reached the end of the data section cleanly.
    problem
        Why the scan stopped early, if it did.
    skipped_chunks
        Number of chunks whose checksum failed (their messages are not used).

    """

    schemas: dict = field(default_factory=dict)
    channels: dict = field(default_factory=dict)
    messages: dict = field(default_factory=dict)
    complete: bool = False
    problem: str = ''
    skipped_chunks: int = 0

    def topics(self):
        """Return topic -> message type for every channel found."""
        return {topic: self.schemas.get(schema, '') for topic, schema in self.channels.values()}

    def topic_messages(self, topic):
        """Return the list of (log_time_ns, bytes) of ``topic`` in file order."""
        out = []
        for cid, (name, _) in self.channels.items():
            if name == topic:
                out.extend(self.messages.get(cid, []))
        return out


def _string(body, pos):
    (length,) = struct.unpack_from('<I', body, pos)
    pos += 4
    if pos + length > len(body):
        raise ValueError('string runs past its record')
    return bytes(body[pos:pos + length]).decode('utf-8'), pos + length


def _decompress_partial(data, compression):
    """Decompress as much of a (possibly truncated) compressed chunk as possible."""
    if compression == '':
        return data
    if compression == 'zstd':
        return zstd.ZstdDecompressor().decompress(data)
    if compression == 'lz4':
        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    raise ValueError(f'unsupported chunk compression {compression!r}')


class _Scanner:

    def __init__(self):
        self.scan = McapScan()
        self.saw_end = False

    def records(self, buf, pos, end):
        """Handle the records in buf[pos:end]; return (position reached, problem or '')."""
        while pos < end:
            if pos + 9 > end:
                return pos, f'record header cut off at byte {pos}'
            op = buf[pos]
            (length,) = struct.unpack_from('<Q', buf, pos + 1)
            body_start = pos + 9
            if op in (_OP_FOOTER, _OP_DATA_END):
                self.saw_end = True
                return end, ''
            if body_start + length > end:
                if op == _OP_CHUNK:
                    self.chunk(buf[body_start:end], truncated=True)
                return pos, f'record (opcode {op:#04x}) at byte {pos} is cut off'
            body = buf[body_start:body_start + length]
            if op == _OP_SCHEMA:
                (sid,) = struct.unpack_from('<H', body, 0)
                name, _ = _string(body, 2)
                self.scan.schemas[sid] = name
            elif op == _OP_CHANNEL:
                cid, sid = struct.unpack_from('<HH', body, 0)
                topic, _ = _string(body, 4)
                self.scan.channels[cid] = (topic, sid)
            elif op == _OP_MESSAGE:
                if length < 22:
                    return pos, f'message record at byte {pos} is too short'
                cid, _, log_time, _ = struct.unpack_from('<HIQQ', body, 0)
                self.scan.messages.setdefault(cid, []).append((log_time, bytes(body[22:])))
            elif op == _OP_CHUNK:
                self.chunk(body, truncated=False)
            pos = body_start + length
        return pos, ''

    def chunk(self, body, truncated):
        _, _, size, crc = struct.unpack_from('<QQQI', body, 0)
        compression, pos = _string(body, 28)
        (compressed_size,) = struct.unpack_from('<Q', body, pos)
        data = body[pos + 8:pos + 8 + compressed_size]
        raw = _decompress_partial(bytes(data), compression)
        if not truncated and crc and crc32(raw) != crc:
            self.scan.skipped_chunks += 1
            return
        self.records(memoryview(raw), 0, min(len(raw), size))


def scan_mcap(path):
    """
    Scan an MCAP file linearly and return every message that can be read.

    Never raises for damaged content: the scan stops at the first record it cannot read and
    says why in ``problem``.

    Parameters
    ----------
    path
        The .mcap file.

    Returns
    -------
    McapScan.

    Raises
    ------
    OSError
        The file cannot be read.
    ValueError
        The file is not an MCAP file (bad magic).

    """
    with open(path, 'rb') as handle:
        buf = handle.read()
    if buf[:len(MAGIC)] != MAGIC:
        raise ValueError('not an MCAP file (magic bytes missing)')
    scanner = _Scanner()
    try:
        _, problem = scanner.records(memoryview(buf), len(MAGIC), len(buf))
    except Exception as err:  # noqa: B902 - damaged bytes raise all kinds; keep what was read
        problem = f'unreadable record ({type(err).__name__}: {err})'
    if not problem and not scanner.saw_end:
        problem = 'the file ends without a footer (recording cut short)'
    scanner.scan.problem = problem
    scanner.scan.complete = not problem
    return scanner.scan


class PackedMessages:
    """
    Message bodies of one topic held in one byte buffer (a list-like of ``bytes``).

    ``buffer[starts[i]:starts[i] + lengths[i]]`` is message i. Readers that decode many
    messages at once (:func:`rotor_id.io.jointstate_cdr.decode_batch`) gather rows straight
    from the buffer instead of building a Python object per message.
    """

    def __init__(self, buffer, starts, lengths):
        self.buffer = buffer
        self.starts = np.asarray(starts, dtype=np.int64)
        self.lengths = np.asarray(lengths, dtype=np.int64)

    def __len__(self):
        return int(self.starts.size)

    def __getitem__(self, i):
        start = int(self.starts[i])
        return self.buffer[start:start + int(self.lengths[i])].tobytes()

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def rows(self, index, width):
        """Return the messages ``index`` (all ``width`` bytes long) as an (n, width) array."""
        # A sliding-window view gathers whole rows (one copy per row), not single bytes.
        windows = np.lib.stride_tricks.sliding_window_view(self.buffer, width)
        return windows[self.starts[index]]


def _take_definition(op, body, schemas, channels):
    """Keep a Schema (id -> name) or Channel (id -> (topic, schema id)) record; say if it was."""
    if op == _OP_SCHEMA:
        (sid,) = struct.unpack_from('<H', body, 0)
        schemas[sid] = _string(body, 2)[0]
    elif op == _OP_CHANNEL:
        cid, sid = struct.unpack_from('<HH', body, 0)
        channels[cid] = (_string(body, 4)[0], sid)
    else:
        return False
    return True


def read_indexed_mcap(path, topics):
    """
    Read the messages of ``topics`` from a healthy, chunked and indexed MCAP, vectorised.

    Walks the file's top-level records (a few per chunk), decompresses every chunk once and
    takes each channel's message offsets from the MessageIndex records that follow the chunk
    (MCAP spec), so no Python step runs per message. Returns None when the file is not of
    that shape (messages outside chunks, no message index, no footer, a bad checksum): the
    caller then uses a general reader.

    Returns
    -------
    (topic -> message type, topic -> (log_time_ns (n,), PackedMessages)) or None.

    """
    with open(path, 'rb') as handle:
        buf = handle.read()
    if buf[:len(MAGIC)] != MAGIC:
        return None
    schemas, channels = {}, {}
    chunks, pieces = [], {}            # pieces: cid -> list of (chunk no, offsets, log times)
    pos, end = len(MAGIC), len(buf)
    current = None
    current_summary = False
    in_place, file_at = True, []       # uncompressed chunks are read where they lie
    while pos + 9 <= end:
        op = buf[pos]
        (length,) = struct.unpack_from('<Q', buf, pos + 1)
        body_start = pos + 9
        if body_start + length > end:
            return None
        if op == _OP_FOOTER:
            break
        body = memoryview(buf)[body_start:body_start + length]
        # Schemas and channels live inside the chunks; the summary section after DataEnd
        # repeats them, which is where this reader takes them from.
        if _take_definition(op, body, schemas, channels):
            pass
        elif op == _OP_MESSAGE:
            return None
        elif op == _OP_CHUNK and current_summary:
            return None
        elif op == _OP_DATA_END:
            current_summary = True
        elif op == _OP_CHUNK:
            _, _, size, crc = struct.unpack_from('<QQQI', body, 0)
            compression, at = _string(body, 28)
            (compressed_size,) = struct.unpack_from('<Q', body, at)
            records = body[at + 8:at + 8 + compressed_size]
            if compression:
                raw = np.frombuffer(_decompress_partial(bytes(records), compression), np.uint8)
                in_place = False
            else:                      # a view of the file's bytes: no copy
                raw = np.frombuffer(records, dtype=np.uint8)
            file_at.append(body_start + at + 8)
            if raw.size != size or (crc and crc32(raw) != crc):
                return None
            current = len(chunks)
            chunks.append(raw)
        elif op == _OP_MESSAGE_INDEX and current is not None:
            cid, nbytes = struct.unpack_from('<HI', body, 0)
            pairs = np.frombuffer(body, dtype='<u8', count=nbytes // 8, offset=6).reshape(-1, 2)
            pieces.setdefault(cid, []).append((current, pairs[:, 1].astype(np.int64),
                                               pairs[:, 0].astype(np.int64)))
        pos = body_start + length
    else:
        return None
    if not chunks or not pieces:
        return None
    del body
    sizes = np.array([c.size for c in chunks], dtype=np.int64)
    if in_place:                      # chunk c starts at byte file_at[c] of the file
        buffer = np.frombuffer(buf, dtype=np.uint8)
        starts_of = np.array(file_at, dtype=np.int64)
    else:
        buffer = np.concatenate(chunks)
        starts_of = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    chunks.clear()
    del buf                           # (still referenced by buffer when read in place)
    return _gather(buffer, starts_of, sizes, schemas, channels, pieces, topics)


def _gather(buffer, starts_of, sizes, schemas, channels, pieces, topics):
    """Return (topic -> type, topic -> (log times, PackedMessages)) from indexed chunks."""
    available, messages = {}, {}
    for cid, (topic, sid) in channels.items():
        available[topic] = schemas.get(sid, '')
        if topic not in topics or cid not in pieces:
            continue
        # The index is not checksummed: every offset and length must stay inside its chunk.
        for c, off, _ in pieces[cid]:
            if off.size and (off.min() < 0 or off.max() + 9 + 22 > sizes[c]):
                return None
        offsets = np.concatenate([starts_of[c] + off for c, off, _ in pieces[cid]])
        limits = np.concatenate([np.full(off.size, starts_of[c] + sizes[c])
                                 for c, off, _ in pieces[cid]])
        log_ns = np.concatenate([lt for _, _, lt in pieces[cid]])
        if not offsets.size:
            continue
        if np.any(buffer[offsets] != _OP_MESSAGE):
            return None
        record_len = np.lib.stride_tricks.sliding_window_view(buffer, 8)[offsets + 1]
        record_len = np.ascontiguousarray(record_len).view('<u8')[:, 0]
        if np.any(record_len < 22) or np.any(offsets + 9 + record_len > limits):
            return None
        starts = offsets + 9 + 22
        messages.setdefault(topic, []).append((log_ns, starts, record_len.astype(np.int64) - 22))
    out = {}
    for topic, parts in messages.items():
        log_ns = np.concatenate([p[0] for p in parts])
        starts = np.concatenate([p[1] for p in parts])
        lengths = np.concatenate([p[2] for p in parts])
        order = np.argsort(starts, kind='stable')          # file order
        out[topic] = (log_ns[order], PackedMessages(buffer, starts[order], lengths[order]))
    return available, out


@dataclass
class McapChunk:
    """
    One chunk as the summary's ChunkIndex describes it (MCAP spec).

    Attributes
    ----------
    start_ns, end_ns
        Earliest and latest log time of its messages.
    offset
        Byte offset of the Chunk record in the file.
    length
        Length of the Chunk record, bytes.
    index_length
        Length of the MessageIndex records that follow it, bytes.
    channels
        Channel ids with messages in it.

    """

    start_ns: int
    end_ns: int
    offset: int
    length: int
    index_length: int
    channels: frozenset


@dataclass
class McapSummary:
    """Schemas, channels and chunk index of an MCAP file, read from its summary section."""

    schemas: dict
    channels: dict
    chunks: list

    def topic_chunks(self, topics):
        """Return the chunks holding a message of any of ``topics``, in file order."""
        ids = {cid for cid, (topic, _) in self.channels.items() if topic in topics}
        return [c for c in self.chunks if c.channels & ids]


def read_mcap_summary(path):
    """
    Read the summary section of an MCAP file (schemas, channels, chunk index).

    Reads the footer and the summary only, not the data: a few kB for an hour of recording.

    Returns
    -------
    McapSummary, or None when the file has no footer, no summary or no chunk index.

    """
    with open(path, 'rb') as handle:
        handle.seek(0, 2)
        size = handle.tell()
        tail = len(MAGIC) + 9 + 20
        if size < len(MAGIC) + tail:
            return None
        handle.seek(size - tail)
        footer = handle.read(tail)
        if footer[-len(MAGIC):] != MAGIC or footer[0] != _OP_FOOTER:
            return None
        summary_start, _, _ = struct.unpack_from('<QQI', footer, 9)
        if not 0 < summary_start < size - tail:
            return None
        handle.seek(summary_start)
        data = memoryview(handle.read(size - tail - summary_start))
    schemas, channels, chunks = {}, {}, []
    pos = 0
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        body = data[pos + 9:pos + 9 + length]
        if len(body) != length:
            return None
        if _take_definition(op, body, schemas, channels):
            pass
        elif op == _OP_CHUNK_INDEX:
            start, end, offset, length_ = struct.unpack_from('<QQQQ', body, 0)
            (map_bytes,) = struct.unpack_from('<I', body, 32)
            entries = np.frombuffer(bytes(body[36:36 + map_bytes]),
                                    dtype=np.dtype([('cid', '<u2'), ('at', '<u8')]))
            (index_length,) = struct.unpack_from('<Q', body, 36 + map_bytes)
            chunks.append(McapChunk(start, end, offset, length_, index_length,
                                    frozenset(int(c) for c in entries['cid'])))
        pos += 9 + length
    if not chunks:
        return None
    chunks.sort(key=lambda c: c.offset)
    return McapSummary(schemas, channels, chunks)


def read_mcap_chunks(path, topics, summary, chunks, log_range=None):
    """
    Read the messages of ``topics`` from some chunks of an indexed MCAP only.

    Each chunk is read from the file with its MessageIndex records and decompressed on its
    own, so memory follows the chunks asked for, not the file.

    Parameters
    ----------
    path
        The .mcap file.
    topics
        Topic names wanted.
    summary
        McapSummary of the file.
    chunks
        McapChunk list (e.g. those overlapping a time window).
    log_range
        (first, last) log time in ns: messages outside are left out; None keeps all.

    Returns
    -------
    Like :func:`read_indexed_mcap`, or None when a chunk is not as the index says.

    """
    kept, pieces = [], {}
    with open(path, 'rb') as handle:
        for chunk in chunks:
            handle.seek(chunk.offset)
            data = handle.read(chunk.length + chunk.index_length)
            if len(data) != chunk.length + chunk.index_length or data[0] != _OP_CHUNK:
                return None
            body = memoryview(data)[9:chunk.length]
            _, _, size, crc = struct.unpack_from('<QQQI', body, 0)
            compression, at = _string(body, 28)
            (compressed_size,) = struct.unpack_from('<Q', body, at)
            records = bytes(body[at + 8:at + 8 + compressed_size])
            raw = np.frombuffer(_decompress_partial(records, compression) if compression
                                else records, dtype=np.uint8)
            if raw.size != size or (crc and crc32(raw) != crc):
                return None
            number = len(kept)
            wanted_here = False
            pos = chunk.length
            while pos + 9 <= len(data):
                op = data[pos]
                (length,) = struct.unpack_from('<Q', data, pos + 1)
                if op == _OP_MESSAGE_INDEX:
                    cid, nbytes = struct.unpack_from('<HI', data, pos + 9)
                    if summary.channels.get(cid, ('',))[0] in topics:
                        pairs = np.frombuffer(data, dtype='<u8', count=nbytes // 8,
                                              offset=pos + 15).reshape(-1, 2)
                        log_ns = pairs[:, 0].astype(np.int64)
                        offsets = pairs[:, 1].astype(np.int64)
                        if log_range is not None:
                            inside = (log_ns >= log_range[0]) & (log_ns <= log_range[1])
                            log_ns, offsets = log_ns[inside], offsets[inside]
                        if offsets.size:
                            pieces.setdefault(cid, []).append((number, offsets, log_ns))
                            wanted_here = True
                pos += 9 + length
            if wanted_here:
                kept.append(raw)
    if not kept:
        return ({topic: summary.schemas.get(sid, '') for topic, sid in summary.channels.values()},
                {})
    sizes = np.array([c.size for c in kept], dtype=np.int64)
    buffer = np.concatenate(kept)
    starts_of = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    kept.clear()
    return _gather(buffer, starts_of, sizes, summary.schemas, summary.channels, pieces, topics)
