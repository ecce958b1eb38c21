"""monoslam_image_evaluate: paper 001's Fig. 5 from rendered images, against the measurement
level (issue 7: the full pipeline from images reaches (c) within 1.5x of its
measurement-level ATE).

    monoslam_image_evaluate --out out/monoslam_image_eval [--seeds 0-9] [--duration-s 20]
    monoslam_image_evaluate --out out/bag_eval --bag bags/dynamic_camera.mcap [more bags]
                            [--shadow-max-pose-sigma 0.03,0.01] [--unchecked-directions 1]

Sources. Without ``--bag`` every seed renders monoslam_evaluate's Fig. 5 scene (its
``Settings.scene()``: 8 moving objects, drawn as textured spheres by
``slam_sim.core.dynamic_render``) frame by frame. Each ``--bag`` is one run written by
``dynamic_camera_sim``: its images, camera_info, true camera pose, labels, true target
corners and scene JSON (seed, scene config and target); every bag's topics, scene and first
camera_info are read before the work starts.

Front end (``FrontEnd``, the same for every variant): the feature tracker
(``core.feature_tracker``, the node's defaults, no predictions: one set of tracks feeds all
variants) and the marker detector (``marker_detector.core.detection``, the node's defaults,
only the target's id and side) on each image give ``MonoSlamFrame``: track ids with raw
pixels, and the known points 0-3 (the detected corners, TL TR BR BL as
``target_known_points``) when the target is detected. Truth: the camera pose of the image,
and per feature whether it is on a moving object: a feature is moving if a label within
``MOVING_RADIUS_PX`` pixels (a square window about its rounded pixel) is a moving object, so
that features on object silhouettes (corners made by an object and what lies behind it)
count as moving; once moving, a track stays moving (a static track that an object passes over
is dragged along or lost). Pixels labelled 'nothing' (no surface: only beyond the lens
model's fold, never inside the closed room in practice) count as not moving; how many
features sit on one is reported.

Runs per seed: variants a, b and c (``monoslam_pipeline.run_variant``) on the image-level
frames, and variant c on the measurement-level frames of the same seed, scene config and
target (``simulation_frames``, target noise from ``default_rng(1000 + seed)`` as
monoslam_evaluate). Metrics are monoslam_evaluate's (ATE raw and sim(3)-aligned, divergence);
the ratio is image c / measurement c per seed, and the acceptance is the ratio of the means
over seeds (raw ATE) <= ``IMAGE_OVER_MEASUREMENT_MAX``. Front-end figures: features per
frame, the share of features (and of tracks) on moving objects, the target detection rate
(frames detected among those in which the target is fully visible and unoccluded) and the
detected corners' error against the true ones (px).

Writes ``monoslam_image_eval.json``, the table as ``monoslam_image_eval.md`` and PNG figures
(top views of the trajectories, image and measurement level; position error over time) into
``--out`` (atomically), prints the table, and logs progress on stderr (images through the
front end, with rate and ETA: rendering, tracking and detection take most of the time; the
four filter runs follow each seed's images) and a line per seed. A run a filter raises on is
listed under ``failures`` and makes the exit status 1.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from marker_detector.conversions import camera_info_fields, image_from_message
from marker_detector.core.detection import DetectorConfig, detect_markers, make_detector
from marker_detector.core.images import ImageError
from monoslam_shadow_node import monoslam_evaluate
from monoslam_shadow_node.conversions import rotation_from_quaternion
from monoslam_shadow_node.core.feature_tracker import FeatureTracker, TrackerConfig
from monoslam_shadow_node.core.monoslam import MonoSlamFrame
from monoslam_shadow_node.evaluate import parse_seeds
from monoslam_shadow_node.evaluation_report import render_png
from monoslam_shadow_node.monoslam_evaluate import (
    finite_mean,
    number_text,
    pose_errors,
    ratio_summary,
    safe_ratio,
    shadow_numbers,
    trajectory_metrics,
)
from monoslam_shadow_node.monoslam_pipeline import (
    DEFAULT_SHADOW_MAX_POSE_SIGMA,
    VARIANTS,
    MeasurementFrame,
    PipelineConfig,
    PipelineError,
    VariantRecord,
    parse_pose_gate,
    run_variant,
    simulation_frames,
)
from slam_core.blas import single_threaded_blas
from slam_core.camera import CameraModel
from slam_core.cli import console_main
from slam_core.errors import BagError
from slam_core.files import write_atomically, write_json
from slam_core.progress import ProgressReporter
from slam_core.stamps import stamp_to_ns
from slam_ros.bag.source import BagSource
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_render import LABEL_NOTHING, DynamicRenderer
from slam_sim.core.dynamic_scene import DEFAULT_START_NS, simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget
from slam_sim.dynamic_camera_bag import (
    CAMERA_POSE_TOPIC,
    LABELS_TOPIC,
    RAW_IMAGE_TOPIC,
    SCENE_TOPIC,
    scene_from_json,
)
from slam_sim.office_camera_bag import CAMERA_INFO_TOPIC, IMAGE_TOPIC, TRUE_FIDUCIALS_TOPIC

PROG = 'monoslam_image_evaluate'
FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
MOVING_RADIUS_PX = 3
"""A feature with a moving object's label this close (square window, px) is moving."""
IMAGE_OVER_MEASUREMENT_MAX = 1.5
REPORT_NAME = 'monoslam_image_eval.json'
TABLE_NAME = 'monoslam_image_eval.md'
RUNS = (*(('image', v) for v in VARIANTS), ('measurement', 'c'))
"""The filter runs per seed: (level, variant)."""


