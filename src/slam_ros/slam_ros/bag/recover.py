"""Rebuild a readable rosbag2 bag from a damaged mcap (docs/design/ros_and_core.md)."""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from rosbags.interfaces import Qos
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.storage_mcap import decompress, get_qos
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from slam_core.errors import BagError
from slam_ros.bag.recording import AtomicBagWriter

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = (
    0x01,
    0x02,
    0x03,
    0x04,
    0x05,
    0x06,
    0x0F,
)
STAGING_NAME = re.compile(r'^\.(?P<name>.+)\.recording-\d+$')


@dataclass
class Channel:
    """A channel record: topic, type, definition and offered QoS."""

    topic: str
    msgtype: str
    msgdef: str
    encoding: str
    offered_qos: list[Qos]


@dataclass
class RecoveryReport:
    """What bag_recover kept and dropped."""

    source: Path
    output: Path
    counts: dict[str, int] = field(default_factory=dict)
    chunks: int = 0
    dropped: list[str] = field(default_factory=list)
    complete: bool = False  # the file ended with its footer: nothing was missing

    @property
    def message_count(self) -> int:
        """Messages recovered."""
        return sum(self.counts.values())


def find_mcap(path: Path) -> Path:
    """The mcap file of ``path``: the file itself, a rosbag2 directory's or a staging dir's."""
    path = Path(path)
    if not path.exists():
        raise BagError(f'{str(path)!r} does not exist')
    if path.is_file():
        return path
    found = sorted(path.glob('*.mcap')) or sorted(path.glob('*/*.mcap'))
    if not found:
        raise BagError(f'{str(path)!r} holds no .mcap file (not a recorder staging dir or bag)')
    if len(found) > 1:
        names = ', '.join(repr(str(p)) for p in found)
        raise BagError(f'{str(path)!r} holds several .mcap files ({names}); name one')
    return found[0]


def default_output(path: Path) -> Path:
    """The output for ``path``: ``NAME`` for a staging dir, else ``STEM_recovered``."""
    path = Path(path).expanduser().absolute()
    match = STAGING_NAME.match(path.name)
    if match and path.is_dir():
        return path.parent / match['name']
    stem = path.stem if path.is_file() else path.name
    return path.parent / f'{stem}_recovered'


def recover(source: Path, output: Path) -> RecoveryReport:
    """Write the recoverable messages of ``source`` to the new bag ``output``."""
    mcap = find_mcap(source)
    report = RecoveryReport(source=Path(source), output=Path(output))
    with mcap.open('rb') as stream:
        head = stream.read(len(MAGIC))
        if head != MAGIC:
            what = 'is empty' if not head else 'does not start with the mcap magic'
            raise BagError(f'{str(mcap)!r} {what}: not an mcap file')
        writer = AtomicBagWriter(output)
        try:
            _copy(stream, mcap, writer, report)
            if not writer.message_count:
                raise BagError(f'{str(mcap)!r}: no complete message to recover; nothing written')
            writer.close()
        except BaseException:
            writer.abort()
            raise
    report.counts = dict(writer.counts)
    return report


def _copy(stream: BinaryIO, mcap: Path, writer: AtomicBagWriter, report: RecoveryReport) -> None:
    schemas: dict[int, tuple[str, str, str]] = {}
    channels: dict[int, Channel] = {}
    hashes: dict[str, str] = {}
    unknown: dict[int, int] = {}
    for offset, op, body in _records(stream, mcap, report):
        if op in (OP_FOOTER, OP_DATA_END):  # the data section is complete
            report.complete = True
            return
        try:  # parse the whole record first: a damaged chunk is dropped whole
            items = _chunk_items(body) if op == OP_CHUNK else _items([(op, body)])
        except (ValueError, KeyError, struct.error, ReaderError) as err:
            report.dropped.append(
                f'the damaged record (op 0x{op:02x}) at byte {offset} ({err}) and the rest '
                'of the file'
            )
            return
        report.chunks += op == OP_CHUNK
        for item in items:
            if item[0] == OP_SCHEMA:
                sid, schema = item[1]
                schemas[sid] = schema
            elif item[0] == OP_CHANNEL:
                cid, sid, topic, metadata = item[1]
                if sid in schemas:
                    msgtype, encoding, msgdef = schemas[sid]
                    offered = get_qos(metadata) if metadata else []
                    channels[cid] = Channel(topic, msgtype, msgdef, encoding, offered)
            else:
                cid, stamp, data = item[1]
                channel = channels.get(cid)
                if channel is None:
                    unknown[cid] = unknown.get(cid, 0) + 1
                    continue
                if not writer.has_topic(channel.topic):
                    writer.add_topic(
                        channel.topic,
                        channel.msgtype,
                        msgdef=channel.msgdef,
                        rihs01=_rihs01(channel, hashes),
                        offered_qos=channel.offered_qos,
                    )
                writer.write(channel.topic, stamp, data)
    for cid, n in sorted(unknown.items()):
        report.dropped.append(f'{n} messages on channel {cid}, which no channel record defines')


