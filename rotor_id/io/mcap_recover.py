"""
Recover the readable messages of a damaged MCAP file.

A recording cut short (power loss, full disk, copy interrupted) has no summary section and no
footer, so an indexed reader refuses it. The records before the damage are intact: this module
walks the data section record by record (MCAP spec: opcode u8, length u64, body) and returns
every message it can read, including those at the start of a truncated chunk.
"""

from binascii import crc32
from dataclasses import dataclass, field
import os
import struct
import sys

if sys.version_info >= (3, 14):  # pragma: no cover
    from compression import zstd
else:
    from backports import zstd
import lz4.frame

MAGIC = b'\x89MCAP0\r\n'
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
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

    def topics(self) -> dict[str, str]:
        """Return topic -> message type for every channel found."""
        return {topic: self.schemas.get(schema, '') for topic, schema in self.channels.values()}

    def topic_messages(self, topic: str) -> list[tuple[int, bytes]]:
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


def scan_mcap(path: str | os.PathLike) -> McapScan:
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
