"""monoslam reads its features serialized (``conversions.features_from_cdr``): the same ids,
pixels, stamp and frame as the message rclpy deserializes, for every alignment of the frame
id; it publishes its predictions serialized (``predictions_cdr``): the message
``fill_predictions`` fills, as rclpy deserializes the bytes; and the feature tracker reads
them serialized (``conversions.predictions_from_cdr``): the same covariances and warps as
from the message; monoslam reads the Shadow filter's statuses serialized
(``monoslam_conversions.dynamic_ids_from_cdr``): the message's DYNAMIC ids."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from monoslam_shadow_node.common.conversions import features_from_cdr, features_from_message
from monoslam_shadow_node.feature_tracker.conversions import (
    prediction_covariances,
    prediction_warps,
    predictions_from_cdr,
)
from monoslam_shadow_node.monoslam.conversions import (
    dynamic_ids,
    dynamic_ids_from_cdr,
    fill_predictions,
    predictions_cdr,
)
from slam_interfaces.msg import FeatureTrack, FeatureTrackArray, ShadowTrack, ShadowTrackArray


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
    features = features_from_cdr(serialize_message(sent), deserialize)
    expected = features_from_message(sent)
    assert features is not None
    assert (features.stamp_ns, features.frame_id) == (expected.stamp_ns, expected.frame_id)
    assert features.ids.dtype == np.int64 and np.array_equal(features.ids, expected.ids)
    assert features.pixels.shape == (count, 2)
    assert np.array_equal(features.pixels, expected.pixels)


@pytest.mark.parametrize('frame_id', ['', 'cam', 'camera_optical'])
@pytest.mark.parametrize('count', [0, 1, 100])
def test_serialized_predictions_read_as_the_message(frame_id: str, count: int) -> None:
    sent = message(frame_id, count, seed=count + 7)
    features, covariances, warps = predictions_from_cdr(serialize_message(sent), deserialize)
    expected = features_from_message(sent)
    assert (features.stamp_ns, features.frame_id) == (expected.stamp_ns, expected.frame_id)
    assert np.array_equal(features.ids, expected.ids)
    assert np.array_equal(features.pixels, expected.pixels)
    assert covariances.shape == warps.shape == (count, 2, 2)
    assert np.array_equal(covariances, prediction_covariances(sent))
    assert np.array_equal(warps, prediction_warps(sent))
    # bytes of no message are refused as the features' are
    with pytest.raises(ValueError, match='features message of 5 bytes is not a '):
        predictions_from_cdr(serialize_message(sent)[:5], deserialize)


def deserialize(raw: bytes) -> FeatureTrackArray:
    return deserialize_message(raw, FeatureTrackArray)


def test_other_encodings_go_to_the_deserializer_and_bytes_of_no_message_are_refused() -> None:
    sent = message('camera', 5, seed=1)
    data = serialize_message(sent)
    calls: list[int] = []

    def counted(raw: bytes) -> FeatureTrackArray:
        calls.append(len(raw))
        return sent

    big_endian = features_from_cdr(b'\x00\x00' + data[2:], counted)  # left to the deserializer
    assert calls == [len(data)] and np.array_equal(big_endian.ids, [t.id for t in sent.tracks])
    for cut in (0, 3, 17, len(data) - 8):
        with pytest.raises(ValueError, match=rf'features message of {cut} bytes is not a '):
            features_from_cdr(data[:cut], deserialize)


def fields(array: FeatureTrackArray) -> tuple[object, ...]:
    tracks = [(t.id, t.u, t.v, list(t.covariance), list(t.warp)) for t in array.tracks]
    stamp = array.header.stamp
    return stamp.sec, stamp.nanosec, array.header.frame_id, tracks


@pytest.mark.parametrize('frame_id', ['', 'c', 'cam', 'came', 'camera_optical'])
@pytest.mark.parametrize('count', [0, 1, 5, 100])
@pytest.mark.parametrize('given', ['both', 'none', 'covariances'])
def test_serialized_predictions_are_the_filled_message(
    frame_id: str, count: int, given: str
) -> None:
    rng = np.random.default_rng(count)
    ids = rng.integers(0, 1 << 40, count)
    pixels = rng.normal(300.0, 200.0, size=(count, 2))
    covariances = rng.normal(size=(count, 2, 2)) if given != 'none' else None
    warps = rng.normal(size=(count, 2, 2)) if given == 'both' else None
    if count >= 5:  # left out, and zeros for what is not finite
        pixels[1, 0] = np.nan
        if covariances is not None:
            covariances[2, 0, 1] = np.inf
        if warps is not None:
            warps[3, 1, 1] = np.nan
    stamp_ns = 1_795_778_104_048_559_873
    data = predictions_cdr(ids, pixels, stamp_ns, frame_id, covariances, warps)
    filled = fill_predictions(
        ids, pixels, stamp_ns, frame_id, FeatureTrackArray(), FeatureTrack, covariances, warps
    )
    assert len(data) == len(serialize_message(filled))
    assert fields(deserialize_message(data, FeatureTrackArray)) == fields(filled)


def shadow_tracks(frame_id: str, count: int, seed: int) -> ShadowTrackArray:
    rng = np.random.default_rng(seed)
    tracks = [
        ShadowTrack(
            id=int(rng.integers(-5, 1 << 40)), status=int(rng.integers(0, 3)),
            position_covariance=rng.normal(size=9), velocity_covariance=rng.normal(size=9),
            test_statistic=float(rng.normal()), test_dof=int(rng.integers(0, 1 << 31)),
        )
        for _ in range(count)
    ]  # fmt: skip
    for track in tracks:
        track.position.x, track.velocity.z = rng.normal(size=2)
    out = ShadowTrackArray(tracks=tracks)
    out.header.frame_id = frame_id
    out.header.stamp.sec = int(rng.integers(0, 2**31 - 1))
    return out


def deserialize_shadow(raw: bytes) -> ShadowTrackArray:
    return deserialize_message(raw, ShadowTrackArray)


@pytest.mark.parametrize('frame_id', ['', 'c', 'cam', 'came', 'camera_optical'])
@pytest.mark.parametrize('count', [0, 1, 2, 150])
def test_serialized_shadow_tracks_give_the_dynamic_ids_of_the_message(
    frame_id: str, count: int
) -> None:
    sent = shadow_tracks(frame_id, count, seed=count)
    data = serialize_message(sent)
    assert dynamic_ids_from_cdr(data, deserialize_shadow) == dynamic_ids(sent)
    calls: list[int] = []

    def counted(raw: bytes) -> ShadowTrackArray:
        calls.append(len(raw))
        return sent

    big_endian = dynamic_ids_from_cdr(b'\x00\x00' + data[2:], counted)  # to the deserializer
    assert calls == [len(data)] and big_endian == dynamic_ids(sent)
    if count:
        with pytest.raises(
            ValueError, match=r'shadow tracks message of \d+ bytes is not a slam_interfaces/Sh'
        ):
            dynamic_ids_from_cdr(data[: len(data) - 8], deserialize_shadow)
