"""tum_rgbd_sequence: a TUM-layout RGB-D sequence as a monocular sequence directory.

Tracks from our feature tracker (or ``--tracks RECORDING``'s ``/features``), moving/static
labels from the depth maps (``--label-rule``), and depths or ``--known-points N``. Writes the
new ``--output``: the sequence files, labels.png, masks.png, label_masks.npz and import.json.

Example: ``tum_rgbd_sequence --dataset ../shared/data/bonn_crowd --convention bonn --output
out/bonn_crowd/sequence``.

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.cli import PlainDescriptionHelpFormatter, console_main
from slam_core.errors import DatasetError
from slam_core.files import write_atomically, write_json
from slam_core.progress import ProgressReporter
from slam_evaluation.sequence_files import Sequence, write_sequence
from slam_evaluation.tum_known_points import KnownPoints, choose_known_points, visibility
from slam_evaluation.tum_labels import (
    LABEL_RULES,
    label_figures,
    label_sequence,
    mask_images,
    rule_report,
)
from slam_evaluation.tum_tracking import ImageTracks, recorded_features, track_images
from slam_sim.core.depth_labels import LabelRule, PoseError, TrackLabels
from slam_sim.core.label_gate import LabelMasks, write_label_masks
from slam_sim.core.reference_error import BandErrors, ReferencePoseError
from slam_sim.core.tum_consistency import Consistency, pose_error, reference_error
from slam_sim.core.tum_rgbd import TumRgbd
from slam_sim.tum_rgbd_bag import add_dataset_arguments, read_dataset

PROG = 'tum_rgbd_sequence'
FIGURE_IMAGES = (100, 300, 500, 700)


@dataclass(frozen=True)
class ImportSettings:
    """The import's settings: static opening (images), known points (at most), pose error (m,
    None: measured), pixel noise (px), figure images, label rule, tracks recording (None: run
    the tracker)."""

    static_images: int = 180
    known_points: int = 0
    pose_sigma_m: float | None = None
    pixel_sigma_px: float = 1.0
    figure_images: tuple[int, ...] = FIGURE_IMAGES
    label_rule: str = 'masks'
    tracks_from: Path | None = None


def pose_rule(sequence: TumRgbd, settings: ImportSettings) -> tuple[LabelRule, list[Consistency]]:
    """Return the label rule with sigma_pose given or measured, and its bands."""
    if settings.pose_sigma_m is not None:
        error = PoseError.constant(settings.pose_sigma_m)
        return LabelRule(settings.pixel_sigma_px, error), []
    try:
        error, bands = pose_error(sequence, range(settings.static_images))
    except ValueError:
        raise DatasetError(
            f'{sequence.directory}: the first {settings.static_images} images hold no two '
            'depth maps with poses to measure the pose error; give --pose-sigma-m'
        ) from None
    return LabelRule(settings.pixel_sigma_px, error), bands


def reference_rule(
    sequence: TumRgbd, settings: ImportSettings
) -> tuple[ReferencePoseError, list[BandErrors]] | str:
    """Return the static opening's reference error table and bands, or why there is none."""
    try:
        return reference_error(
            sequence, range(settings.static_images), pixel_sigma_px=settings.pixel_sigma_px
        )
    except ValueError as error:
        return f'the first {settings.static_images} images: {error}'


@dataclass(frozen=True, eq=False)
class ImportResult:
    """What an import made: the sequence, labels (all tracks and the static opening's), known
    points, report (import.json's content) and figures (file name -> PNG bytes)."""

    sequence: Sequence
    labels: TrackLabels
    opening: TrackLabels
    known: KnownPoints
    report: dict[str, Any]
    figures: dict[str, bytes]
    files: dict[str, bytes] = field(default_factory=dict)
    """Other files (name -> bytes): label_masks.npz with the mask rule."""


