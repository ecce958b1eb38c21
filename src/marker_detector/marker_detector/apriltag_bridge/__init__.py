"""The apriltag_bridge node: apriltag_ros detections to range-bearing sightings."""
