"""Benchmark: marker_detector frames per second on one core, next to bare cv2.aruco.

Frames are 640x480 gray renders (``marker_detector.core.rendering``: supersampled, the
corners exactly where the camera model puts them) of 5 AprilTag 36h11 markers of 0.16 m, one
per column of the image, 0.8-3.5 m away (sides of 20-100 px), turned up to 0.6 rad about
each axis, over a smooth random texture with dark and light clutter, blurred (0.7 px) and
noisy (2 gray levels); a mild plumb-bob lens. Everything is seeded.

Measured in the same run, each over all frames, best of ``--repeats`` passes, with
cv2.setNumThreads(1):

* reference: a bare ``cv2.aruco.ArucoDetector`` with OpenCV's default parameters and stock
  dictionary, ``detectMarkers`` only (no pose);
* ours: ``detect_markers`` (detection, edge-refined corners, re-decoding of rejected
  candidates, IPPE pose with a Gauss-Newton step, covariance, quality gates) for both
  ``detector_profile`` values, each with ``corner_refinement`` 'subpix' and 'none', and the
  accurate profile without the edge fit (cv2's cornerSubPix corners only).

Per variant: frames/s, its ratio to the reference, markers found (of 5 per frame), the
median and 95th percentile corner error against the rendered truth and the largest range
error. Acceptance: at least 100 frames/s with the node's default settings (profile
'accurate', subpixel refinement on, full pipeline); PASS or FAIL is printed and FAIL exits
with 1.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/marker_detector_speed.py [--frames 40] [--repeats 5]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from bench_common import best_of, source_revision

from marker_detector.core.detection import detect_markers, make_detector
from marker_detector.core.detector_config import DetectorConfig
from marker_detector.core.rendering import MarkerPlacement, render_markers
from slam_core.camera import CameraModel
from slam_core.geometry.so3 import rotation_from_vector

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / 'results' / 'marker_detector_speed.md'
ACCEPT_FPS = 100.0
MARKERS_PER_FRAME = 5
MARKER_SIZE_M = 0.16
CAMERA = CameraModel(
    640,
    480,
    np.array([[520.0, 0.0, 322.0], [0.0, 520.0, 241.0], [0.0, 0.0, 1.0]]),
    np.array([-0.12, 0.05, 0.0, 0.0, 0.0]),
)
FACING = np.diag([1.0, -1.0, -1.0])  # marker face towards the camera, printed upright


@dataclass(frozen=True)
class Frame:
    """A rendered image and the markers in it."""

    image: np.ndarray
    placements: list[MarkerPlacement]


@dataclass(frozen=True)
class Variant:
    """One pipeline measured: a label and our config (None: the reference).

    ``accepted`` marks the node's default pipeline (the acceptance target).
    """

    label: str
    config: DetectorConfig | None
    accepted: bool = False


@dataclass(frozen=True)
class Row:
    """Timing and accuracy of one variant."""

    variant: Variant
    fps: float
    found: int
    median_corner_px: float
    p95_corner_px: float
    max_range_error: float


def background(rng: np.random.Generator) -> np.ndarray:
    """Return a (480, 640) textured background with a few dark and light rectangles."""
    texture = cv2.GaussianBlur(rng.uniform(40.0, 220.0, (480, 640)), (0, 0), 5.0)
    for _ in range(6):
        x, y = rng.integers(0, 600), rng.integers(0, 440)
        w, h = rng.integers(20, 120), rng.integers(20, 120)
        texture[y : y + h, x : x + w] = rng.choice([30.0, 230.0])
    return texture


def make_frame(rng: np.random.Generator) -> Frame:
    """Return one frame: 5 markers, one per image column, at random distances and tilts."""
    placements = []
    ids = rng.choice(587, MARKERS_PER_FRAME, replace=False)  # distinct: matched by id
    for column, marker_id in enumerate(ids):
        distance = rng.uniform(0.8, 3.5)
        x_fraction = (column + 0.5) / MARKERS_PER_FRAME - 0.5 + rng.uniform(-0.03, 0.03)
        x = x_fraction * distance * CAMERA.width / CAMERA.K[0, 0]
        y = rng.uniform(-0.25, 0.25) * distance * CAMERA.height / CAMERA.K[1, 1]
        rotation = rotation_from_vector(rng.uniform(-0.6, 0.6, 3)) @ FACING
        placements.append(
            MarkerPlacement(int(marker_id), MARKER_SIZE_M, rotation, np.array([x, y, distance]))
        )
    image = render_markers(CAMERA, placements, background(rng))
    image = cv2.GaussianBlur(image, (0, 0), 0.7) + rng.normal(0.0, 2.0, image.shape)
    return Frame(np.clip(np.round(image), 0, 255).astype(np.uint8), placements)


Found = list[tuple[int, np.ndarray, float]]  # (id, corners (4, 2) px, range m or nan)


def run_variant(variant: Variant, frames: list[Frame], repeats: int) -> Row:
    """Time one variant over all frames and score its corners and ranges."""
    if variant.config is None:
        reference = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
            cv2.aruco.DetectorParameters(),
        )

        def step(frame: Frame) -> Found:
            corners, ids, _ = reference.detectMarkers(frame.image)
            if ids is None:
                return []
            return [
                (int(i), c.reshape(4, 2).astype(np.float64), float('nan'))
                for c, i in zip(corners, ids.ravel(), strict=True)
            ]
    else:
        config, detector = variant.config, make_detector(variant.config)

        def step(frame: Frame) -> Found:
            result = detect_markers(frame.image, CAMERA, config, detector)
            return [(d.id, d.corners_px, d.range_m) for d in result.detections]

    seconds, outputs = best_of(repeats, lambda: [step(frame) for frame in frames])
    corner_errors, range_errors, found = [], [], 0
    for frame, markers in zip(frames, outputs, strict=True):
        truth = {p.marker_id: p for p in frame.placements}
        for marker_id, corners, range_m in markers:
            placement = truth.get(marker_id)
            if placement is None:
                continue
            found += 1
            corner_errors.extend(
                np.linalg.norm(corners - placement.corners_px(CAMERA), axis=1).tolist()
            )
            if np.isfinite(range_m):
                range_errors.append(abs(range_m / np.linalg.norm(placement.translation_m) - 1))
    return Row(
        variant,
        len(frames) / seconds,
        found,
        float(np.median(corner_errors)),
        float(np.percentile(corner_errors, 95)),
        float(max(range_errors)) if range_errors else float('nan'),
    )


VARIANTS = [
    Variant('reference: bare cv2.aruco, default parameters, detectMarkers only', None),
    Variant('ours accurate (default), full pipeline, subpix', DetectorConfig(), accepted=True),
    Variant('ours accurate, full pipeline, no subpix', DetectorConfig(corner_refinement='none')),
    Variant('ours fast, full pipeline, subpix', DetectorConfig(detector_profile='fast')),
    Variant(
        'ours fast, full pipeline, no subpix',
        DetectorConfig(detector_profile='fast', corner_refinement='none'),
    ),
    Variant(
        'ours accurate, cornerSubPix corners only (no edge fit, no re-decoding)',
        DetectorConfig(edge_refinement=False, redecode_rejected=False),
    ),
]


def render_report(rows: list[Row], *, frames: int, repeats: int, passed: bool) -> str:
    """Return the Markdown report."""
    now = datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')
    reference_fps = rows[0].fps
    lines = [
        '# marker_detector: frames per second on one core, next to bare cv2.aruco',
        '',
        f'{now}; {platform.platform()}, {os.cpu_count()} CPUs, Python '
        f'{platform.python_version()}, OpenCV {cv2.__version__}, numpy {np.__version__}; '
        f'commit {source_revision()}. {frames} frames of 640x480 px with '
        f'{MARKERS_PER_FRAME} AprilTag 36h11 markers each, best of {repeats} passes, '
        'cv2.setNumThreads(1).',
        '',
        '| pipeline | frames/s | ms/frame | / reference | markers found '
        '| median corner error px | p95 corner error px | max range error |',
        '|---|---:|---:|---:|---:|---:|---:|---:|',
    ]
    for row in rows:
        range_error = (
            '—' if np.isnan(row.max_range_error) else f'{100 * row.max_range_error:.2f} %'
        )
        lines.append(
            f'| {row.variant.label} | {row.fps:.1f} | {1e3 / row.fps:.2f} '
            f'| {row.fps / reference_fps:.2f} | {row.found} / {frames * MARKERS_PER_FRAME} '
            f'| {row.median_corner_px:.3f} | {row.p95_corner_px:.3f} | {range_error} |'
        )
    best = max((row for row in rows if row.variant.accepted), key=lambda row: row.fps)
    lines += [
        '',
        f'Acceptance: at least {ACCEPT_FPS:.0f} frames/s with the default settings: '
        f'{best.fps:.1f} frames/s ({best.variant.label}) -> **{"PASS" if passed else "FAIL"}**.',
        '',
    ]
    return '\n'.join(lines)


def build_arg_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--frames', type=int, default=40, help='rendered frames')
    parser.add_argument('--repeats', type=int, default=5, help='timed passes (best kept)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the scenes')
    parser.add_argument('--output', type=Path, default=DEFAULT_OUTPUT, help='Markdown report')
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_arg_parser().parse_args(argv)
    cv2.setNumThreads(1)
    rng = np.random.default_rng(args.seed)
    frames = [make_frame(rng) for _ in range(args.frames)]
    rows = []
    for variant in VARIANTS:
        rows.append(run_variant(variant, frames, args.repeats))
        print(f'{variant.label}: {rows[-1].fps:.1f} frames/s', flush=True)
    passed = max(row.fps for row in rows if row.variant.accepted) >= ACCEPT_FPS
    report = render_report(rows, frames=args.frames, repeats=args.repeats, passed=passed)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(report, encoding='utf-8')
    print(report)
    return 0 if passed else 1


if __name__ == '__main__':
    sys.exit(main())