def import_sequence(
    sequence: TumRgbd,
    settings: ImportSettings,
    *,
    rule: tuple[LabelRule, list[Consistency]] | None = None,
    progress: Callable[[int], None] | None = None,
    mask_progress: Callable[[int], None] | None = None,
    recorded: Mapping[int, ImageTracks] | None = None,
    reference: tuple[ReferencePoseError, list[BandErrors]] | str | None = None,
) -> ImportResult:
    """Return the sequence of a TUM-layout sequence with its report and figures;
    ``progress(images tracked)``, ``mask_progress(masks done)``; ``rule``, ``recorded`` and
    ``reference``: precomputed results, used if given."""
    started = time.monotonic()
    label_rule, bands = rule if rule is not None else pose_rule(sequence, settings)
    if reference is None:
        reference = reference_rule(sequence, settings)
    mask_of = mask_images(sequence, settings.figure_images)
    keep = tuple(sorted({*settings.figure_images, *mask_of.values()}))
    if recorded is None and settings.tracks_from is not None:
        recorded = recorded_features(settings.tracks_from)
    tracked = track_images(sequence, label_rule, keep=keep, progress=progress, recorded=recorded)
    posed = sequence.has_pose[tracked.images]
    frame_of = np.cumsum(sequence.has_pose) - 1
    frames, ids = frame_of[tracked.images[posed]], tracked.ids[posed]
    labelled = label_sequence(
        sequence, tracked, rule=settings.label_rule, endpoint_rule=label_rule,
        static_images=settings.static_images, keep_masks=tuple(mask_of.values()),
        progress=mask_progress,
    )  # fmt: skip
    labels, opening = labelled.chosen.labels, labelled.chosen.opening
    pixel_of = {
        (int(i), int(k)): (float(p[0]), float(p[1]))
        for i, k, p in zip(tracked.images, tracked.ids, tracked.pixels, strict=True)
    }
    track_ids, seen = np.unique(ids, return_counts=True)
    lifetimes = {int(k): int(n) for k, n in zip(track_ids, seen, strict=True)}
    known = choose_known_points(
        sequence.camera, tracked.depth, pixel_of, labels, lifetimes, cap=settings.known_points
    )
    poses = sequence.poses[sequence.has_pose]
    depth = tracked.depth
    camera_of = sequence.poses[depth.frames]  # T_world_camera of each depth sighting's image
    local = np.einsum('sji,sj->si', camera_of[:, :3, :3], depth.points - camera_of[:, :3, 3])
    usable = sequence.has_pose[depth.frames] & (local[:, 2] > 0.0)
    depths = {
        (int(frame_of[f]), int(i)): float(z)
        for f, i, z in zip(depth.frames[usable], depth.ids[usable], local[usable, 2], strict=True)
    }
    result = Sequence(
        sequence.camera, sequence.stamps_ns[sequence.has_pose], poses[:, :3, 3],
        poses[:, :3, :3], frames, ids, tracked.pixels[posed], labels.moving_by_id(),
        known.points if known.points else None, None, None if known.points else depths,
    )  # fmt: skip
    figures = label_figures(sequence, tracked, labelled, settings.figure_images)
    report = {
        **_inputs(sequence),
        'frames_written': len(result.stamps_ns),
        'tracks_from': None if settings.tracks_from is None else str(settings.tracks_from),
        'recorded_frames_matched': (
            None if recorded is None else int(np.isin(sequence.stamps_ns, list(recorded)).sum())
        ),
        'sightings': len(ids),
        'depth_sightings': len(tracked.depth.ids),
        'tracks': labels.counts(),
        'label_rule': rule_report(labelled.rule, label_rule),
        'static_opening': {
            'images': settings.static_images,
            'tracks': opening.counts(),
            'false_alarm_rate': opening.moving_share(),
            'pose_error_bands': [band.summary() for band in bands],
        },
        'reference_pose_error': (
            {'table': None, 'reason': reference}
            if isinstance(reference, str)
            else {
                'table': reference[0].to_json(),
                'bands': [band.summary() for band in reference[1]],
            }
        ),
        'by_rule': {name: by.summary() for name, by in labelled.by_rule.items()},
        'known_points': {
            'image': known.image,
            'frame': int(frame_of[known.image]) if known.image >= 0 else -1,
            'candidates': known.candidates,
            'ids': sorted(known.points),
            **visibility(frames, ids, sorted(known.points), _rate_hz(sequence)),
        },
        'figure': {
            'file': 'labels.png' if 'labels.png' in figures else None,
            'images': [i for i in settings.figure_images if i in tracked.kept],
            'masks_file': 'masks.png' if 'masks.png' in figures else None,
            'mask_images': {str(i): m for i, m in mask_of.items() if m in labelled.masks},
        },
        'elapsed_s': time.monotonic() - started,
    }
    files = {}
    if labelled.gate_masks:
        images = sorted(labelled.gate_masks)
        gate = [labelled.gate_masks[i] for i in images]
        files['label_masks.npz'] = write_label_masks(
            LabelMasks(
                sequence.stamps_ns[images].astype(np.int64),
                np.stack([g.codes for g in gate]),
                np.stack([g.depth_mm for g in gate]),
                np.stack([g.pose for g in gate]),
                sequence.camera,
                label_rule.pose_error,
            )
        )
    return ImportResult(result, labels, opening, known, report, figures, files)


