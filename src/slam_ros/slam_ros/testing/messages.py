"""Seeded synthetic messages of any known type, and bags (docs/design/ros_and_core.md)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import (
    Nodetype,
    Qos,
)

from slam_ros.qos import output_qos, recorded_from_profile
from slam_ros.typesys import TypeRegistry

_NUMPY_TYPES = {
    'bool': np.bool_,
    'byte': np.uint8,
    'char': np.uint8,
    'int8': np.int8,
    'uint8': np.uint8,
    'int16': np.int16,
    'uint16': np.uint16,
    'int32': np.int32,
    'uint32': np.uint32,
    'int64': np.int64,
    'uint64': np.uint64,
    'float32': np.float32,
    'float64': np.float64,
}
# What the synthetic bags record as offered QoS: reliable, volatile, keep last 100.
RELIABLE_QOS = recorded_from_profile(output_qos(depth=100))


def _scalar(typename: str, rng: np.random.Generator) -> object:
    if typename == 'string':
        return f'frame_{int(rng.integers(0, 10**6))}'
    if typename == 'bool':
        return bool(rng.integers(0, 2))
    if typename in ('float32', 'float64'):
        value = float(rng.normal(0.0, 100.0))
        return float(np.float32(value)) if typename == 'float32' else value
    info = np.iinfo(_NUMPY_TYPES[typename])
    return int(rng.integers(max(info.min, -(10**6)), min(info.max, 10**6) + 1))


def _array(typename: str, length: int, rng: np.random.Generator) -> object:
    if typename == 'string':
        return [_scalar('string', rng) for _ in range(length)]
    dtype = _NUMPY_TYPES[typename]
    if typename in ('float32', 'float64'):
        return rng.normal(0.0, 100.0, length).astype(dtype)
    if typename == 'bool':
        return rng.integers(0, 2, length).astype(np.bool_)
    info = np.iinfo(dtype)
    return rng.integers(max(info.min, -(10**6)), min(info.max, 10**6) + 1, length).astype(dtype)


def random_message(
    registry: TypeRegistry, msgtype: str, rng: np.random.Generator, *, max_sequence: int = 4
) -> object:
    """Return a rosbags message of ``msgtype`` with every field set from ``rng``."""
    registry.ensure(msgtype)
    store = registry.typestore
    _, fields = store.fielddefs[msgtype]
    values: dict[str, Any] = {}
    for name, (nodetype, field_detail) in fields:
        detail: Any = field_detail  # rosbags' field union; its shape depends on nodetype
        if nodetype == Nodetype.BASE:
            values[name] = _scalar(detail[0], rng)
        elif nodetype == Nodetype.NAME:
            values[name] = random_message(registry, detail, rng, max_sequence=max_sequence)
        else:
            (inner_type, inner_detail), bound = detail
            length = (
                bound if nodetype == Nodetype.ARRAY else int(rng.integers(1, max_sequence + 1))
            )
            if inner_type == Nodetype.BASE:
                values[name] = _array(inner_detail[0], length, rng)
            else:
                values[name] = [
                    random_message(registry, inner_detail, rng, max_sequence=max_sequence)
                    for _ in range(length)
                ]
    return store.types[msgtype](**values)


def set_stamp(message: object, stamp_ns: int) -> None:
    """Set ``message.header.stamp`` (when it has a header) to ``stamp_ns``."""
    header = getattr(message, 'header', None)
    if header is not None and hasattr(header, 'stamp'):
        header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)


@dataclass(frozen=True)
class BagTopic:
    """A topic for ``write_bag``: its type and message rate."""

    name: str
    msgtype: str
    rate_hz: float


@dataclass(frozen=True)
class WrittenMessage:
    """A message written by ``write_bag``: topic, bag stamp (int ns) and CDR bytes."""

    topic: str
    timestamp_ns: int
    data: bytes


def write_bag(
    path: Path,
    topics: Sequence[BagTopic],
    *,
    duration_s: float,
    registry: TypeRegistry | None = None,
    seed: int = 0,
    start_ns: int = 1_700_000_000 * 10**9,
    storage: str = 'mcap',
    qos: Qos = RELIABLE_QOS,
    message_factory: Callable[[np.random.Generator], object] | None = None,
) -> list[WrittenMessage]:
    """Write a rosbag2 bag ('mcap' or 'sqlite3') of random messages; return them by stamp."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    registry = registry if registry is not None else TypeRegistry()
    rng = np.random.default_rng(seed)
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    written: list[WrittenMessage] = []
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        connections = {
            topic.name: registry.add_connection(writer, topic.name, topic.msgtype, [qos])
            for topic in topics
        }
        schedule = sorted(
            (start_ns + round(i * 1e9 / topic.rate_hz), index)
            for index, topic in enumerate(topics)
            for i in range(max(1, int(duration_s * topic.rate_hz)))
        )
        for stamp_ns, index in schedule:
            topic = topics[index]
            message = (
                message_factory(rng)
                if message_factory is not None
                else random_message(registry, topic.msgtype, rng)
            )
            set_stamp(message, stamp_ns)
            data = bytes(registry.typestore.serialize_cdr(message, topic.msgtype))
            writer.write(connections[topic.name], stamp_ns, data)
            written.append(WrittenMessage(topic.name, stamp_ns, data))
    return written


def plain(message: object) -> object:
    """Return a rosbags message as nested dicts and lists, for equality checks."""
    if isinstance(message, np.ndarray):
        return message.tolist()
    if isinstance(message, (list, tuple)):
        return [plain(item) for item in message]
    fields = getattr(message, '__dataclass_fields__', None)
    if fields is None:
        return message
    return {name: plain(getattr(message, name)) for name in fields if name != '__msgtype__'}


def decode_all(registry: TypeRegistry, msgtype: str, payloads: Sequence[bytes]) -> list[object]:
    """Decode CDR payloads of ``msgtype`` into plain nested structures."""
    registry.ensure(msgtype)
    store = registry.typestore
    return [plain(store.deserialize_cdr(data, msgtype)) for data in payloads]
