"""monoslam and shadow_filter count every camera_info they reject (CameraInfoWatch.rejected,
'camera_info rejected' on /diagnostics) and keep the last good camera."""

from __future__ import annotations

from sensor_msgs.msg import CameraInfo

from monoslam_shadow_node.common.conversions import CameraInfoWatch


def info(fx: float) -> CameraInfo:
    message = CameraInfo(width=64, height=48, distortion_model='plumb_bob')
    message.k = [fx, 0.0, 32.0, 0.0, 50.0, 24.0, 0.0, 0.0, 1.0]
    message.d = [0.0] * 5
    return message


def test_each_rejected_camera_info_is_counted_and_the_camera_kept() -> None:
    watch = CameraInfoWatch('camera/camera_info')
    first = watch.update(info(0.0))
    assert first is not None and first.camera is None and 'fx=0' in first.text
    assert 'still waiting' in first.text and watch.rejected == 1
    good = watch.update(info(50.0))
    assert good is not None and good.camera is not None and good.first
    for count in (2, 3):  # the same bad one again is rejected (and counted) again
        again = watch.update(info(0.0))
        assert again is not None and again.camera is None and 'camera kept' in again.text
        assert watch.rejected == count
    assert watch.update(info(50.0)) is None  # the kept camera is unchanged
