"""A read-only view of one bag as ROS 2 CDR, any format (docs/design/ros_and_core.md)."""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from rosbags.convert.converter import is_same_wireformat, migrate_bytes
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, ConnectionExtRosbag1, ConnectionExtRosbag2, Qos
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from slam_core.errors import BagError

ROS1_TO_ROS2_RENAMES = {'tf/msg/tfMessage': 'tf2_msgs/msg/TFMessage'}


@dataclass(frozen=True)
class TopicSummary:
    """One topic of a bag: type, message count and recorded QoS."""

    name: str
    msgtype: str
    count: int
    offered_qos: tuple[Qos, ...]
    latched: bool


@dataclass(frozen=True)
class BagMessage:
    """One message: topic, ROS 2 type name, receive stamp (int ns) and CDR bytes."""

    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


def storage_kind(path: Path) -> str:
    """Return 'ros1', 'mcap' or 'sqlite3' for a bag path (file or rosbag2 directory)."""
    if path.suffix == '.bag':
        return 'ros1'
    if path.suffix == '.mcap':
        return 'mcap'
    if path.suffix == '.db3':
        return 'sqlite3'
    if path.is_dir():
        if any(path.glob('*.mcap')):
            return 'mcap'
        if any(path.glob('*.db3')):
            return 'sqlite3'
        if any(path.glob('*/*.mcap')):  # a killed recorder's staging dir .NAME.recording-PID
            raise BagError(
                f'bag {str(path)!r} is an unfinished recording (its recorder was killed)'
                f'{recover_hint(path)}'
            )
        raise BagError(f'bag {str(path)!r}: directory holds no .mcap or .db3 file')
    raise BagError(
        f'bag {str(path)!r}: unrecognized format {path.suffix!r}; expected a rosbag2 '
        'directory, a .mcap or .db3 file, or a ROS 1 .bag'
    )


