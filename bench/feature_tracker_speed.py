"""Benchmark: feature tracker frames per second on one core, next to a bare OpenCV loop.

Frames are 640x480 gray views of a seeded multi-scale texture (blurred noise at four scales
and a few hundred flat rectangles and ellipses, 1600x1200) through a slowly varying
homography: a pan of up to 6 px per frame, rotation, zoom and a little perspective, with a
brightness drift of +-4 % and camera noise of 2 gray levels. Everything is seeded; the
homographies give every tracked point's true position.

Measured in the same run, over all frames, best of ``--repeats`` passes (each pass times
every variant once, so that load from elsewhere falls on all alike), pinned to one CPU with
cv2.setNumThreads(1):

* reference: a bare loop of cv2.calcOpticalFlowPyrLK of the previous image's corners (the
  same window, levels and stopping rule as ours) and cv2.goodFeaturesToTrack(150 corners,
  quality 0.01, 10 px apart) on every image: no ids, no checks, no masks, no grid;
* ours: ``FeatureTracker.track`` with the node's defaults (150 features, Shi-Tomasi,
  detection every 3rd image where features are missing, grid, subpixel refinement,
  forward-backward check), and variants: FAST corners, detection every image and every 5th
  image, no forward-backward check; and the defaults through ``FeatureTrackingProcessor`` with what
  the node does around it (decoding a mono8 sensor_msgs/Image payload and serializing the
  FeatureTrackArray; no DDS).

Per variant: frames/s, its ratio to the reference, features per frame, the frame-to-frame
error of the tracks against the truth (median, 95th percentile, share above 1 px) and, for
ours, the mean track length. With ``--bag`` the frames are instead the images of a bag
(sensor_msgs/Image or CompressedImage, decoded by marker_detector's ``image_from_message``;
``--image-topic``, default the first of /camera/image_raw and its /compressed), timed the
same way; a bag has no truth, so the error columns stay empty.

Acceptance: at least 30 frames/s with the node's defaults; PASS or FAIL is printed, FAIL
exits with 1. The report goes to ``bench/results/feature_tracker_speed.md``.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/feature_tracker_speed.py [--frames 300] [--repeats 5]
    python bench/feature_tracker_speed.py --bag bags/dynamic_camera.mcap [--frames 300]
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import math
import os
import platform
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
from bench_common import best_of, pin_to_one_core, source_revision

from marker_detector.detector.conversions import image_from_message
from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from monoslam_shadow_node.feature_tracker.core.feature_tracker import FeatureTracker
from monoslam_shadow_node.feature_tracker.processor import (
    FeatureFrame,
    FeatureTrackingProcessor,
    feature_frame_cdr,
)
from slam_core.errors import BagError, SlamError
from slam_core.files import write_atomically
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / 'results' / 'feature_tracker_speed.md'
ACCEPT_FPS = 30.0
WIDTH, HEIGHT = 640, 480
TEXTURE_SIZE = (1200, 1600)
PERIOD_NS = 33_333_333
DEFAULTS = TrackerConfig()
BAG_IMAGE_TOPICS = ('/camera/image_raw', '/camera/image_raw/compressed')

FloatArray = np.ndarray
Tracks = list[tuple[np.ndarray, np.ndarray]]  # per frame: ids (N,) and pixels (N, 2)


@dataclass(frozen=True)
class Sequence:
    """The frames (F, H, W) uint8, their homographies (F, 3, 3): texture -> image (None for
    a bag's frames) and where they come from."""

    frames: np.ndarray
    homographies: np.ndarray | None
    source: str


@dataclass(frozen=True)
class Row:
    """One variant's timing and accuracy."""

    label: str
    fps: float
    features: float
    median_error_px: float
    p95_error_px: float
    outlier_share: float
    track_length: float | None
    accepted: bool = False


def scene_texture(rng: np.random.Generator) -> np.ndarray:
    """Return a (1200, 1600) float32 texture: noise blurred at four scales, and flat shapes."""
    height, width = TEXTURE_SIZE
    texture = np.zeros(TEXTURE_SIZE, np.float32)
    for sigma, weight in ((1.5, 0.35), (4.0, 0.3), (10.0, 0.2), (30.0, 0.15)):
        noise = cv2.GaussianBlur(
            rng.normal(0.0, 1.0, TEXTURE_SIZE).astype(np.float32), (0, 0), sigma
        )
        texture += weight * noise / noise.std()
    texture = 128.0 + 40.0 * texture
    for _ in range(300):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        size = (int(rng.integers(6, 60)), int(rng.integers(6, 60)))
        gray = float(rng.uniform(20.0, 235.0))
        if rng.random() < 0.5:
            cv2.rectangle(texture, centre, (centre[0] + size[0], centre[1] + size[1]), gray, -1)
        else:
            cv2.ellipse(texture, centre, size, float(rng.uniform(0, 180)), 0, 360, gray, -1)
    return cv2.GaussianBlur(texture, (0, 0), 0.8)


def homography(k: int) -> np.ndarray:
    """Texture pixel -> image pixel of frame k: a slow pan, rotation, zoom and perspective."""
    height, width = TEXTURE_SIZE
    pan_u = 300.0 * math.sin(2 * math.pi * k / 300)
    pan_v = 150.0 * math.sin(2 * math.pi * k / 200 + 1.0)
    angle = 0.1 * math.sin(2 * math.pi * k / 250)
    zoom = 1.0 + 0.15 * math.sin(2 * math.pi * k / 350)
    to_centre = np.array([[1, 0, -(width / 2 + pan_u)], [0, 1, -(height / 2 + pan_v)], [0, 0, 1]])
    cos, sin = zoom * math.cos(angle), zoom * math.sin(angle)
    turn = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    tilt = np.array([[1, 0, 0], [0, 1, 0], [2e-5 * math.sin(k / 40), 1e-5 * math.cos(k / 50), 1]])
    to_image = np.array([[1, 0, WIDTH / 2], [0, 1, HEIGHT / 2], [0, 0, 1]])
    return to_image @ tilt @ turn @ to_centre


def make_sequence(count: int, seed: int) -> Sequence:
    """Return ``count`` frames of the texture through ``homography``, with brightness drift and
    camera noise."""
    rng = np.random.default_rng(seed)
    texture = scene_texture(rng)
    frames, homographies = [], []
    for k in range(count):
        matrix = homography(k)
        image = cv2.warpPerspective(texture, matrix, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
        image = image * (1.0 + 0.04 * math.sin(k / 30)) + rng.normal(0.0, 2.0, image.shape)
        frames.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
        homographies.append(matrix)
    return Sequence(
        np.array(frames),
        np.array(homographies),
        f'{WIDTH}x{HEIGHT} px views of a texture through a slowly varying homography',
    )


def bag_sequence(path: Path, topic: str | None, count: int) -> Sequence:
    """Return the first ``count`` images of a bag's image topic, decoded to gray."""
    registry = TypeRegistry()
    frames = []
    with BagSource(path) as source:
        topics = source.topics()
        topic = topic or next((t for t in BAG_IMAGE_TOPICS if t in topics), None)
        if topic is None or topic not in topics:
            raise BagError(f'bag {str(path)!r} has no image topic {topic or BAG_IMAGE_TOPICS}')
        msgtype = topics[topic].msgtype
        registry.ensure(msgtype)
        for message in source.messages([topic]):
            decoded = registry.typestore.deserialize_cdr(message.data, msgtype)
            frames.append(image_from_message(decoded))
            if len(frames) == count:
                break
    if len(frames) < 2:
        raise BagError(f'bag {str(path)!r}: fewer than 2 images on {topic}')
    height, width = frames[0].shape
    return Sequence(np.array(frames), None, f'{width}x{height} px images of {topic} in {path}')


# --- the variants ----------------------------------------------------------------------------


def run_reference(frames: np.ndarray) -> Tracks:
    """The bare loop; a corner's 'id' is its row in the previous image's corners."""
    window = (DEFAULTS.lk_window_px, DEFAULTS.lk_window_px)
    criteria = (
        cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT,
        DEFAULTS.lk_max_iterations,
        DEFAULTS.lk_epsilon_px,
    )
    tracks: Tracks = []
    previous, corners = None, None
    for image in frames:
        if previous is not None and corners is not None:
            moved, status, _ = cv2.calcOpticalFlowPyrLK(
                previous, image, corners, corners.copy(), winSize=window,
                maxLevel=DEFAULTS.lk_pyramid_levels, criteria=criteria,
            )  # fmt: skip
            ok = status.ravel() == 1
            tracks.append((np.flatnonzero(ok), moved.reshape(-1, 2)[ok].astype(np.float64)))
        corners = cv2.goodFeaturesToTrack(
            image, DEFAULTS.max_features, DEFAULTS.quality_level, DEFAULTS.min_distance_px
        )
        previous = image
    return tracks


def reference_pairs(frames: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per step k -> k+1 of the reference: the corners of frame k (N, 2) and where LK took the
    successful ones (N, 2; NaN where it failed), for scoring (untimed)."""
    pairs = []
    window = (DEFAULTS.lk_window_px, DEFAULTS.lk_window_px)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, DEFAULTS.lk_max_iterations,
                DEFAULTS.lk_epsilon_px)  # fmt: skip
    for before, after in itertools.pairwise(frames):
        corners = cv2.goodFeaturesToTrack(
            before, DEFAULTS.max_features, DEFAULTS.quality_level, DEFAULTS.min_distance_px
        )
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            before, after, corners, corners.copy(), winSize=window,
            maxLevel=DEFAULTS.lk_pyramid_levels, criteria=criteria,
        )  # fmt: skip
        end = moved.reshape(-1, 2).astype(np.float64)
        end[status.ravel() != 1] = np.nan
        pairs.append((corners.reshape(-1, 2).astype(np.float64), end))
    return pairs


def run_tracker(frames: np.ndarray, config: TrackerConfig) -> Tracks:
    tracker = FeatureTracker(config)
    tracks: Tracks = []
    for image in frames:
        result = tracker.track(image)
        tracks.append((result.ids, result.pixels))
    return tracks


def image_message(image: np.ndarray, stamp_ns: int) -> Any:
    """A sensor_msgs/Image look-alike (fields by name, as conversions read them)."""
    height, width = image.shape
    header = SimpleNamespace(
        stamp=SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id='camera_optical_frame',
    )
    return SimpleNamespace(
        header=header, encoding='mono8', width=width, height=height, step=width,
        data=image.tobytes(),
    )  # fmt: skip


def run_node_path(messages: list[Any]) -> Tracks:
    """Decode, process and serialize the output message, as the node's image callback does."""
    processor = FeatureTrackingProcessor(TrackerConfig())
    tracks: Tracks = []
    for message in messages:
        stamp_ns = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
        image = image_from_message(message)
        for outcome in processor.add_image(stamp_ns, message.header.frame_id, image, now_s=0.0):
            if isinstance(outcome, FeatureFrame):
                feature_frame_cdr(outcome)
                tracks.append((outcome.features.ids, outcome.features.pixels))
    return tracks


# --- scoring ---------------------------------------------------------------------------------


def moved_by(matrix: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    points = np.column_stack([pixels, np.ones(len(pixels))]) @ matrix.T
    return points[:, :2] / points[:, 2:]


def step_errors(tracks: Tracks, homographies: np.ndarray | None) -> np.ndarray:
    """Frame-to-frame errors (px) of every track seen in consecutive frames (none without
    homographies)."""
    errors: list[np.ndarray] = []
    if homographies is None:
        return np.zeros(0)
    for k in range(1, len(tracks)):
        ids_before, before = tracks[k - 1]
        ids_after, after = tracks[k]
        common, rows_before, rows_after = np.intersect1d(
            ids_before, ids_after, return_indices=True
        )
        if not len(common):
            continue
        step = homographies[k] @ np.linalg.inv(homographies[k - 1])
        truth = moved_by(step, before[rows_before])
        errors.append(np.linalg.norm(after[rows_after] - truth, axis=1))
    return np.concatenate(errors) if errors else np.zeros(0)


def reference_errors(sequence: Sequence) -> np.ndarray:
    errors: list[np.ndarray] = []
    if sequence.homographies is None:
        return np.zeros(0)
    for k, (before, after) in enumerate(reference_pairs(sequence.frames)):
        ok = np.all(np.isfinite(after), axis=1)
        step = sequence.homographies[k + 1] @ np.linalg.inv(sequence.homographies[k])
        errors.append(np.linalg.norm(after[ok] - moved_by(step, before[ok]), axis=1))
    return np.concatenate(errors)


def track_length(tracks: Tracks) -> float:
    """Mean number of frames a track id appears in."""
    ids, counts = np.unique(np.concatenate([ids for ids, _ in tracks]), return_counts=True)
    return float(np.mean(counts)) if len(ids) else 0.0


def row(
    label: str, seconds: float, tracks: Tracks, errors: np.ndarray, frames: int, **extra: Any
) -> Row:
    known = len(errors) > 0
    return Row(
        label=label,
        fps=frames / seconds,
        features=float(np.mean([len(ids) for ids, _ in tracks])),
        median_error_px=float(np.median(errors)) if known else math.nan,
        p95_error_px=float(np.percentile(errors, 95)) if known else math.nan,
        outlier_share=float(np.mean(errors > 1.0)) if known else math.nan,
        **extra,
    )


@dataclass(frozen=True)
class Variant:
    """One pipeline to time: its label, the run over all frames, whether it is the node's
    defaults (the acceptance target) and whether it is the reference."""

    label: str
    run: Callable[[], Tracks]
    accepted: bool = False
    reference: bool = False


def best_interleaved(repeats: int, variants: list[Variant]) -> list[tuple[float, Tracks]]:
    """Return per variant the shortest wall time (s) over ``repeats`` passes and its tracks.
    Each pass times every variant once, so that load from elsewhere on the machine falls on
    all of them alike (bench_common.best_of would time one variant's passes back to back)."""
    best: list[tuple[float, Tracks]] = [(math.inf, []) for _ in variants]
    for _ in range(max(repeats, 1)):
        for index, variant in enumerate(variants):
            seconds, tracks = best_of(1, variant.run)
            if seconds < best[index][0]:
                best[index] = (seconds, tracks)
    return best


def measure(sequence: Sequence, repeats: int) -> list[Row]:
    frames, count = sequence.frames, len(sequence.frames)
    messages = [image_message(image, 10**18 + k * PERIOD_NS) for k, image in enumerate(frames)]
    variants = [
        Variant('reference: bare goodFeaturesToTrack + calcOpticalFlowPyrLK every frame',
                lambda: run_reference(frames), reference=True),
        Variant('ours, defaults (Shi-Tomasi every 3rd frame, grid, subpixel, forward-backward)',
                lambda: run_tracker(frames, TrackerConfig()), accepted=True),
        Variant('ours, FAST corners', lambda: run_tracker(frames, TrackerConfig(detector='fast'))),
        Variant('ours, detection every frame',
                lambda: run_tracker(frames, TrackerConfig(detect_every_n_frames=1))),
        Variant('ours, detection every 5th frame',
                lambda: run_tracker(frames, TrackerConfig(detect_every_n_frames=5))),
        Variant('ours, no forward-backward check',
                lambda: run_tracker(frames, TrackerConfig(fb_threshold_px=0.0))),
        Variant('ours, defaults, node path without DDS (decode, processor, fill message)',
                lambda: run_node_path(messages), accepted=True),
    ]  # fmt: skip
    rows = []
    for variant, (seconds, tracks) in zip(
        variants, best_interleaved(repeats, variants), strict=True
    ):
        if variant.reference:
            errors, length = reference_errors(sequence), None
        else:
            errors, length = step_errors(tracks, sequence.homographies), track_length(tracks)
        rows.append(
            row(variant.label, seconds, tracks, errors, count, track_length=length,
                accepted=variant.accepted)
        )  # fmt: skip
        print(f'{variant.label}: {rows[-1].fps:.1f} frames/s', flush=True)
    return rows


# --- report ----------------------------------------------------------------------------------


def _number(value: float, text: str) -> str:
    return '—' if math.isnan(value) else text


def render_report(
    rows: list[Row], *, sequence: Sequence, repeats: int, pinned: str, passed: bool
) -> str:
    """Return the Markdown report."""
    now = datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')
    reference = rows[0].fps
    lines = [
        '# feature_tracker: frames per second on one core, next to a bare OpenCV loop',
        '',
        f'{now}; {platform.platform()}, {os.cpu_count()} CPUs ({pinned}), Python '
        f'{platform.python_version()}, OpenCV {cv2.__version__} with '
        f'cv2.getNumThreads() = {cv2.getNumThreads()}, numpy {np.__version__}; commit '
        f'{source_revision()}. {len(sequence.frames)} frames: {sequence.source}; best of '
        f'{repeats} passes; {DEFAULTS.max_features} features.',
        '',
        '| pipeline | frames/s | ms/frame | / reference | features/frame | step error median px '
        '| p95 px | > 1 px | mean track length (frames) |',
        '|---|---:|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for item in rows:
        length = '—' if item.track_length is None else f'{item.track_length:.1f}'
        lines.append(
            f'| {item.label} | {item.fps:.1f} | {1e3 / item.fps:.2f} | {item.fps / reference:.2f} '
            f'| {item.features:.1f} '
            f'| {_number(item.median_error_px, f"{item.median_error_px:.3f}")} '
            f'| {_number(item.p95_error_px, f"{item.p95_error_px:.3f}")} '
            f'| {_number(item.outlier_share, f"{100 * item.outlier_share:.2f} %")} | {length} |'
        )
    slowest = min((item for item in rows if item.accepted), key=lambda item: item.fps)
    lines += [
        '',
        f"Acceptance: at least {ACCEPT_FPS:.0f} frames/s with the node's defaults: "
        f'{slowest.fps:.1f} frames/s ({slowest.label}) -> **{"PASS" if passed else "FAIL"}**.',
        '',
    ]
    return '\n'.join(lines)


def build_arg_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=(__doc__ or '').split('\n\n')[0])
    parser.add_argument('--frames', type=int, default=300, help='frames in the sequence')
    parser.add_argument('--repeats', type=int, default=5, help='timed passes (best kept)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the texture and noise')
    parser.add_argument('--bag', type=Path, default=None, help='time the images of this bag')
    parser.add_argument('--image-topic', default=None, help="the bag's image topic")
    parser.add_argument('--cpu', type=int, default=None, help='CPU to pin to (default: last)')
    parser.add_argument('--output', type=Path, default=DEFAULT_OUTPUT, help='Markdown report')
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_arg_parser().parse_args(argv)
    pinned = pin_to_one_core(args.cpu)
    try:
        sequence = (
            make_sequence(args.frames, args.seed)
            if args.bag is None
            else bag_sequence(args.bag, args.image_topic, args.frames)
        )
    except SlamError as err:
        print(f'feature_tracker_speed: error: {err}', file=sys.stderr)
        return 2
    rows = measure(sequence, args.repeats)
    passed = min(item.fps for item in rows if item.accepted) >= ACCEPT_FPS
    report = render_report(
        rows, sequence=sequence, repeats=args.repeats, pinned=pinned, passed=passed
    )
    write_atomically(args.output, report)
    print(report)
    return 0 if passed else 1


if __name__ == '__main__':
    sys.exit(main())