# --- sources of images ----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImageFrame:
    """One camera image with its truth: stamp int ns, the raw grey image (H, W) uint8, labels
    (H, W) int16 (``dynamic_render``'s: -2 nothing, -1 static, i >= 0 moving object i),
    R_world_camera (3, 3), optical centre (3,) m in map, and the target's true raw corners
    (4, 2) px when it is fully visible and unoccluded (else None)."""

    stamp_ns: int
    image: NDArray[np.uint8]
    labels: NDArray[np.int16]
    rotation: FloatArray
    centre_m: FloatArray
    target_corners_px: FloatArray | None


@dataclass(frozen=True, eq=False)
class FrameSource:
    """One run to evaluate: seed, scene config, target and camera (CameraInfo model), the
    bag it is read from (None: rendered) and its number of images."""

    seed: int
    config: DynamicSceneConfig
    target: InitTarget
    camera: CameraModel
    bag: Path | None
    frame_count: int

    @property
    def name(self) -> str:
        """'rendered' or the bag's path."""
        return 'rendered' if self.bag is None else str(self.bag)

    def frames(self) -> Iterator[ImageFrame]:
        """Yield the run's images with their truth, in stamp order."""
        return rendered_frames(self) if self.bag is None else bag_frames(self.bag, self.target)


def rendered_source(seed: int, config: DynamicSceneConfig) -> FrameSource:
    """Return the source that renders ``seed``'s run of ``config`` with the default target."""
    info = config.camera().camera_info()
    camera = CameraModel.from_camera_info(
        info.width, info.height, info.k, info.d, info.distortion_model
    )
    return FrameSource(seed, config, InitTarget(), camera, None, config.frame_count)


def rendered_frames(source: FrameSource) -> Iterator[ImageFrame]:
    """Yield the rendered frames of a source (frame k at DEFAULT_START_NS + k / rate)."""
    renderer = DynamicRenderer(source.config, source.seed, target=source.target)
    for index in range(source.frame_count):
        frame = renderer.render(index)
        yield ImageFrame(
            DEFAULT_START_NS + round(index * 1e9 / source.config.rate_hz),
            frame.image,
            frame.labels,
            frame.rotation,
            frame.position_m,
            frame.target_corners_px,
        )


def _image_topic(path: Path, topics: Mapping[str, Any]) -> str:
    """Return the bag's image topic; BagError naming the bag and the topics it lacks."""
    required = (SCENE_TOPIC, CAMERA_INFO_TOPIC, CAMERA_POSE_TOPIC, LABELS_TOPIC)
    missing = [topic for topic in required if topic not in topics]
    image = next((t for t in (IMAGE_TOPIC, RAW_IMAGE_TOPIC) if t in topics), None)
    if image is None:
        missing.append(f'{IMAGE_TOPIC} or {RAW_IMAGE_TOPIC}')
    if missing:
        raise BagError(
            f'bag {str(path)!r} is not a dynamic_camera_sim bag: no {", ".join(missing)} '
            '(write one with dynamic_camera_sim)'
        )
    return str(image)