class BagSource:
    """Open a bag for reading; use as a context manager."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'bag {str(self.path)!r} does not exist')
        self.storage = storage_kind(self.path)
        try:
            self._reader = AnyReader(
                [self.path], default_typestore=get_typestore(Stores.ROS2_JAZZY)
            )
        except Exception as err:
            hint = recover_hint(self.path) if self.storage == 'mcap' else ''
            raise BagError(
                f'bag {str(self.path)!r} cannot be read: {_describe(err)}{hint}'
            ) from None
        self._converters: dict[str, Callable[[bytes], bytes]] = {}
        self._ros2_store: Typestore | None = None

    def __enter__(self) -> BagSource:
        try:
            self._reader.open()
        except Exception as err:
            raise BagError(
                f'bag {str(self.path)!r} is corrupt or truncated and cannot be opened: '
                f'{_describe(err)}{self._hint()}'
            ) from None
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._reader.stack is not None:
            self._reader.close()

    @property
    def is_ros1(self) -> bool:
        """True for a ROS 1 ``.bag``."""
        return self.storage == 'ros1'

    @property
    def start_ns(self) -> int:
        """Stamp of the earliest message, int ns (0 for an empty bag)."""
        return self._reader.start_time if self._reader.message_count else 0

    @property
    def end_ns(self) -> int:
        """Stamp of the latest message, int ns (0 for an empty bag)."""
        return self._latest_stamp_ns() if self._reader.message_count else 0

    @property
    def duration_ns(self) -> int:
        """end_ns - start_ns."""
        return self.end_ns - self.start_ns

    @property
    def message_count(self) -> int:
        """Number of messages in the bag."""
        return self._reader.message_count

    @property
    def typestore(self) -> Typestore:
        """The type store holding the bag's own definitions."""
        return self._reader.typestore

    def _latest_stamp_ns(self) -> int:
        # rosbags reports end_time as one past the latest stamp for rosbag2 and ROS 1 alike.
        return self._reader.end_time - 1

    def topics(self) -> dict[str, TopicSummary]:
        """Return the bag's topics by name."""
        summaries = {}
        for name, info in self._reader.topics.items():
            offered: list[Qos] = []
            latched = False
            for connection in info.connections:
                if isinstance(connection.ext, ConnectionExtRosbag2):
                    offered.extend(connection.ext.offered_qos_profiles)
                elif isinstance(connection.ext, ConnectionExtRosbag1):
                    latched = latched or bool(connection.ext.latching)
            msgtype = info.msgtype or info.connections[0].msgtype
            summaries[name] = TopicSummary(
                name=name,
                msgtype=self._ros2_name(msgtype),
                count=info.msgcount,
                offered_qos=tuple(offered),
                latched=latched,
            )
        return summaries

    def messages(
        self,
        topics: Collection[str] | None = None,
        *,
        start_ns: int | None = None,
        validate: bool = False,
    ) -> Iterator[BagMessage]:
        """Yield ROS 2 CDR messages in stamp order; ``validate`` decodes each once."""
        connections = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if not connections:
            return
        stamp = start_ns
        try:
            for connection, timestamp, raw in self._reader.messages(
                connections=connections, start=start_ns
            ):
                stamp = timestamp
                data = self._to_cdr(connection, raw)
                if validate and not self.is_ros1:  # ROS 1 data was decoded to convert it
                    self._check_payload(connection, timestamp, data)
                yield BagMessage(
                    topic=connection.topic,
                    msgtype=self._ros2_name(connection.msgtype),
                    timestamp_ns=timestamp,
                    data=data,
                )
        except BagError:
            raise
        except Exception as err:
            at = '' if stamp is None else f' after stamp {stamp} ns'
            raise BagError(
                f'bag {str(self.path)!r} is corrupt or truncated{at}: {_describe(err)}'
                f'{self._hint()}'
            ) from None

    def _hint(self) -> str:
        return recover_hint(self.path) if self.storage == 'mcap' else ''

    def _check_payload(self, connection: Connection, timestamp: int, data: bytes) -> None:
        try:
            self._reader.typestore.deserialize_cdr(data, connection.msgtype)
        except Exception as err:
            raise BagError(
                f'bag {str(self.path)!r} is corrupt: message on {connection.topic!r} at stamp '
                f'{timestamp} ns does not decode as {connection.msgtype}: {_describe(err)}'
            ) from None

    @staticmethod
    def _ros2_name(msgtype: str) -> str:
        return ROS1_TO_ROS2_RENAMES.get(msgtype, msgtype)

    def _to_cdr(self, connection: Connection, raw: bytes) -> bytes:
        if not self.is_ros1:
            return bytes(raw)
        convert = self._converters.get(connection.msgtype)
        if convert is None:
            convert = self._make_ros1_converter(connection.msgtype)
            self._converters[connection.msgtype] = convert
        return convert(raw)

    def _make_ros1_converter(self, msgtype: str) -> Callable[[bytes], bytes]:
        source_store = self._reader.typestore
        if self._ros2_store is None:
            # The bag's own definitions, but with the ROS 2 Header (no seq), as rosbags-convert.
            header = get_typestore(Stores.ROS2_JAZZY).fielddefs['std_msgs/msg/Header']
            self._ros2_store = get_typestore(Stores.EMPTY)
            self._ros2_store.register({**source_store.fielddefs, 'std_msgs/msg/Header': header})
        target_store = self._ros2_store
        if is_same_wireformat(source_store, target_store, msgtype, msgtype):
            return lambda raw: bytes(target_store.ros1_to_cdr(raw, msgtype))
        cache: dict[str, object] = {}
        return lambda raw: bytes(
            migrate_bytes(
                source_store,
                target_store,
                msgtype,
                msgtype,
                cache,
                raw,
                src_is2=False,
                dst_is2=True,
            )
        )


def recover_hint(path: Path) -> str:
    """The advice appended to an unreadable mcap bag's error."""
    return f'; run `bag_recover {path}` to rebuild a readable bag from it'


def _describe(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f'{type(err).__name__}: {text[0]}' if text else type(err).__name__