def _inputs(sequence: TumRgbd) -> dict[str, Any]:
    """Return the report's description of the input: dataset, convention, camera, counts."""
    camera = sequence.camera
    return {
        'dataset': str(sequence.directory),
        'convention': sequence.convention,
        'camera': {
            'width': camera.width, 'height': camera.height, 'fx': camera.fx, 'fy': camera.fy,
            'cx': camera.cx, 'cy': camera.cy, 'd': camera.D.tolist(),
        },
        'images': sequence.counts(),
        'tracker': 'FeatureTracker(TrackerConfig()): the feature_tracker node defaults',
    }  # fmt: skip


def _rate_hz(sequence: TumRgbd) -> float:
    """Return the colour images' mean rate, Hz (NaN for one image)."""
    span_s = (int(sequence.stamps_ns[-1]) - int(sequence.stamps_ns[0])) / 1e9
    return (len(sequence.rgb) - 1) / span_s if span_s > 0 else float('nan')


def write_import(output: Path, result: ImportResult) -> Path:
    """Write the import into the new directory ``output`` atomically; DatasetError if it exists,
    its parent is missing, or it cannot be written."""
    target = Path(output).expanduser().absolute()
    if target.exists():
        raise DatasetError(f'output {str(target)!r} exists already; remove it or choose another')
    if not target.parent.is_dir():
        raise DatasetError(f'output {str(target)!r}: directory {str(target.parent)!r} is missing')
    staging = target.parent / f'.{target.name}.writing-{os.getpid()}'
    try:
        staging.mkdir()
        write_sequence(staging, result.sequence)
        for name, data in {**result.figures, **result.files}.items():
            write_atomically(staging / name, data)
        write_json(staging / 'import.json', result.report)
        staging.rename(target)
    except OSError as err:
        raise DatasetError(f'output {str(target)!r} cannot be written: {err}') from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def summary(output: Path, report: dict[str, Any]) -> str:
    """Return the one-line summary of an import."""
    tracks, opening = report['tracks'], report['static_opening']
    known = report['known_points']
    in_view = (
        f'in view for {known["frames_in_view_min"]}-{known["frames_in_view_max"]} frames '
        f'(median {known["frames_in_view_median"]:g}, {known["seconds_in_view_median"]:.1f} s), '
        f'at least 4 of them up to frame {known["last_frame_with_at_least_4"]}'
        if known['count']
        else 'none'
    )
    source = (
        f', recorded in {report["tracks_from"]} ({report["recorded_frames_matched"]} images '
        'matched)'
        if report.get('tracks_from')
        else ''
    )
    return (
        f'{PROG}: wrote {output}: {report["frames_written"]} frames, {tracks["tracks"]} tracks '
        f'({tracks["moving"]} moving, {tracks["static"]} static, {tracks["unknown"]} unknown)'
        f'{source}; '
        f'static opening: {opening["tracks"]["moving"]} of '
        f'{opening["tracks"]["moving"] + opening["tracks"]["static"]} labelled moving '
        f'(false alarms {100 * (opening["false_alarm_rate"] or 0.0):.1f} %); '
        f'sigma_pose {_sigmas(report["label_rule"]["pose_error"])}; '
        f'reference error {_reference(report["reference_pose_error"])}; {known["count"]} known '
        f'points from image {known["image"]}, {in_view}; {report["elapsed_s"]:.1f} s'
    )


def _sigmas(error: dict[str, Any]) -> str:
    pairs = zip(error['separations_s'], error['sigmas_m'], strict=True)
    return ', '.join(f'{1e3 * sigma:.0f} mm at {dt:.2f} s' for dt, sigma in pairs)


