"""camera_mount's transforms: the mount from parameters and REP 103's optical frame."""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time

from slam_bringup.camera_mount import PARAMETERS, mount_transforms
from slam_core.geometry.quaternion import rotation_from_quaternion


def _matrix(transform) -> np.ndarray:  # type: ignore[no-untyped-def]
    q = transform.transform.rotation
    t = transform.transform.translation
    out = np.eye(4)
    out[:3, :3] = rotation_from_quaternion([q.w, q.x, q.y, q.z])
    out[:3, 3] = (t.x, t.y, t.z)
    return out


def test_a_pitched_mount_sees_ahead_and_down_in_the_optical_frame() -> None:
    values = {param.name: param.default for param in PARAMETERS}
    values.update(xyz_m=[0.2, 0.0, 1.1], rpy_rad=[0.0, 0.3, 0.0])  # pitched 0.3 rad down
    mount, optical = mount_transforms(values, Time())
    assert (mount.header.frame_id, mount.child_frame_id) == ('base_link', 'camera_link')
    assert (optical.header.frame_id, optical.child_frame_id) == (
        'camera_link',
        'camera_optical_frame',
    )
    base_from_optical = _matrix(mount) @ _matrix(optical)
    forward = base_from_optical[:3, :3] @ [0.0, 0.0, 1.0]  # the optical axis, z
    np.testing.assert_allclose(forward, [np.cos(0.3), 0.0, -np.sin(0.3)], atol=1e-12)
    right = base_from_optical[:3, :3] @ [1.0, 0.0, 0.0]  # image x: to the robot's right
    np.testing.assert_allclose(right, [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(base_from_optical[:3, 3], [0.2, 0.0, 1.1])
