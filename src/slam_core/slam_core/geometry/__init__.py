"""Rigid-body geometry: se2, so3, quaternion, se3 (conventions: docs/design/ros_and_core.md)."""
