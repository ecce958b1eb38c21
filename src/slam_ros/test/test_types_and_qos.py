"""Unit tests of type lookup, QoS translation and parameter helpers."""

from __future__ import annotations

import pytest
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from rosbags.interfaces import QosDurability, QosReliability

from slam_core.errors import ParameterError, TypeDefinitionError
from slam_ros.params import parse_remaps
from slam_ros.qos import latched_qos, output_qos, profile_from_recorded, recorded_from_profile
from slam_ros.testing.messages import RELIABLE_QOS
from slam_ros.typesys import TypeRegistry, message_class, split_type_name


def test_registry_learns_slam_interfaces_from_msg_files() -> None:
    registry = TypeRegistry()
    msgdef, rihs01 = registry.msgdef_and_hash('slam_interfaces/msg/MoveableLandmarkArray')
    assert 'LandmarkSighting' in msgdef
    assert rihs01.startswith('RIHS01_')
    assert 'slam_interfaces/msg/LandmarkSighting' in registry.typestore.fielddefs


def test_unknown_type_is_named() -> None:
    with pytest.raises(TypeDefinitionError, match='widget_msgs/msg/Widget'):
        TypeRegistry().ensure('widget_msgs/msg/Widget', context='topic /w')
    with pytest.raises(TypeDefinitionError, match="topic '/w'"):
        message_class('widget_msgs/msg/Widget', topic='/w')
    with pytest.raises(TypeDefinitionError, match='malformed'):
        split_type_name('nonsense')


def test_message_class_imports_rclpy_types() -> None:
    assert message_class('nav_msgs/msg/Odometry').__name__ == 'Odometry'
    assert message_class('slam_interfaces/msg/LandmarkMap').__name__ == 'LandmarkMap'


@pytest.mark.parametrize('profile', [output_qos(), latched_qos()], ids=['output', 'latched'])
def test_qos_round_trip_through_bag_metadata(profile: object) -> None:
    recorded = recorded_from_profile(profile)  # type: ignore[arg-type]
    replayed = profile_from_recorded([recorded])
    assert replayed.reliability == profile.reliability  # type: ignore[attr-defined]
    assert replayed.durability == profile.durability  # type: ignore[attr-defined]
    assert replayed.depth == profile.depth  # type: ignore[attr-defined]


def test_sensor_topics_replay_best_effort_as_recorded() -> None:
    best_effort = RELIABLE_QOS._replace(reliability=QosReliability.BEST_EFFORT)
    assert profile_from_recorded([best_effort]).reliability == ReliabilityPolicy.BEST_EFFORT


def test_disagreeing_publishers_replay_with_the_qos_every_subscriber_matches() -> None:
    best_effort = RELIABLE_QOS._replace(reliability=QosReliability.BEST_EFFORT)
    latched = RELIABLE_QOS._replace(durability=QosDurability.TRANSIENT_LOCAL)
    replayed = profile_from_recorded([best_effort, latched])
    assert replayed.reliability == ReliabilityPolicy.RELIABLE
    assert replayed.durability == DurabilityPolicy.VOLATILE


def test_ros1_topics_replay_reliable_and_latched_if_latched() -> None:
    assert profile_from_recorded([], latched=True).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert profile_from_recorded([]).reliability == ReliabilityPolicy.RELIABLE


def test_parse_remaps() -> None:
    assert parse_remaps('remap', ['/a:=/b', 'c:=d']) == {'/a': '/b', 'c': 'd'}
    with pytest.raises(ParameterError, match="remap='/a'"):
        parse_remaps('remap', ['/a'])
    with pytest.raises(ParameterError, match='twice'):
        parse_remaps('remap', ['/a:=/b', '/a:=/c'])