def _target(path: Path, text: str) -> InitTarget:
    """Return the target described in a scene JSON's 'target' entry."""
    try:
        entry = json.loads(text)['target']
        return InitTarget(
            marker_id=int(entry['marker_id']),
            side_m=float(entry['side_m']),
            centre_m=np.asarray(entry['centre_m'], dtype=np.float64),
            rotation=np.asarray(entry['rotation'], dtype=np.float64),
            dictionary=str(entry['dictionary']),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise BagError(f'bag {str(path)!r}: {SCENE_TOPIC} has no usable target: {err}') from None


def bag_source(path: Path) -> FrameSource:
    """Return the source of a dynamic_camera_sim bag (seed, config and target from its scene
    JSON, camera from its first camera_info). Raises BagError naming the bag if it is
    missing, corrupt or lacks a topic."""
    with BagSource(path) as bag:
        topics = bag.topics()
        image_topic = _image_topic(path, topics)
        first: dict[str, Any] = {}
        for message in bag.messages([SCENE_TOPIC, CAMERA_INFO_TOPIC]):
            first.setdefault(
                message.topic, bag.typestore.deserialize_cdr(message.data, message.msgtype)
            )
            if len(first) == 2:
                break
    if len(first) < 2:
        absent = [t for t in (SCENE_TOPIC, CAMERA_INFO_TOPIC) if t not in first]
        raise BagError(f'bag {str(path)!r}: no message on {", ".join(absent)}')
    text = str(first[SCENE_TOPIC].data)
    info = camera_info_fields(first[CAMERA_INFO_TOPIC])
    del info['frame_id']
    try:
        seed, config = scene_from_json(text)
        camera = CameraModel.from_camera_info(**info)
    except ValueError as err:
        raise BagError(f'bag {str(path)!r}: {err}') from None
    return FrameSource(seed, config, _target(path, text), camera, path, topics[image_topic].count)


def bag_frames(path: Path, target: InitTarget) -> Iterator[ImageFrame]:
    """Yield a dynamic_camera_sim bag's images with their truth, in stamp order. Raises
    BagError naming the bag, topic and stamp of a message that is missing or undecodable."""
    with BagSource(path) as bag:
        image_topic = _image_topic(path, bag.topics())
        wanted = (image_topic, CAMERA_POSE_TOPIC, LABELS_TOPIC, TRUE_FIDUCIALS_TOPIC)
        parts: dict[str, Any] = {}
        stamp_ns: int | None = None
        for message in bag.messages(wanted):
            if stamp_ns is not None and message.timestamp_ns != stamp_ns:
                yield _bag_frame(path, stamp_ns, parts, image_topic, target)
                parts = {}
            stamp_ns = message.timestamp_ns
            parts[message.topic] = bag.typestore.deserialize_cdr(message.data, message.msgtype)
        if stamp_ns is not None:
            yield _bag_frame(path, stamp_ns, parts, image_topic, target)


def _bag_frame(
    path: Path, stamp_ns: int, parts: Mapping[str, Any], image_topic: str, target: InitTarget
) -> ImageFrame:
    """Return the frame of one stamp's messages (image, pose, labels, true fiducials)."""
    missing = [t for t in (image_topic, CAMERA_POSE_TOPIC, LABELS_TOPIC) if t not in parts]
    if missing:
        raise BagError(f'bag {str(path)!r}: no {", ".join(missing)} at stamp {stamp_ns} ns')
    try:
        image = image_from_message(parts[image_topic])
        labels = image_from_message(parts[LABELS_TOPIC]).astype(np.int16) + LABEL_NOTHING
    except ImageError as err:
        raise BagError(f'bag {str(path)!r}: at stamp {stamp_ns} ns: {err}') from None
    pose = parts[CAMERA_POSE_TOPIC].pose
    q, p = pose.orientation, pose.position
    corners = None
    for detection in getattr(parts.get(TRUE_FIDUCIALS_TOPIC), 'detections', []):
        if int(detection.id) == target.marker_id:
            corners = np.asarray(detection.corners_px, dtype=np.float64).reshape(4, 2)
    return ImageFrame(
        stamp_to_ns(parts[image_topic].header.stamp),
        image,
        labels,
        rotation_from_quaternion(q.x, q.y, q.z, q.w),
        np.array([p.x, p.y, p.z], dtype=np.float64),
        corners,
    )


# --- front end: tracker, marker detector, truth ---------------------------------------------


def moving_near(labels: NDArray[np.int16], pixels: FloatArray, radius_px: int) -> BoolArray:
    """Return (N,) whether a moving object's label (>= 0) lies within ``radius_px`` (square
    window, clipped at the image border) of each raw pixel (N, 2), rounded."""
    height, width = labels.shape
    centre = np.rint(np.asarray(pixels, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    offsets = np.arange(-radius_px, radius_px + 1)
    cols = np.clip(centre[:, 0, None, None] + offsets[None, None, :], 0, width - 1)
    rows = np.clip(centre[:, 1, None, None] + offsets[None, :, None], 0, height - 1)
    return np.asarray(np.any(labels[rows, cols] >= 0, axis=(1, 2)), dtype=bool)


@dataclass
class FrontEndStats:
    """Running counts of the front end: frames, features, features flagged moving, on a
    moving object's label at their own pixel, on 'nothing'; tracks started and flagged
    moving; frames with the target fully visible (truth), detected, both; and the detected
    corners' errors against the truth (px, 4 per frame with both)."""

    frames: int = 0
    features: int = 0
    moving: int = 0
    on_moving_label: int = 0
    on_nothing: int = 0
    tracks: int = 0
    moving_tracks: int = 0
    target_visible: int = 0
    target_detected: int = 0
    detected_and_visible: int = 0
    corner_errors_px: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """Return the counts with the derived shares and corner error statistics."""
        errors = np.array(self.corner_errors_px)
        counts = {k: v for k, v in asdict(self).items() if k != 'corner_errors_px'}
        return {
            **counts,
            'features_per_frame': safe_ratio(self.features, self.frames),
            'moving_share': safe_ratio(self.moving, self.features),
            'moving_track_share': safe_ratio(self.moving_tracks, self.tracks),
            'detection_rate': safe_ratio(self.detected_and_visible, self.target_visible),
            'detected_not_visible': self.target_detected - self.detected_and_visible,
            'corner_rms_px': float(np.sqrt(np.mean(errors**2))) if len(errors) else math.nan,
            'corner_max_px': float(errors.max()) if len(errors) else math.nan,
        }


class FrontEnd:
    """Turns images into SLAM frames with their truth (module docstring): the feature tracker,
    the marker detector on the target, and the moving flags from the labels."""

    def __init__(self, camera: CameraModel, target: InitTarget) -> None:
        self.camera, self.target = camera, target
        self.tracker = FeatureTracker(TrackerConfig())
        self.detector_config = DetectorConfig(
            dictionary=target.dictionary,
            default_marker_size_m=target.side_m,
            allowed_ids=(target.marker_id,),
        )
        self._detector = make_detector(self.detector_config)
        self._moving_ids: set[int] = set()
        self.stats = FrontEndStats()

    def frame(self, image_frame: ImageFrame) -> MeasurementFrame:
        """Return the measurements of one image (tracks; the target's corners as known points
        0-3 if detected) and its truth (moving flags, camera pose)."""
        features = self.tracker.track(image_frame.image)
        ids, pixels = features.ids, features.pixels
        moving = self._moving(image_frame.labels, ids, pixels)
        corners = self._detect(image_frame)
        keys = np.arange(4 if corners is not None else 0, dtype=np.int64)
        known = corners if corners is not None else np.zeros((0, 2))
        stats = self.stats
        stats.frames += 1
        stats.features += len(ids)
        stats.moving += int(moving.sum())
        stats.tracks = self.tracker.next_id - 1
        stats.moving_tracks = len(self._moving_ids)
        return MeasurementFrame(
            MonoSlamFrame(image_frame.stamp_ns, ids, pixels, keys, known),
            moving,
            image_frame.rotation,
            image_frame.centre_m,
        )

    def _moving(
        self, labels: NDArray[np.int16], ids: NDArray[np.int64], pixels: FloatArray
    ) -> BoolArray:
        """Return the features' moving flags (window rule, sticky per track); count labels."""
        near = moving_near(labels, pixels, MOVING_RADIUS_PX)
        self._moving_ids.update(ids[near].tolist())
        moving = near | np.isin(ids, list(self._moving_ids))
        height, width = labels.shape
        rounded = np.clip(np.rint(pixels).astype(np.int64), 0, [width - 1, height - 1])
        own = labels[rounded[:, 1], rounded[:, 0]]
        self.stats.on_moving_label += int(np.count_nonzero(own >= 0))
        self.stats.on_nothing += int(np.count_nonzero(own == LABEL_NOTHING))
        return np.asarray(moving, dtype=bool)

    def _detect(self, image_frame: ImageFrame) -> FloatArray | None:
        """Return the target's detected raw corners (4, 2) px (None if not detected) and
        count the detection against the truth."""
        result = detect_markers(
            image_frame.image, self.camera, self.detector_config, self._detector
        )
        found = [d for d in result.detections if d.id == self.target.marker_id]
        corners = np.asarray(found[0].corners_px, dtype=np.float64) if found else None
        truth = image_frame.target_corners_px
        stats = self.stats
        stats.target_visible += truth is not None
        stats.target_detected += corners is not None
        if corners is not None and truth is not None:
            stats.detected_and_visible += 1
            stats.corner_errors_px += np.linalg.norm(corners - truth, axis=1).tolist()
        return corners


# --- running --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Settings:
    """The command line: the runs (sources), monoslam_evaluate's settings (the filters'
    settings ``pipeline``; ``scene`` is the rendered Fig. 5 scene) and the output directory."""

    sources: tuple[FrameSource, ...]
    evaluation: monoslam_evaluate.Settings
    out: Path

    def pipeline(self, target: InitTarget) -> PipelineConfig:
        """Return the filters' settings of both levels for ``target``."""
        return self.evaluation.pipeline(target)


@dataclass(eq=False)
class SeedResult:
    """One run's report entry, its front-end counts, and per filter run ('image a', ...,
    'measurement c') the position error (K,) m and estimated centres (K, 3) m; the true
    centres (K, 3) m, for the figures."""

    entry: dict[str, Any]
    front_end: FrontEndStats
    errors: dict[str, FloatArray] = field(default_factory=dict)
    centres: dict[str, FloatArray] = field(default_factory=dict)
    truth: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))


def measurement_frames(source: FrameSource) -> list[MeasurementFrame]:
    """Return the measurement-level frames of the source's seed, scene config and target
    (target noise from default_rng(1000 + seed), as monoslam_evaluate)."""
    run = simulate_dynamic_scene(source.seed, source.config)
    rng = np.random.default_rng(monoslam_evaluate.TARGET_NOISE_SEED_OFFSET + source.seed)
    return simulation_frames(run, source.target, rng=rng)


def run_metrics(record: VariantRecord, errors: FloatArray) -> dict[str, Any]:
    """Return a filter run's metrics from its pose errors (K, 6) (``pose_errors``):
    monoslam_evaluate's trajectory metrics, map size, moving features that entered the map,
    filter time; the Shadow numbers of variant c."""
    metrics = {
        **trajectory_metrics(record, errors),
        'map_points': len(record.map_points),
        'dynamic_entered_map': len(record.dynamic_in_map),
        'ms_per_frame': 1e3 * record.runtime_s / max(len(errors), 1),
    }
    if record.variant == 'c':
        metrics['shadow'] = shadow_numbers(record)
    return metrics


def evaluate_source(
    source: FrameSource, settings: Settings, advance: Callable[[], None]
) -> SeedResult:
    """Build the image-level frames of a source, run every filter (``RUNS``) and return the
    result; ``advance()`` after each image."""
    front_end = FrontEnd(source.camera, source.target)
    frames = []
    for image_frame in source.frames():
        frames.append(front_end.frame(image_frame))
        advance()
    entry: dict[str, Any] = {'seed': source.seed, 'source': source.name, 'frames': len(frames)}
    entry['front_end'] = front_end.stats.summary()
    result = SeedResult(entry, front_end.stats)
    result.truth = np.array([f.true_centre for f in frames]).reshape(-1, 3)
    levels = {'image': frames, 'measurement': measurement_frames(source)}
    pipeline = settings.pipeline(source.target)
    for level, variant in RUNS:
        try:
            record = run_variant(variant, levels[level], source.camera, pipeline)
        except PipelineError as error:
            failure = {'seed': source.seed, 'level': level, 'variant': variant}
            entry.setdefault('failures', []).append({**failure, 'error': str(error)})
            traceback.print_exception(error, file=sys.stderr)
            continue
        errors = pose_errors(record, levels[level])
        entry.setdefault(level, {})[variant] = run_metrics(record, errors)
        result.errors[f'{level} {variant}'] = np.linalg.norm(errors[:, :3], axis=1)
        result.centres[f'{level} {variant}'] = record.centres
    entry['ratio_c'] = {key: _level_ratio_of(entry, key) for key in ('ate_m', 'ate_sim3_m')}
    return result


def _level_ratio_of(entry: Mapping[str, Any], key: str) -> float:
    image, measurement = entry.get('image', {}).get('c'), entry.get('measurement', {}).get('c')
    if image is None or measurement is None:
        return math.nan
    return safe_ratio(image[key], measurement[key])


def _seed_line(result: SeedResult) -> str:
    """Return one line about a finished seed, for the log."""
    entry = result.entry
    ate = {
        name: entry.get(level, {}).get(variant, {}).get('ate_m', math.nan)
        for name, (level, variant) in zip(('a', 'b', 'c', 'meas'), RUNS, strict=True)
    }
    front = entry['front_end']
    return (
        f'{PROG}: seed {entry["seed"]} ({entry["source"]}): ATE image a {ate["a"]:.3f}, '
        f'b {ate["b"]:.3f}, c {ate["c"]:.3f} m; measurement c {ate["meas"]:.3f} m; ratio '
        f'{entry["ratio_c"]["ate_m"]:.2f}; {front["features_per_frame"]:.0f} features/frame, '
        f'target detected in {100 * front["detection_rate"]:.0f} % of its frames'
    )


# --- report ---------------------------------------------------------------------------------


def run_totals(runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Return one filter run's aggregates over seeds (means over finite values)."""
    totals: dict[str, Any] = {'seeds': len(runs)}
    for key in ('ate_m', 'ate_sim3_m', 'sim3_scale', 'ms_per_frame'):
        totals[f'{key}_mean'] = finite_mean([run[key] for run in runs])
    totals['diverged'] = sum(run['diverged'] for run in runs)
    totals['dynamic_entered_map'] = sum(run['dynamic_entered_map'] for run in runs)
    if runs and 'shadow' in runs[0]:
        totals['shadow'] = {k: sum(run['shadow'][k] for run in runs) for k in runs[0]['shadow']}
    return totals


def _runs(per_seed: Sequence[Mapping[str, Any]], level: str, variant: str) -> list[dict[str, Any]]:
    """Return a filter run's metrics per seed, each with its seed."""
    return [
        {'seed': entry['seed'], **entry[level][variant]}
        for entry in per_seed
        if variant in entry.get(level, {})
    ]


def level_ratio(per_seed: Sequence[Mapping[str, Any]], key: str) -> dict[str, Any] | None:
    """Return mean ``key`` of image c / mean of measurement c over the seeds both ran, and
    per seed."""
    return ratio_summary(_runs(per_seed, 'image', 'c'), _runs(per_seed, 'measurement', 'c'), key)


def acceptance(ratio: Mapping[str, Any] | None) -> dict[str, Any]:
    """Return the acceptance point: mean ATE(c) images / mean ATE(c) measurements."""
    seeds = ratio['per_seed'] if ratio is not None else []
    value = ratio['ratio_of_means'] if ratio is not None else math.nan
    meeting = [r['ratio'] <= IMAGE_OVER_MEASUREMENT_MAX for r in seeds]
    return {
        'name': 'ATE(c) images / ATE(c) measurements',
        'target': f'<= {IMAGE_OVER_MEASUREMENT_MAX:g}',
        'value': value,
        'seeds_meeting': f'{sum(meeting)}/{len(meeting)}',
        'passed': bool(math.isfinite(value) and value <= IMAGE_OVER_MEASUREMENT_MAX),
    }


def _pooled(results: Sequence[SeedResult]) -> FrontEndStats:
    pooled = FrontEndStats()
    for result in results:
        for name, value in asdict(result.front_end).items():
            setattr(pooled, name, getattr(pooled, name) + value)
    return pooled


def error_curves(results: Sequence[SeedResult]) -> dict[str, FloatArray]:
    """Return per filter run the position errors (S, K) m over seeds, NaN-padded to the
    longest run (NaN: no estimate)."""
    length = max((len(r.truth) for r in results), default=0)
    curves = {}
    for level, variant in RUNS:
        name = f'{level} {variant}'
        rows = np.full((len(results), length), np.nan)
        for row, result in zip(rows, results, strict=True):
            if name in result.errors:
                row[: len(result.errors[name])] = result.errors[name]
        curves[name] = rows
    return curves


def rms_over_seeds(values: FloatArray) -> FloatArray:
    """Return per frame (K,) the RMS over seeds of values (S, K) (NaN where none is finite)."""
    finite = np.isfinite(values)
    counts = finite.sum(axis=0)
    sums = np.where(finite, values**2, 0.0).sum(axis=0)
    return np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)


def report(settings: Settings, results: Sequence[SeedResult], wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, per seed entries, totals, ratios, acceptance,
    RMS error curves, failures and run time."""
    per_seed = [result.entry for result in results]
    target = settings.sources[0].target if settings.sources else InitTarget()
    totals: dict[str, Any] = {
        level: {v: run_totals(_runs(per_seed, level, v)) for lv, v in RUNS if lv == level}
        for level in ('image', 'measurement')
    }
    totals['front_end'] = _pooled(results).summary()
    ratios = {key: level_ratio(per_seed, key) for key in ('ate_m', 'ate_sim3_m')}
    curves = {name: rms_over_seeds(values) for name, values in error_curves(results).items()}
    rate = settings.sources[0].config.rate_hz if settings.sources else math.nan
    return {
        'config': {
            'sources': [
                {
                    'seed': s.seed,
                    'source': s.name,
                    'frames': s.frame_count,
                    'scene': asdict(s.config),
                }
                for s in settings.sources
            ],
            'pipeline': asdict(settings.pipeline(target)),
            'tracker': asdict(TrackerConfig()),
            'moving_radius_px': MOVING_RADIUS_PX,
            'target_noise_seed': f'{monoslam_evaluate.TARGET_NOISE_SEED_OFFSET} + seed',
        },
        'per_seed': per_seed,
        'totals': totals,
        'ratio_c': ratios['ate_m'],
        'ratio_c_sim3': ratios['ate_sim3_m'],
        'acceptance': acceptance(ratios['ate_m']),
        'curves': {'rate_hz': rate, **{f'{name} rms_m': v for name, v in curves.items()}},
        'failures': [f for entry in per_seed for f in entry.get('failures', [])],
        'runtime': {'wall_s': wall_s},
    }


# --- table and figures ----------------------------------------------------------------------


def _ate_cell(run: Mapping[str, Any] | None, key: str) -> str:
    if run is None:
        return 'failed'
    return number_text(run[key]) + ('*' if run['diverged'] else '')


TABLE_HEADER = (
    'seed', 'a ATE', 'b ATE', 'c ATE', 'meas. c ATE', 'c img/meas', 'a sim3', 'b sim3',
    'c sim3', 'meas. c sim3', 'features/frame', 'moving %', 'target det. %', 'corner rms px',
)  # fmt: skip
"""The table's columns: ATE raw (m) of image a, b, c and measurement c, the ratio, ATE after
the sim(3) alignment (m), and the front end."""


def _front_cells(front: Mapping[str, Any]) -> list[str]:
    return [
        number_text(front['features_per_frame'], 0),
        number_text(100.0 * front['moving_share'], 1),
        number_text(100.0 * front['detection_rate'], 1),
        number_text(front['corner_rms_px'], 2),
    ]


def _seed_cells(entry: Mapping[str, Any]) -> list[str]:
    runs = [entry.get(level, {}).get(variant) for level, variant in RUNS]
    return [
        str(entry['seed']),
        *(_ate_cell(run, 'ate_m') for run in runs),
        number_text(entry['ratio_c']['ate_m'], 2),
        *(_ate_cell(run, 'ate_sim3_m') for run in runs),
        *_front_cells(entry['front_end']),
    ]


def _mean_cells(content: Mapping[str, Any]) -> list[str]:
    totals = content['totals']
    runs = [totals[level][variant] for level, variant in RUNS]
    ratio = content['ratio_c']
    return [
        'mean',
        *(number_text(run['ate_m_mean']) for run in runs),
        number_text(ratio['ratio_of_means'] if ratio else None, 2),
        *(number_text(run['ate_sim3_m_mean']) for run in runs),
        *_front_cells(totals['front_end']),
    ]


def table_text(content: Mapping[str, Any]) -> str:
    """Return the markdown table of a report (a row per seed and the means) with the
    acceptance verdict, the Shadow numbers of image c and the failed runs."""
    rows = [list(TABLE_HEADER), ['---'] * len(TABLE_HEADER)]
    rows += [_seed_cells(entry) for entry in content['per_seed']]
    rows.append(_mean_cells(content))
    lines = ['| ' + ' | '.join(row) + ' |' for row in rows]
    point = content['acceptance']
    lines += [
        '',
        'ATE in m (raw: the target fixes the scale; sim3: after the sim(3) alignment); '
        '* diverged (ATE > 1 m, tracking lost or a non-finite estimate). a, b, c: image level; '
        'meas. c: measurement level, same seed and scene.',
        f'Acceptance {point["name"]} = {number_text(point["value"], 2)} '
        f'(target {point["target"]}; '
        f'seeds meeting {point["seeds_meeting"]}): {"PASS" if point["passed"] else "FAIL"}',
    ]
    shadow = content['totals']['image']['c'].get('shadow')
    if shadow:
        lines.append(
            f'Image c Shadow filter: {shadow["handovers"]} handovers ({shadow["handovers_moving"]}'
            f' moving, {shadow["handovers_refused"]} refused); frames processed '
            f'{shadow["frames_processed"]}, skipped by the pose gate '
            f'{shadow["frames_skipped_pose_gate"]}, without a pose {shadow["frames_without_pose"]}'
        )
    lines += [
        f'FAILED RUN seed {f["seed"]} ({f["level"]} {f["variant"]}): {f["error"]}'
        for f in content['failures']
    ]
    return '\n'.join(lines)


RUN_STYLES = {
    'image a': {'color': 'tab:green', 'lw': 0.8},
    'image b': {'color': 'tab:red', 'lw': 0.6, 'alpha': 0.7},
    'image c': {'color': 'tab:blue', 'lw': 1.0},
    'measurement c': {'color': 'tab:orange', 'lw': 1.0, 'ls': '--'},
}
TOPVIEW_COLUMNS = 5
TOPVIEW_MARGIN_M = 0.75


def write_figures(directory: Path, results: Sequence[SeedResult], rate_hz: float) -> list[Path]:
    """Draw the top views (one per seed) and the position error over time; return the PNG
    paths."""
    import matplotlib

    matplotlib.use('Agg')
    if not results:
        return []
    columns = min(TOPVIEW_COLUMNS, len(results))
    rows = math.ceil(len(results) / columns)
    drawings: list[tuple[str, Callable[[Any, Any], None], Any, tuple[float, float]]] = [
        ('monoslam_image_topview.png', _topviews, results, (4.0 * columns, 3.6 * rows)),
        ('monoslam_image_ate_time.png', _errors_over_time, (results, rate_hz), (11.0, 3.8)),
    ]
    return [
        write_atomically(directory / name, render_png(draw, data, size))
        for name, draw, data, size in drawings
    ]


def _topviews(figure: Any, results: Sequence[SeedResult]) -> None:
    columns = min(TOPVIEW_COLUMNS, len(results))
    rows = math.ceil(len(results) / columns)
    grid = np.atleast_1d(figure.subplots(rows, columns, squeeze=False)).ravel()
    for axes, result in zip(grid, results, strict=False):
        truth = result.truth
        axes.plot(truth[:, 0], truth[:, 1], 'k-', lw=1.6, alpha=0.5, label='truth')
        for name, centres in result.centres.items():
            axes.plot(centres[:, 0], centres[:, 1], label=name, **RUN_STYLES[name])
        low = truth[:, :2].min(axis=0) - TOPVIEW_MARGIN_M
        high = truth[:, :2].max(axis=0) + TOPVIEW_MARGIN_M
        axes.set_xlim(low[0], high[0])
        axes.set_ylim(low[1], high[1])
        axes.set_aspect('equal')
        axes.set_xlabel('x [m]')
        axes.set_ylabel('y [m]')
        axes.set_title(f'seed {result.entry["seed"]}: camera top view', fontsize=9)
        axes.grid(True, lw=0.3)
    grid[0].legend(fontsize=6, loc='lower right')
    for axes in grid[len(results) :]:
        axes.set_visible(False)


def _errors_over_time(figure: Any, data: tuple[Sequence[SeedResult], float]) -> None:
    results, rate_hz = data
    curves = error_curves(results)
    left, right = figure.subplots(1, 2, sharey=True)
    for name, values in curves.items():
        times = np.arange(values.shape[1]) / rate_hz
        left.plot(times, rms_over_seeds(values), label=name, **RUN_STYLES[name])
        if name in ('image c', 'measurement c'):
            for row in values:
                right.plot(times, row, color=RUN_STYLES[name]['color'], lw=0.4, alpha=0.6)
    left.set_title('camera position error, RMS over seeds', fontsize=9)
    right.set_title('per seed: image c (blue), measurement c (orange)', fontsize=9)
    left.set_ylabel('|centre error| [m]')
    for axes in (left, right):
        axes.set_yscale('log')
        axes.set_xlabel('time [s]')
        axes.grid(True, lw=0.3)
    left.legend(fontsize=7)


# --- command line ---------------------------------------------------------------------------


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/monoslam_image_eval'),
        help='output directory (default out/monoslam_image_eval)',
    )
    parser.add_argument('--seeds', help='seeds to render, e.g. 0-9 (default) or 1,4')
    parser.add_argument('--duration-s', type=float, help='rendered run length, s (default 20)')
    parser.add_argument(
        '--bag',
        type=Path,
        nargs='+',
        action='extend',
        default=[],
        help='dynamic_camera_sim bags to evaluate instead of rendering (one run each)',
    )
    gate = ','.join(f'{v:g}' for v in DEFAULT_SHADOW_MAX_POSE_SIGMA)
    parser.add_argument(
        '--shadow-max-pose-sigma',
        default=gate,
        help=f'the Shadow pose gate as monoslam_evaluate (default {gate}; inf: no gate)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=1,
        choices=(0, 1, 2),
        help="the Shadow filter's STATIC rule as monoslam_evaluate (default 1)",
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.bag and (args.seeds is not None or args.duration_s is not None):
        parser.error('--bag: a bag brings its own seed and duration; drop --seeds/--duration-s')
    try:
        seeds = parse_seeds(args.seeds or '0-9')
        gate_values = parse_pose_gate(args.shadow_max_pose_sigma)
    except ValueError as error:
        parser.error(str(error).replace('shadow max pose sigma', '--shadow-max-pose-sigma'))
    duration_s = args.duration_s if args.duration_s is not None else 20.0
    evaluation = monoslam_evaluate.Settings(
        seeds, duration_s, VARIANTS, gate_values, args.out, args.unchecked_directions
    )
    try:
        scene = evaluation.scene()
    except ValueError as error:
        parser.error(f'--duration-s {duration_s:g}: {error}')
    sources = [rendered_source(seed, scene) for seed in seeds]
    if args.bag:
        missing = [str(path) for path in args.bag if not path.exists()]
        if missing:
            parser.error(f'--bag: {", ".join(missing)}: no such file or directory')
        try:
            sources = [bag_source(path) for path in args.bag]
        except BagError as error:
            parser.error(f'--bag: {error}')
    return Settings(tuple(sources), evaluation, args.out)


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation; print the table; write the JSON report, the table and the figures
    to --out. Exit status 1 if a filter raised on a run (listed in the report)."""
    settings = _arguments(argv)
    single_threaded_blas()
    started = time.perf_counter()
    total = sum(source.frame_count for source in settings.sources)
    progress = ProgressReporter(total, label=PROG, unit=' images')
    results, done = [], 0

    def advance() -> None:
        nonlocal done
        done += 1
        progress.update(done)

    for source in settings.sources:
        results.append(evaluate_source(source, settings, advance))
        print(_seed_line(results[-1]), file=sys.stderr)  # noqa: T201
    progress.finish()
    content = report(settings, results, time.perf_counter() - started)
    figures = write_figures(settings.out, results, content['curves']['rate_hz'])
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / REPORT_NAME, content)
    table = table_text(content)
    write_atomically(settings.out / TABLE_NAME, table + '\n')
    print(table)  # noqa: T201
    print(f'wrote {settings.out / REPORT_NAME}, {TABLE_NAME} and {len(figures)} figures')  # noqa: T201
    return 1 if content['failures'] else 0


if __name__ == '__main__':
    sys.exit(main())
