"""Message types: rosbags definitions and rclpy classes (docs/design/ros_and_core.md)."""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from pathlib import Path

from rosbags.interfaces import Connection, Nodetype, Qos
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from slam_core.errors import TypeDefinitionError


def split_type_name(msgtype: str) -> tuple[str, str, str]:
    """Return (package, kind, name) of ``pkg/msg/Name``; accept ``pkg/Name`` as msg."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        return parts[0], 'msg', parts[1]
    if len(parts) == 3 and all(parts):
        return parts[0], parts[1], parts[2]
    raise TypeDefinitionError(f'malformed message type name {msgtype!r}; expected pkg/msg/Name')


def ament_prefixes() -> list[Path]:
    """Return the install prefixes on AMENT_PREFIX_PATH, in lookup order."""
    return [Path(p) for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]


def find_msg_file(msgtype: str, prefixes: list[Path] | None = None) -> Path | None:
    """Return the installed ``.msg`` file of ``msgtype``, or None."""
    package, kind, name = split_type_name(msgtype)
    for prefix in ament_prefixes() if prefixes is None else prefixes:
        candidate = prefix / 'share' / package / kind / f'{name}.msg'
        if candidate.is_file():
            return candidate
    return None


class TypeRegistry:
    """A rosbags type store that grows on demand from installed ``.msg`` files."""

    def __init__(self, *, typestore: Typestore | None = None) -> None:
        self.typestore = typestore if typestore is not None else get_typestore(Stores.ROS2_JAZZY)

    def ensure(self, msgtype: str, *, context: str = '') -> None:
        """Make ``msgtype`` and its field types known (TypeDefinitionError if undefined)."""
        pending = [msgtype]
        while pending:
            current = pending.pop()
            if current in self.typestore.fielddefs:
                continue
            path = find_msg_file(current)
            if path is None:
                where = f' ({context})' if context else ''
                raise TypeDefinitionError(
                    f'message type {current!r}{where} has no definition: no '
                    f'share/{"/".join(split_type_name(current))}.msg on AMENT_PREFIX_PATH. '
                    'Build its interface package and source scripts/env.sh'
                )
            types = get_types_from_msg(path.read_text(encoding='utf-8'), current)
            self.typestore.register(types)
            for _, fields in types.values():
                pending.extend(_referenced_types(fields))

    def msgdef_and_hash(self, msgtype: str) -> tuple[str, str]:
        """Return the ROS 2 message definition text and RIHS01 hash of ``msgtype``."""
        self.ensure(msgtype)
        msgdef, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
        return msgdef, self.typestore.hash_rihs01(msgtype)

    def add_connection(
        self, writer: Writer, topic: str, msgtype: str, qos: Sequence[Qos]
    ) -> Connection:
        """Register ``topic`` on ``writer`` with this registry's definition; return it."""
        msgdef, rihs01 = self.msgdef_and_hash(msgtype)
        return writer.add_connection(
            topic, msgtype, msgdef=msgdef, rihs01=rihs01, offered_qos_profiles=list(qos)
        )


def _referenced_types(fields: object) -> list[str]:
    """Return the complex type names that a rosbags field list refers to."""
    names = []
    for _, (nodetype, detail) in fields:  # type: ignore[attr-defined]
        if nodetype == Nodetype.NAME:
            names.append(detail)
        elif nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            inner_type, inner_detail = detail[0]
            if inner_type == Nodetype.NAME:
                names.append(inner_detail)
    return names


def message_class(msgtype: str, *, topic: str | None = None) -> type:
    """Import the rclpy class of ``msgtype`` (``nav_msgs/msg/Odometry``); TypeDefinitionError."""
    package, kind, name = split_type_name(msgtype)
    where = f'topic {topic!r} has type {msgtype!r}' if topic else f'type {msgtype!r}'
    try:
        module = importlib.import_module(f'{package}.{kind}')
    except ImportError as err:
        raise TypeDefinitionError(
            f'{where}, which has no definition in this ROS environment (cannot import '
            f'{package}.{kind}: {err}). Build its interface package, or leave the topic out'
        ) from None
    cls = getattr(module, name, None)
    if not isinstance(cls, type):
        raise TypeDefinitionError(
            f'{where}, which has no definition in this ROS environment ({package}.{kind} '
            f'has no {name}). Build its interface package, or leave the topic out'
        )
    return cls
