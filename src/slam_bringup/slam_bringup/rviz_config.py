"""What an .rviz file needs from a graph; does a running graph give it (docs/design/bringup.md)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from slam_ros.tf_tree import TfTree

DISPLAY_TYPES = {
    'rviz_default_plugins/Image': 'sensor_msgs/msg/Image',
    'rviz_default_plugins/Marker': 'visualization_msgs/msg/Marker',
    'rviz_default_plugins/MarkerArray': 'visualization_msgs/msg/MarkerArray',
    'rviz_default_plugins/Odometry': 'nav_msgs/msg/Odometry',
    'rviz_default_plugins/Path': 'nav_msgs/msg/Path',
    'rviz_default_plugins/PointCloud2': 'sensor_msgs/msg/PointCloud2',
    'rviz_default_plugins/Pose': 'geometry_msgs/msg/PoseStamped',
    'rviz_default_plugins/PoseArray': 'geometry_msgs/msg/PoseArray',
    'rviz_default_plugins/PoseWithCovariance': 'geometry_msgs/msg/PoseWithCovarianceStamped',
}
"""Display class -> the message type it subscribes to (its "Topic")."""
NO_TOPIC_CLASSES = frozenset(
    {'rviz_default_plugins/Axes', 'rviz_default_plugins/Grid', 'rviz_default_plugins/TF'}
)
"""Display classes without a topic (TF reads /tf and /tf_static itself)."""
GROUP_CLASS = 'rviz_common/Group'
PANEL_CLASSES = frozenset({'rviz_default_plugins/Image'})
"""Displays that draw in their own panel: their messages need no transform."""
RELIABILITY = {'Reliable': 'reliable', 'Best Effort': 'best_effort'}
DURABILITY = {'Volatile': 'volatile', 'Transient Local': 'transient_local'}


class RvizConfigError(ValueError):
    """An .rviz file that cannot be read, or names a display class of unknown needs."""


@dataclass(frozen=True)
class TopicQos:
    """A display's QoS: depth, 'reliable' or 'best_effort', 'volatile' or 'transient_local'."""

    depth: int
    reliability: str
    durability: str

    def profile(self) -> Any:
        """Return it as an rclpy QoSProfile (keep last ``depth``)."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        return QoSProfile(
            depth=self.depth,
            reliability=ReliabilityPolicy.RELIABLE
            if self.reliability == 'reliable'
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL
            if self.durability == 'transient_local'
            else DurabilityPolicy.VOLATILE,
        )


@dataclass(frozen=True)
class DisplayNeeds:
    """One display: name, class and, with a topic, its QoS, message type and frame need."""

    name: str
    display_class: str
    topic: str | None = None
    qos: TopicQos | None = None
    message_type: str | None = None
    in_fixed_frame: bool = False


@dataclass(frozen=True)
class RvizNeeds:
    """An .rviz file's needs: its fixed frame and its displays."""

    path: Path
    fixed_frame: str
    displays: tuple[DisplayNeeds, ...]

    def topics(self) -> dict[str, DisplayNeeds]:
        """Return the displays with a topic, by topic."""
        return {d.topic: d for d in self.displays if d.topic is not None}


@dataclass
class GraphObservation:
    """What a running graph was seen doing: publisher types, frame ids received, the TF tree."""

    publishers: dict[str, set[str]] = field(default_factory=dict)
    frame_ids: dict[str, set[str]] = field(default_factory=dict)
    received: dict[str, int] = field(default_factory=dict)
    tree: TfTree = field(default_factory=TfTree)

    def frames(self) -> set[str]:
        """Return every frame of the TF tree."""
        return set(self.tree.edges) | {edge.parent for edge in self.tree.edges.values()}