Item = tuple[int, Any]


def _items(records: list[tuple[int, bytes]]) -> list[Item]:
    """Parse schema, channel and message records; skip the others (indexes, metadata)."""
    items: list[Item] = []
    for op, record in records:
        if op == OP_SCHEMA:
            (sid,) = struct.unpack_from('<H', record)
            name, at = _string(record, 2)
            encoding, at = _string(record, at)
            data, _ = _string(record, at)
            items.append((op, (sid, (name, encoding, data))))
        elif op == OP_CHANNEL:
            cid, sid = struct.unpack_from('<HH', record)
            topic, at = _string(record, 4)
            _, at = _string(record, at)  # message encoding: cdr
            (n,) = struct.unpack_from('<I', record, at)
            if at + 4 + n > len(record):
                raise ValueError(f'channel {topic!r}: metadata runs past its record')
            items.append((op, (cid, sid, topic, record[at + 4 : at + 4 + n])))
        elif op == OP_MESSAGE:
            cid, stamp = struct.unpack_from('<HxxxxQ', record)
            if len(record) < 22:
                raise ValueError('a message record shorter than its fields')
            items.append((op, (cid, stamp, bytes(record[22:]))))
    return items


def _records(
    stream: BinaryIO, mcap: Path, report: RecoveryReport
) -> Iterator[tuple[int, int, bytes]]:
    """Yield (offset, opcode, body) of each complete top-level record; report where it ends."""
    while True:
        offset = stream.tell()
        head = stream.read(9)
        if not head:
            report.dropped.append(f'nothing: the file ends at byte {offset} without a footer')
            return
        if len(head) < 9:
            report.dropped.append(f'{len(head)} bytes of a cut record header at byte {offset}')
            return
        op, length = struct.unpack('<BQ', head)
        body = stream.read(length) if length < 1 << 40 else b''
        if len(body) < length:
            what = 'chunk (its messages)' if op == OP_CHUNK else f'record (op 0x{op:02x})'
            report.dropped.append(
                f'a cut {what} at byte {offset}: {len(body) + 9} of {length + 9} bytes on disk'
            )
            return
        yield offset, op, body


def _string(data: bytes, at: int) -> tuple[str, int]:
    (n,) = struct.unpack_from('<I', data, at)
    end = at + 4 + n
    if end > len(data):
        raise ValueError('string runs past its record')
    return data[at + 4 : end].decode(), end


def _chunk_items(body: bytes) -> list[Item]:
    size, crc = struct.unpack_from('<QI', body, 16)
    compression, at = _string(body, 28)
    (length,) = struct.unpack_from('<Q', body, at)
    data = body[at + 8 : at + 8 + length]
    if len(data) != length:
        raise ValueError('chunk records run past the chunk')
    raw = decompress(data, compression, size, crc)
    at = 0
    records = []
    while at < len(raw):
        op, n = struct.unpack_from('<BQ', raw, at)
        if at + 9 + n > len(raw):
            raise ValueError('a record runs past its chunk')
        records.append((op, raw[at + 9 : at + 9 + n]))
        at += 9 + n
    return _items(records)


def _rihs01(channel: Channel, cache: dict[str, str]) -> str:
    """The type hash rosbag2 metadata wants, from the definition stored in the mcap."""
    if channel.msgtype not in cache:
        store = get_typestore(Stores.EMPTY)
        try:
            if channel.encoding == 'ros2idl':
                store.register(get_types_from_idl(channel.msgdef))
            else:
                store.register(get_types_from_msg(channel.msgdef, channel.msgtype))
            cache[channel.msgtype] = store.hash_rihs01(channel.msgtype)
        except Exception as err:
            raise BagError(
                f'topic {channel.topic!r}: its stored definition of {channel.msgtype} does '
                f'not parse: {err}'
            ) from None
    return cache[channel.msgtype]