def _reference(error: dict[str, Any]) -> str:
    table = error['table']
    if table is None:
        return f'none ({error["reason"]})'
    rows = zip(
        table['separations_s'],
        table['rotation_sigmas_rad'],
        table['translation_sigmas_m'],
        strict=True,
    )
    return ', '.join(
        f'{np.degrees(rotation):.2f} deg and {1e3 * centre:.0f} mm at {dt:.2f} s'
        for dt, rotation, centre in rows
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, formatter_class=PlainDescriptionHelpFormatter
    )
    add_dataset_arguments(parser)
    defaults = ImportSettings()
    parser.add_argument(
        '--output', required=True, type=Path, metavar='DIR', help='new sequence directory'
    )
    parser.add_argument(
        '--static-images',
        type=int,
        metavar='N',
        default=defaults.static_images,
        help='colour images at the start with nothing moving (default 180)',
    )
    parser.add_argument(
        '--known-points',
        type=int,
        metavar='N',
        default=defaults.known_points,
        help='most known points (default 0: none, MonoSLAM starts from the depths)',
    )
    parser.add_argument(
        '--pose-sigma-m',
        type=float,
        metavar='M',
        default=None,
        help="ground truth's position error per axis, m (default: from the static opening)",
    )
    parser.add_argument(
        '--pixel-sigma-px',
        type=float,
        metavar='PX',
        default=defaults.pixel_sigma_px,
        help="tracker's pixel noise per axis, px (default 1)",
    )
    parser.add_argument(
        '--figure-images',
        type=int,
        metavar='INDEX',
        nargs='*',
        default=list(defaults.figure_images),
        help='colour images drawn in labels.png and masks.png (default 100 300 500 700)',
    )
    parser.add_argument(
        '--tracks',
        type=Path,
        metavar='RECORDING',
        default=None,
        help="a graph recording's /features as the tracks (default: run the feature tracker)",
    )
    parser.add_argument(
        '--label-rule',
        choices=LABEL_RULES,
        default=defaults.label_rule,
        help='masks: per-pixel motion masks (default); endpoints: first vs last depth points',
    )
    return parser


def _stage(total: int, label: str, unit: str) -> Callable[[int], None]:
    """Return a progress callback for one stage, finished at ``total``."""
    reporters: list[ProgressReporter] = []

    def update(done: int) -> None:
        if not reporters:
            reporters.append(ProgressReporter(total, label=label, unit=unit))
        reporters[0].update(done)
        if done >= total:
            reporters[0].finish()

    return update


@console_main(PROG)
def main(argv: list[str] | None = None) -> int:
    """Import a TUM-layout RGB-D sequence as a sequence directory."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    sequence = read_dataset(parser, args)
    if args.static_images < 0 or args.known_points < 0:
        parser.error('--static-images and --known-points must be >= 0')
    for option, value in (('--pose-sigma-m', args.pose_sigma_m),
                          ('--pixel-sigma-px', args.pixel_sigma_px)):  # fmt: skip
        if value is not None and not (np.isfinite(value) and value >= 0.0):
            parser.error(f'{option} must be a finite number >= 0, got {value}')
    settings = ImportSettings(
        args.static_images, args.known_points, args.pose_sigma_m, args.pixel_sigma_px,
        tuple(args.figure_images), args.label_rule, args.tracks,
    )  # fmt: skip
    target = Path(args.output).expanduser().absolute()
    if target.exists():
        raise DatasetError(f'output {str(target)!r} exists already; remove it or choose another')
    # a recording without /features is named before the slow steps
    recorded = None if args.tracks is None else recorded_features(args.tracks)
    if settings.pose_sigma_m is None:
        note = f'{PROG}: measuring the pose error on the first {settings.static_images} images'
        print(note, file=sys.stderr)  # noqa: T201
    rule = pose_rule(sequence, settings)
    note = (
        f"{PROG}: measuring the reference's rotation and centre error on the first "
        f'{settings.static_images} images (SIFT matches and PnP)'
    )
    print(note, file=sys.stderr)  # noqa: T201
    reference = reference_rule(sequence, settings)
    masked = int(np.count_nonzero((sequence.depth_index >= 0) & sequence.has_pose))
    result = import_sequence(
        sequence, settings, rule=rule, progress=_stage(len(sequence.rgb), PROG, ' images'),
        mask_progress=_stage(masked, f'{PROG} masks', ' depth maps'), recorded=recorded,
        reference=reference,
    )  # fmt: skip
    output = write_import(target, result)
    print(summary(output, result.report))  # noqa: T201
    return 0


if __name__ == '__main__':
    sys.exit(main())