def _mapping(value: object, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise RvizConfigError(f'{where}: expected a mapping, got {type(value).__name__}')
    return value


def _walk(displays: object, where: str) -> Iterator[Mapping[str, Any]]:
    if not isinstance(displays, list):
        raise RvizConfigError(f'{where}: expected a list of displays')
    for index, entry in enumerate(displays):
        display = _mapping(entry, f'{where}[{index}]')
        if display.get('Class') == GROUP_CLASS:
            yield from _walk(display.get('Displays', []), f'{where}[{index}].Displays')
        else:
            yield display


def _topic_qos(topic: Mapping[str, Any], where: str) -> TopicQos:
    try:
        return TopicQos(
            depth=int(topic['Depth']),
            reliability=RELIABILITY[str(topic['Reliability Policy'])],
            durability=DURABILITY[str(topic['Durability Policy'])],
        )
    except (KeyError, ValueError, TypeError) as err:
        raise RvizConfigError(f'{where}.Topic: bad or missing QoS field ({err})') from err


def _display(display: Mapping[str, Any], where: str) -> DisplayNeeds:
    display_class = str(display.get('Class', ''))
    name = str(display.get('Name', display_class))
    where = f'{where} {name!r} ({display_class})'
    if display_class in NO_TOPIC_CLASSES:
        return DisplayNeeds(name, display_class)
    if display_class not in DISPLAY_TYPES:
        raise RvizConfigError(f'{where}: display class of unknown needs (not in DISPLAY_TYPES)')
    topic = _mapping(display.get('Topic'), f'{where}.Topic')
    value = topic.get('Value')
    if not isinstance(value, str) or not value.startswith('/'):
        raise RvizConfigError(f'{where}.Topic.Value: {value!r} is not an absolute topic name')
    return DisplayNeeds(
        name,
        display_class,
        topic=value,
        qos=_topic_qos(topic, where),
        message_type=DISPLAY_TYPES[display_class],
        in_fixed_frame=display_class not in PANEL_CLASSES,
    )


def read_rviz(path: Path | str) -> RvizNeeds:
    """Return the needs of the .rviz file at ``path`` (raises RvizConfigError)."""
    path = Path(path)
    try:
        content = yaml.safe_load(path.read_text(encoding='utf-8'))
    except (OSError, yaml.YAMLError) as err:
        raise RvizConfigError(f'{path}: {err}') from err
    manager = _mapping(_mapping(content, str(path)).get('Visualization Manager'), f'{path}')
    options = _mapping(manager.get('Global Options'), f'{path}: Global Options')
    fixed_frame = options.get('Fixed Frame')
    if not isinstance(fixed_frame, str) or not fixed_frame:
        raise RvizConfigError(f'{path}: Global Options has no Fixed Frame')
    displays = tuple(
        _display(display, f'{path}: display')
        for display in _walk(manager.get('Displays'), f'{path}: Displays')
    )
    return RvizNeeds(path, fixed_frame, displays)


def check_rviz(needs: RvizNeeds, seen: GraphObservation) -> list[str]:
    """Return the problems of showing the observed graph with ``needs`` (empty: none)."""
    problems = []
    frames = seen.frames()
    if needs.fixed_frame not in frames:
        problems.append(
            f'fixed frame {needs.fixed_frame!r} is not in the TF tree (frames: {sorted(frames)})'
        )
    for display in needs.displays:
        if display.topic is None:
            continue
        label = f'display {display.name!r} ({display.display_class}) on {display.topic}'
        types = seen.publishers.get(display.topic, set())
        if not types:
            problems.append(f'{label}: nobody publishes it')
            continue
        if display.message_type not in types:
            problems.append(
                f'{label}: published as {sorted(types)}, the display takes {display.message_type}'
            )
            continue
        if not seen.received.get(display.topic):
            problems.append(f"{label}: nothing received with the display's QoS {display.qos}")
            continue
        if not display.in_fixed_frame:
            continue
        for frame in sorted(seen.frame_ids.get(display.topic, set())):
            if frame != needs.fixed_frame and not seen.tree.lookup_chain(needs.fixed_frame, frame):
                problems.append(
                    f'{label}: frame {frame!r} has no transform to the fixed frame '
                    f'{needs.fixed_frame!r}'
                )
    return problems
