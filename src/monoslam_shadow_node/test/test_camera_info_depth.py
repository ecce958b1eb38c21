"""monoslam and shadow_filter take one camera_info per features message, so their best-effort
camera_info queue holds as many messages as the reliable features queue: a node behind its
features by more than the sensor depth (0.5 s) would otherwise lose camera_info first (real
rclpy nodes; their subscriptions' QoS is read back)."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy

from monoslam_shadow_node.monoslam.node import MonoSlamNode
from monoslam_shadow_node.shadow_filter.node import ShadowFilterNode
from slam_ros.qos import SENSOR_DEPTH


@pytest.mark.parametrize('make', [MonoSlamNode, ShadowFilterNode])
def test_camera_info_is_kept_as_deep_as_the_features(
    ros_context: None, make: Callable[[], Node]
) -> None:
    node = make()
    try:
        qos = {sub.topic_name: sub.qos_profile for sub in node.subscriptions}
        info, features = qos['/camera/camera_info'], qos['/features']
        assert info.reliability == ReliabilityPolicy.BEST_EFFORT  # a camera driver's QoS
        assert features.reliability == ReliabilityPolicy.RELIABLE
        assert info.depth == features.depth > SENSOR_DEPTH
    finally:
        node.destroy_node()
