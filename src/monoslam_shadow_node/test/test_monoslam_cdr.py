"""monoslam reads its features serialized (``features_from_cdr``): the same ids, pixels, stamp
and frame as the message rclpy deserializes, for every alignment of the frame id."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from monoslam_shadow_node.conversions import features_from_message
from monoslam_shadow_node.monoslam_conversions import features_from_cdr
from slam_interfaces.msg import FeatureTrack, FeatureTrackArray


def message(frame_id: str, count: int, seed: int) -> FeatureTrackArray:
    rng = np.random.default_rng(seed)
    tracks = [
        FeatureTrack(
            id=int(rng.integers(-5, 1 << 40)), u=float(rng.normal(300.0, 200.0)),
            v=float(rng.normal(240.0, 200.0)), covariance=rng.normal(size=3),
            warp=rng.normal(size=4),
        )
        for _ in range(count)
    ]  # fmt: skip
    out = FeatureTrackArray(tracks=tracks)
    out.header.frame_id = frame_id
    out.header.stamp.sec = int(rng.integers(0, 2**31 - 1))
    out.header.stamp.nanosec = int(rng.integers(0, 10**9))
    return out


@pytest.mark.parametrize('frame_id', ['', 'c', 'cam', 'came', 'camera_optical', 'kamera_é'])
@pytest.mark.parametrize('count', [0, 1, 3, 150])
def test_serialized_features_read_as_the_message(frame_id: str, count: int) -> None:
    sent = message(frame_id, count, seed=count)
    features = features_from_cdr(serialize_message(sent))
    expected = features_from_message(sent)
    assert features is not None
    assert (features.stamp_ns, features.frame_id) == (expected.stamp_ns, expected.frame_id)
    assert features.ids.dtype == np.int64 and np.array_equal(features.ids, expected.ids)
    assert features.pixels.shape == (count, 2)
    assert np.array_equal(features.pixels, expected.pixels)


def test_other_encodings_and_truncated_data_are_left_to_the_deserializer() -> None:
    data = serialize_message(message('camera', 5, seed=1))
    assert features_from_cdr(b'\x00\x00' + data[2:]) is None  # big-endian CDR
    assert features_from_cdr(data[:-8]) is None
    assert features_from_cdr(b'') is None
