"""odometry_ingest's landmark_observations durability: volatile by default (a bag player's
publishers), transient-local with observations_transient_local, so that live it gets the
detector's history of sightings published before it discovered the detector (a real rclpy
node; its subscription's QoS is read back)."""

from __future__ import annotations

import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy

from em_sam_node.odometry_ingest.node import OdometryIngestNode


@pytest.mark.parametrize(
    ('transient_local', 'durability'),
    [(False, DurabilityPolicy.VOLATILE), (True, DurabilityPolicy.TRANSIENT_LOCAL)],
)
def test_observations_durability_follows_the_parameter(
    ros_context: None, transient_local: bool, durability: DurabilityPolicy
) -> None:
    overrides = [Parameter('observations_transient_local', value=transient_local)]
    node = OdometryIngestNode(parameter_overrides=overrides)
    try:
        qos = {sub.topic_name: sub.qos_profile for sub in node.subscriptions}
        assert qos['/landmark_observations'].durability == durability
        assert qos['/landmark_observations'].depth == 1000
    finally:
        node.destroy_node()
