"""Messages <-> the feature tracker: predicted pixels, covariances and warps."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from monoslam_shadow_node.common.conversions import (
    CDR_ERRORS,
    cdr_features,
    deserialized,
    features_from_message,
    tracks_cdr,
)
from monoslam_shadow_node.common.core.inputs import Features
from slam_core.arrays import FloatArray


def predictions_from_cdr(
    data: bytes, deserialize: Callable[[bytes], Any]
) -> tuple[Features, FloatArray, FloatArray]:
    """Return a serialized FeatureTrackArray's predicted pixels, covariances (K, 2, 2) px^2
    and warps (K, 2, 2)."""
    try:
        stamp_ns, frame_id, tracks = tracks_cdr(data)
    except CDR_ERRORS:
        message = deserialized(data, deserialize)
        return (
            features_from_message(message),
            prediction_covariances(message),
            prediction_warps(message),
        )
    features = cdr_features(stamp_ns, frame_id, tracks)
    return features, _covariances_2x2(tracks['covariance']), tracks['warp'].reshape(-1, 2, 2)


def _covariances_2x2(upper: FloatArray) -> FloatArray:
    """Return the covariances (K, 2, 2) of FeatureTrack.covariance rows (K, 3) [uu, uv, vv]."""
    upper = np.asarray(upper, dtype=np.float64).reshape(-1, 3)
    covariances = np.empty((len(upper), 2, 2))
    covariances[:, 0, 0], covariances[:, 1, 1] = upper[:, 0], upper[:, 2]
    covariances[:, 0, 1] = covariances[:, 1, 0] = upper[:, 1]
    return covariances


def prediction_covariances(message: Any) -> FloatArray:
    """Return a FeatureTrackArray's prediction covariances (K, 2, 2) px^2 (zeros: none)."""
    return _covariances_2x2(
        np.array([list(track.covariance) for track in message.tracks], dtype=np.float64)
    )


def prediction_warps(message: Any) -> FloatArray:
    """Return a FeatureTrackArray's template warps (K, 2, 2), row-major (zeros: none)."""
    warps = np.array([list(track.warp) for track in message.tracks], dtype=np.float64)
    return warps.reshape(-1, 2, 2)
