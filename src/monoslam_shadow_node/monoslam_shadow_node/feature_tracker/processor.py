"""The feature_tracker's ROS-free processor: image order, camera_info, predictions and
bookkeeping around ``core.feature_tracker.FeatureTracker``.

Rules: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.conversions import FEATURE_TRACK_CDR, feature_array_cdr
from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.feature_tracker.core.feature_config import GrayImage, TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker, as_gray_image
from monoslam_shadow_node.feature_tracker.core.feature_types import (
    DROP_REASONS,
    Predictions,
    TrackedFeatures,
)
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel

PREDICTIONS_KEPT = 10
DROP_KINDS = ('out_of_order', 'repeated_stamp', 'size_mismatch', 'bad_image')
"""Why an image was dropped (``Notice.kind``; the node adds 'undecodable')."""


@dataclass(frozen=True, eq=False)
class FeatureFrame:
    """The features of one image, and whether a prediction for its stamp was used."""

    stamp_ns: int
    frame_id: str
    features: TrackedFeatures
    predicted: bool


Outcome = FeatureFrame | Notice


@dataclass(frozen=True)
class CameraInfoKey:
    """What the processor keeps of a camera_info: frame id, size px, K (9), D, model."""

    frame_id: str
    width: int
    height: int
    k: tuple[float, ...]
    d: tuple[float, ...]
    distortion_model: str

    def same_camera(self, other: CameraInfoKey) -> bool:
        """True when ``other`` has the same size, intrinsics and distortion."""
        return (self.width, self.height, self.k, self.d, self.distortion_model) == (
            other.width,
            other.height,
            other.k,
            other.d,
            other.distortion_model,
        )

    def describe(self) -> str:
        """Return a one-line summary for the log."""
        fx, cx, fy, cy = self.k[0], self.k[2], self.k[4], self.k[5]
        return (
            f'{self.width}x{self.height} px, fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}, '
            f'{self.distortion_model or "no distortion model"} d={list(self.d)}, '
            f'frame {self.frame_id!r}'
        )


@dataclass
class TrackingStats:
    """Running totals of images, features, tracks (dropped by reason), predictions (used,
    missed, late), re-identification and restarts."""

    frames: int = 0
    features: int = 0
    latest_features: int = 0
    started: int = 0
    predicted_tracks: int = 0
    searched: int = 0
    unsearched: int = 0
    unaligned: int = 0
    revived: int = 0
    images_dropped: dict[str, int] = field(default_factory=dict)
    tracks_dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(DROP_REASONS, 0))
    predictions_used: int = 0
    predictions_missed: int = 0
    predictions_late: int = 0
    restarts: int = 0
    camera_rejected: int = 0

    def count_frame(self, frame: FeatureFrame) -> None:
        """Add one tracked image."""
        counts = frame.features.counts
        self.frames += 1
        self.features += len(frame.features.ids)
        self.latest_features = len(frame.features.ids)
        self.started += counts.new
        self.predicted_tracks += counts.predicted
        self.searched += counts.searched
        self.unsearched += counts.unsearched
        self.unaligned += counts.unaligned
        self.revived += counts.revived
        for reason, count in counts.dropped_by_reason().items():
            self.tracks_dropped[reason] += count

    def count_drop(self, kind: str) -> None:
        """Add one dropped image."""
        self.images_dropped[kind] = self.images_dropped.get(kind, 0) + 1


@dataclass(frozen=True, eq=False)
class _Waiting:
    stamp_ns: int
    frame_id: str
    image: GrayImage
    since_s: float


class FeatureTrackingProcessor:
    """Feeds images to a FeatureTracker in stamp order."""

    def __init__(
        self,
        config: TrackerConfig,
        *,
        use_predictions: bool = False,
        prediction_timeout_s: float = 0.0,
        restart_backstep_ns: int = 1_000_000_000,
        camera_info_topic: str = 'camera/camera_info',
    ) -> None:
        if not (math.isfinite(prediction_timeout_s) and prediction_timeout_s >= 0.0):
            raise ValueError(f'prediction_timeout_s={prediction_timeout_s!r}: must be >= 0 s')
        if restart_backstep_ns <= 0:
            raise ValueError(f'restart_backstep_ns={restart_backstep_ns!r}: must be > 0 ns')
        self.tracker = FeatureTracker(config)
        self.use_predictions = use_predictions
        self.prediction_timeout_s = prediction_timeout_s
        self.restart_backstep_ns = restart_backstep_ns
        self.camera_info_topic = camera_info_topic
        self.camera: CameraInfoKey | None = None
        self.stats = TrackingStats()
        self._last_ns: int | None = None  # the last image taken (tracked or waiting)
        self._tracked_ns: int | None = None  # the last image tracked
        self._shape: tuple[int, ...] | None = None
        self._waiting: _Waiting | None = None
        self._predictions: dict[int, Predictions] = {}
        self._said_no_camera = False

    @property
    def waiting(self) -> bool:
        """True while an image waits for its prediction."""
        return self._waiting is not None

    # --- camera_info ------------------------------------------------------------------------

    def set_camera_info(
        self,
        *,
        frame_id: str,
        width: int,
        height: int,
        k: Sequence[float],
        d: Sequence[float],
        distortion_model: str,
    ) -> Notice | None:
        """Take a camera_info; return what to log (None: nothing changed)."""
        key = CameraInfoKey(frame_id, width, height, tuple(k), tuple(d), distortion_model)
        try:  # the one camera_info check of the suite, though tracking uses only the size
            CameraModel.from_camera_info(width, height, k, d, distortion_model)
        except ValueError as err:
            self.stats.camera_rejected += 1
            kept = 'previous camera kept' if self.camera else 'tracking goes on without one'
            return Notice(
                'camera_rejected',
                'error',
                f'{self.camera_info_topic} rejected ({err}); {kept}',
            )
        previous, self.camera = self.camera, key
        if previous is None:
            return Notice('camera', 'info', f'camera: {key.describe()}')
        if key.same_camera(previous):
            return None
        dropped = self.tracker.reset()
        self.stats.restarts += 1
        return Notice(
            'camera_changed',
            'warning',
            f'{self.camera_info_topic} changed: now {key.describe()} (was {previous.width}x'
            f'{previous.height} px, fx={previous.k[0]:g}); {dropped} tracks dropped, tracking '
            f'starts over with the next image (new ids from {self.tracker.next_id})',
        )

    # --- predictions ------------------------------------------------------------------------

    def add_predictions(
        self,
        stamp_ns: int,
        ids: IntArray,
        pixels: FloatArray,
        covariances: FloatArray | None = None,
        warps: FloatArray | None = None,
    ) -> list[Outcome]:
        """Take predicted pixels (K, 2), covariances (K, 2, 2) px^2 and warps (K, 2, 2) for the
        image at ``stamp_ns``; return the outcomes."""
        if not self.use_predictions:
            return []
        if self._tracked_ns is not None and stamp_ns <= self._tracked_ns:
            self.stats.predictions_late += 1
            return []
        self._predictions[stamp_ns] = Predictions(
            np.asarray(ids, np.int64).reshape(-1),
            np.asarray(pixels, np.float64).reshape(-1, 2),
            None if covariances is None else np.asarray(covariances, np.float64).reshape(-1, 2, 2),
            None if warps is None else np.asarray(warps, np.float64).reshape(-1, 2, 2),
        )
        while len(self._predictions) > PREDICTIONS_KEPT:
            del self._predictions[min(self._predictions)]
        waiting = self._waiting
        if waiting is not None and stamp_ns >= waiting.stamp_ns:
            return self._release()
        return []

    def poll(self, *, now_s: float) -> list[Outcome]:
        """Track the waiting image if its prediction is overdue; return the outcomes."""
        waiting = self._waiting
        if waiting is not None and now_s - waiting.since_s >= self.prediction_timeout_s:
            return self._release()
        return []

    # --- images -----------------------------------------------------------------------------

    def add_image(
        self, stamp_ns: int, frame_id: str, image: object, *, now_s: float
    ) -> list[Outcome]:
        """Take a decoded gray image (H, W) uint8 taken at ``stamp_ns``; return the outcomes."""
        outcomes: list[Outcome] = []
        if self.camera is None and not self._said_no_camera:
            self._said_no_camera = True
            outcomes.append(
                Notice(
                    'no_camera_info',
                    'warning',
                    f'no {self.camera_info_topic} received yet: tracking without it (it is '
                    'only needed to check the image size and to notice camera changes)',
                    stamp_ns,
                )
            )
        try:
            gray = as_gray_image(image)
        except ValueError as err:
            text = f'image at stamp {stamp_ns} ns dropped: {err}'
            return [*outcomes, self._drop('bad_image', 'error', stamp_ns, text)]
        height, width = gray.shape
        camera = self.camera
        if camera is not None and (width, height) != (camera.width, camera.height):
            return [*outcomes, self._drop(
                'size_mismatch', 'error', stamp_ns,
                f'image at stamp {stamp_ns} ns dropped: it is {width}x{height} px but '
                f'{self.camera_info_topic} says {camera.width}x{camera.height} px',
            )]  # fmt: skip
        if self._last_ns is not None and stamp_ns <= self._last_ns:
            if self._last_ns - stamp_ns < self.restart_backstep_ns:
                repeated = stamp_ns == self._last_ns
                return [*outcomes, self._drop(
                    'repeated_stamp' if repeated else 'out_of_order', 'warning', stamp_ns,
                    f'image at stamp {stamp_ns} ns dropped: it '
                    f'{"has the same stamp as" if repeated else "is older than"} the image '
                    f'before it ({self._last_ns} ns); images must come in stamp order',
                )]  # fmt: skip
            outcomes += self._release()
            outcomes.append(self._restart(stamp_ns))
        else:
            outcomes += self._release()
        self._last_ns = stamp_ns
        frame_id = frame_id or (camera.frame_id if camera is not None else '')
        if (
            self.use_predictions
            and self.prediction_timeout_s > 0.0
            and stamp_ns not in self._predictions
        ):
            self._waiting = _Waiting(stamp_ns, frame_id, gray, now_s)
            return outcomes
        return outcomes + self._track(stamp_ns, frame_id, gray)

    def flush(self) -> list[Outcome]:
        """Track the waiting image now, if any (e.g. when the input ends)."""
        return self._release()

    def _release(self) -> list[Outcome]:
        waiting, self._waiting = self._waiting, None
        if waiting is None:
            return []
        return self._track(waiting.stamp_ns, waiting.frame_id, waiting.image)

    def _restart(self, stamp_ns: int) -> Notice:
        dropped = self.tracker.reset()
        self.stats.restarts += 1
        self._predictions.clear()
        self._tracked_ns = None
        return Notice(
            'restart',
            'warning',
            f'image stamps jumped back from {self._last_ns} ns to {stamp_ns} ns (at least '
            f'{self.restart_backstep_ns / 1e9:g} s): the source restarted; {dropped} tracks '
            f'dropped, tracking starts over (new ids from {self.tracker.next_id})',
            stamp_ns,
        )

    def _track(self, stamp_ns: int, frame_id: str, image: GrayImage) -> list[Outcome]:
        outcomes: list[Outcome] = []
        predictions = self._predictions.pop(stamp_ns, None)
        for old in [s for s in self._predictions if s < stamp_ns]:
            del self._predictions[old]
        if self.use_predictions:
            if predictions is None:
                self.stats.predictions_missed += 1
            else:
                self.stats.predictions_used += 1
        shape = image.shape
        features = self.tracker.track(image, predictions)
        if self._shape is not None and shape != self._shape and self.camera is None:
            outcomes.append(
                Notice(
                    'image_size_changed',
                    'warning',
                    f'image at stamp {stamp_ns} ns is {shape[1]}x{shape[0]} px, the image '
                    f'before was {self._shape[1]}x{self._shape[0]} px: tracking started over',
                    stamp_ns,
                )
            )
        self._shape = shape
        self._tracked_ns = stamp_ns
        frame = FeatureFrame(stamp_ns, frame_id, features, predictions is not None)
        self.stats.count_frame(frame)
        outcomes.append(frame)
        return outcomes

    def _drop(self, kind: str, level: str, stamp_ns: int, text: str) -> Notice:
        self.stats.count_drop(kind)
        return Notice(kind, level, text, stamp_ns)


def status_line(stats: TrackingStats, rate_hz: float | None = None) -> str:
    """Return a one-line summary of ``stats`` for the log (``rate_hz``: images per second)."""
    rate = f' ({rate_hz:.1f}/s)' if rate_hz is not None else ''
    mean = stats.features / stats.frames if stats.frames else 0.0
    dropped = ', '.join(
        f'{reason.replace("_", "-")} {count}'
        for reason, count in stats.tracks_dropped.items()
        if count
    )
    images = ', '.join(
        f'{kind.replace("_", " ")} {count}' for kind, count in stats.images_dropped.items()
    )
    text = (
        f'{stats.frames} images tracked{rate}, {stats.latest_features} features in the latest '
        f'(mean {mean:.1f}); {stats.started} tracks started, dropped: {dropped or "none"}; '
        f'images dropped: {images or "none"}; {stats.restarts} restarts'
    )
    if stats.predictions_used or stats.predictions_missed or stats.predictions_late:
        text += (
            f'; predictions used for {stats.predictions_used} images ({stats.predicted_tracks} '
            f'tracks), missing for {stats.predictions_missed}, {stats.predictions_late} late'
        )
    if stats.searched or stats.unsearched:
        text += (
            f'; {stats.revived} dropped tracks re-identified of {stats.searched} searched '
            f'({stats.unsearched} too uncertain to search, {stats.unaligned} candidates left '
            'unaligned for time)'
        )
    return text


def feature_frame_cdr(frame: FeatureFrame) -> bytes:
    """Return ``frame`` as a serialized FeatureTrackArray (id, u, v per finite feature)."""
    ids, pixels = frame.features.ids, frame.features.pixels
    finite = np.all(np.isfinite(pixels), axis=1)
    tracks = np.zeros(int(np.count_nonzero(finite)), FEATURE_TRACK_CDR)
    tracks['id'], tracks['u'], tracks['v'] = ids[finite], pixels[finite, 0], pixels[finite, 1]
    return feature_array_cdr(tracks, frame.stamp_ns, frame.frame_id)
