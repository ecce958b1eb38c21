"""Messages <-> the apriltag_bridge: apriltag_msgs/AprilTagDetectionArray to tags. Fields
are read by name, so rclpy and rosbags messages both work; the sightings go out through
``marker_detector.common.conversions``."""

from __future__ import annotations

from typing import Any

import numpy as np

from marker_detector.apriltag_bridge.processor import Tag


def tags_from_message(message: Any) -> list[Tag]:
    """The tags of an AprilTagDetectionArray (fields read by name)."""
    return [
        Tag(
            family=str(item.family),
            id=int(item.id),
            corners_px=np.array([[c.x, c.y] for c in item.corners], dtype=np.float64),
        )
        for item in message.detections
    ]
