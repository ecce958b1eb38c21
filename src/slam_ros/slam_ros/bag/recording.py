"""An mcap writer whose bag appears at its path only when closed (docs/design/ros_and_core.md)."""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapWriter

from slam_core.errors import BagError


@dataclass(frozen=True)
class TopicRecord:
    """A recorded topic: its writer connection and how many messages it got."""

    connection: Connection
    msgtype: str


class AtomicBagWriter:
    """Writes one mcap bag; ``close()`` finalizes it and moves it to ``target``."""

    def __init__(self, target: Path, *, flush_period_s: float = 1.0) -> None:
        if not flush_period_s > 0:
            raise BagError(f'flush_period_s must be > 0, got {flush_period_s}')
        self.flush_period_s = flush_period_s
        self.target = Path(target).expanduser().absolute()
        if self.target.exists():
            raise BagError(f'output {str(self.target)!r} exists already; choose another name')
        if not self.target.parent.is_dir():
            raise BagError(
                f'output {str(self.target)!r}: directory {str(self.target.parent)!r} '
                'does not exist'
            )
        self.staging_root = self.target.parent / f'.{self.target.name}.recording-{os.getpid()}'
        self.staging = self.staging_root / self.target.name
        try:
            self.staging_root.mkdir()
            self._writer = Writer(self.staging, version=9, storage_plugin=StoragePlugin.MCAP)
            self._writer.open()
        except OSError as err:
            raise BagError(f'output {str(self.target)!r} cannot be written: {err}') from None
        # rosbags' mcap storage keeps the open chunk in memory; close_chunk() writes it out.
        storage = self._writer.storage
        if not isinstance(storage, McapWriter):
            raise BagError(f'rosbags gave a {type(storage).__name__}, not its mcap writer')
        self._storage = storage
        self._last_flush = time.monotonic()
        self.counts: dict[str, int] = {}
        self._topics: dict[str, TopicRecord] = {}
        self.closed = False

    def add_topic(
        self, topic: str, msgtype: str, *, msgdef: str, rihs01: str, offered_qos: Sequence[Qos]
    ) -> None:
        """Register a topic before writing its first message."""
        connection = self._writer.add_connection(
            topic, msgtype, msgdef=msgdef, rihs01=rihs01, offered_qos_profiles=offered_qos
        )
        self._topics[topic] = TopicRecord(connection, msgtype)
        self.counts[topic] = 0

    def has_topic(self, topic: str) -> bool:
        """True when ``topic`` was registered."""
        return topic in self._topics

    def write(self, topic: str, timestamp_ns: int, data: bytes) -> None:
        """Append one CDR message received at ``timestamp_ns``."""
        self._writer.write(self._topics[topic].connection, timestamp_ns, data)
        self.counts[topic] += 1
        if time.monotonic() - self._last_flush >= self.flush_period_s:
            self.flush()

    def flush(self) -> None:
        """Write the open chunk (if it holds messages) and flush the file to the OS."""
        self._last_flush = time.monotonic()
        if self.closed:
            return
        if self._storage.chunk.msgs:
            self._storage.close_chunk()
        self._storage.bio.flush()

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return sum(self.counts.values())

    def close(self) -> Path:
        """Finalize the bag (index, metadata.yaml) and move it to the target; idempotent."""
        if not self.closed:
            self.closed = True
            self._writer.close()
            try:
                self.staging.rename(self.target)
            except OSError as err:
                raise BagError(
                    f'output {str(self.target)!r} cannot be created: {err}; the finished bag '
                    f'is at {str(self.staging)!r}'
                ) from None
            shutil.rmtree(self.staging_root, ignore_errors=True)
        return self.target

    def abort(self) -> None:
        """Discard the bag: nothing appears at the target (for a conversion that failed)."""
        if not self.closed:
            self.closed = True
            try:
                self._writer.close()
            finally:
                shutil.rmtree(self.staging_root, ignore_errors=True)
