"""Study: does MonoSLAM's drift on a real sequence come from its measurements or from how
long its features live?

Variant (a) (MonoSLAM on the features labelled static, depth start) runs over the first
``--frames`` frames of an on-disk sequence (``sequence_files``; default the Bonn crowd import,
whose first 180 frames show no person), in three forms:

* ``recorded``: the sequence as it is (our tracker's tracks, labels, depths);
* ``consistent``: the same tracks, seen in the same frames, but each static track's pixels
  replaced by the projection, through the reference poses, of one world point (its first
  depth sighting back-projected through the reference pose of that frame) plus white noise of
  ``--pixel-sigma-px`` (the filter's default noise): measurements that agree exactly with the
  reference trajectory and the filter's noise model, with the tracker's track lives. Tracks
  without a depth sighting are left out;
* ``recorded + start kept``: the recorded static tracks, and beside them (ids apart) the
  depth start's points as ``persistent 0`` has them: what re-identifying the known points
  would give on top of our tracker's tracks;
* ``persistent L``: only the tracks of the depth start (the first frame with depths), their
  world points projected into every frame where they lie in the image, with white noise;
  each track's id changes every ``L`` frames (0: never; staggered over the tracks), so a
  feature lives L frames and comes back under a new id, as our tracker's ids do without
  re-identification.

Each run reports the position error at the last frame and its RMS, the mean position NEES
(3 degrees of freedom, against the filter's own covariance; the reference's error does not
enter, and in the consistent forms there is none) and the mean life of the tracks measured.
If ``consistent`` drifts like ``recorded`` while ``persistent 0`` does not, the drift comes
from the features' short lives, not from the tracker's errors. A synthetic form's figures are
the median over ``--noise-seeds`` noise draws (one draw is noisy: position NEES 36 or 103 for
``persistent 30``), each form with its own seeds. Figures: bench/README.md.
Run (after ``bash scripts/bootstrap.sh``; a few seconds per run)::

    source scripts/env.sh
    python bench/monoslam_track_life_study.py --sequence out/bonn_crowd/sequence
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slam_core.arrays import FloatArray
from slam_evaluation.monoslam_pipeline import PipelineConfig, run_variant
from slam_evaluation.sequence_files import (
    Sequence,
    in_depth_start_frame,
    measurement_frames,
    read_sequence,
)

ID_STRIDE = 10**6  # persistent forms: new id = id + ID_STRIDE * ((frame + id) // life)


def first_frames(sequence: Sequence, count: int) -> Sequence:
    """Return the sequence cut to its first ``count`` frames."""
    keep = sequence.frame < count
    depths = {k: v for k, v in (sequence.depths or {}).items() if k[0] < count}
    return dataclasses.replace(
        sequence,
        stamps_ns=sequence.stamps_ns[:count],
        centres=sequence.centres[:count],
        rotations=sequence.rotations[:count],
        frame=sequence.frame[keep],
        ids=sequence.ids[keep],
        pixels=sequence.pixels[keep],
        depths=depths,
    )


def world_points(sequence: Sequence) -> dict[int, tuple[int, FloatArray]]:
    """Return per track with a depth sighting: the frame of its first one and the world
    point (3,) m its depth gives through the reference pose there."""
    points: dict[int, tuple[int, FloatArray]] = {}
    row = {
        (f, t): k
        for k, (f, t) in enumerate(
            zip(sequence.frame.tolist(), sequence.ids.tolist(), strict=True)
        )
    }
    for (frame, track), depth in sorted((sequence.depths or {}).items()):
        seen = row.get((frame, track))
        if track in points or seen is None or not (math.isfinite(depth) and depth > 0.0):
            continue
        ray, valid = sequence.camera.unproject(sequence.pixels[seen])
        if not bool(valid):
            continue
        camera_point = depth * np.array([ray[0], ray[1], 1.0])
        points[track] = (frame, sequence.rotations[frame] @ camera_point + sequence.centres[frame])
    return points


def _project(sequence: Sequence, frame: int, point: FloatArray) -> FloatArray | None:
    """Return the raw pixel (2,) of a world point in a frame, or None outside the image."""
    local = sequence.rotations[frame].T @ (point - sequence.centres[frame])
    if local[2] <= 0.1:
        return None
    pixel = sequence.camera.project(local[None])[0]
    width, height = sequence.camera.width, sequence.camera.height
    inside = 0.0 <= pixel[0] <= width - 1 and 0.0 <= pixel[1] <= height - 1
    return pixel if inside else None


def consistent(sequence: Sequence, sigma_px: float, rng: np.random.Generator) -> Sequence:
    """Return the ``consistent`` form (module docstring)."""
    labels = sequence.labels or {}
    points = world_points(sequence)
    rows: list[tuple[int, int, FloatArray]] = []
    for frame, track in zip(sequence.frame.tolist(), sequence.ids.tolist(), strict=True):
        if labels.get(track, False) or track not in points:
            continue
        pixel = _project(sequence, frame, points[track][1])
        if pixel is not None:
            rows.append((frame, track, pixel + rng.normal(0.0, sigma_px, 2)))
    return _with_sightings(sequence, rows, sequence.depths or {})


def persistent(
    sequence: Sequence, life: int, sigma_px: float, rng: np.random.Generator
) -> Sequence:
    """Return the ``persistent`` form with tracks living ``life`` frames (0: for ever)."""
    depths = sequence.depths or {}
    start = min(frame for frame, _ in depths)
    points = {t: p for t, (f, p) in world_points(sequence).items() if f == start}
    rows = []
    for frame in range(len(sequence.stamps_ns)):
        for track, point in points.items():
            pixel = _project(sequence, frame, point)
            if pixel is not None:
                renamed = track + ID_STRIDE * ((frame + track) // life if life else 0)
                rows.append((frame, renamed, pixel + rng.normal(0.0, sigma_px, 2)))
    start_depths = {k: v for k, v in depths.items() if k[0] == start and k[1] in points}
    return _with_sightings(sequence, rows, start_depths)


def start_kept(sequence: Sequence, sigma_px: float, rng: np.random.Generator) -> Sequence:
    """Return the ``recorded + start kept`` form (module docstring)."""
    kept = persistent(sequence, 0, sigma_px, rng)
    labels = sequence.labels or {}
    static = np.array([not labels.get(t, False) for t in sequence.ids.tolist()], dtype=bool)
    offset = int(sequence.ids.max(initial=0)) + 1
    frame = np.concatenate([sequence.frame[static], kept.frame])
    ids = np.concatenate([sequence.ids[static], kept.ids + offset])
    pixels = np.vstack([sequence.pixels[static], kept.pixels])
    order = np.lexsort((ids, frame))
    depths = {(f, t + offset): d for (f, t), d in (kept.depths or {}).items()}
    return dataclasses.replace(
        sequence,
        frame=frame[order],
        ids=ids[order],
        pixels=pixels[order],
        labels={},
        depths=depths,
    )


def _with_sightings(
    sequence: Sequence,
    rows: list[tuple[int, int, FloatArray]],
    depths: dict[tuple[int, int], float],
) -> Sequence:
    rows.sort(key=lambda row: (row[0], row[1]))
    return dataclasses.replace(
        sequence,
        frame=np.array([r[0] for r in rows], dtype=np.int64),
        ids=np.array([r[1] for r in rows], dtype=np.int64),
        pixels=np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 2),
        labels={},
        depths=depths,
    )


def run(sequence: Sequence, second_order: bool = True) -> dict[str, float]:
    """Run variant (a) from the depth start, with ``MonoSlamConfig.second_order`` as
    given; return its figures (module docstring)."""
    frames = in_depth_start_frame(measurement_frames(sequence))
    config = PipelineConfig()
    slam = dataclasses.replace(config.slam, known_points_source='depth', second_order=second_order)
    config = dataclasses.replace(config, slam=slam)
    record = run_variant('a', frames, sequence.camera, config)
    truth = np.array([f.true_centre for f in frames])
    error = record.centres - truth
    tracked = np.all(np.isfinite(error), axis=1) & np.all(
        np.isfinite(record.pose_covariances), axis=(1, 2)
    )
    nees = [
        float(e @ np.linalg.solve(p[:3, :3], e))
        for e, p in zip(error[tracked], record.pose_covariances[tracked], strict=True)
    ]
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    for index, ids in enumerate(record.measured_ids):
        for track in ids:
            first.setdefault(track, index)
            last[track] = index
    lives = [last[t] - first[t] + 1 for t in first]
    norms = np.linalg.norm(error[tracked], axis=1)
    return {
        'frames': len(frames),
        'tracked': int(tracked.sum()),
        'lost': len(record.lost_frames),
        'final_error_m': float(norms[-1]) if len(norms) else math.nan,
        'rms_error_m': float(np.sqrt(np.mean(norms**2))) if len(norms) else math.nan,
        'position_nees': float(np.mean(nees)) if nees else math.nan,
        'measured_track_life': float(np.mean(lives)) if lives else math.nan,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--sequence', type=Path, default=Path('out/bonn_crowd/sequence'))
    parser.add_argument('--frames', type=int, default=180)
    parser.add_argument('--lives', default='0,15,30,60', help='persistent forms: frames per id')
    parser.add_argument('--pixel-sigma-px', type=float, default=1.0)
    parser.add_argument(
        '--noise-seeds', type=int, default=4, help='noise draws per synthetic form (median)'
    )
    parser.add_argument(
        '--first-order', action='store_true', help='MonoSlamConfig.second_order false'
    )
    args = parser.parse_args(argv)
    sequence = first_frames(read_sequence(args.sequence), args.frames)
    sigma = args.pixel_sigma_px

    def persistent_form(life: int, rng: np.random.Generator) -> Sequence:
        return persistent(sequence, life, sigma, rng)

    # each form draws its noise from its own seeds: a form's figures do not depend on which
    # other forms run
    forms: list[tuple[str, int, Callable[[np.random.Generator], Sequence]]] = [
        ('recorded', -2, lambda _: sequence),
        ('consistent', -1, lambda rng: consistent(sequence, sigma, rng)),
        ('recorded + start kept', ID_STRIDE, lambda rng: start_kept(sequence, sigma, rng)),
    ]
    for life in (int(x) for x in args.lives.split(',')):
        forms.append((f'persistent {life}', life, functools.partial(persistent_form, life)))
    print(
        f'{args.sequence}, frames 0-{args.frames - 1}, variant (a), depth start, '
        f'second_order {not args.first_order}; synthetic forms: median over '
        f'{args.noise_seeds} noise draws'
    )
    print(
        '| form | final error, m | RMS error, m | position NEES (3 dof) '
        '| life of measured tracks, frames | lost (all draws) |'
    )
    print('|---|---|---|---|---|---|')
    for name, key, make in forms:
        draws = 1 if name == 'recorded' else args.noise_seeds
        runs = [
            run(make(np.random.default_rng([seed, key + 2])), not args.first_order)
            for seed in range(draws)
        ]
        figures = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        lost = sum(int(r['lost']) for r in runs)
        print(
            f'| {name} | {figures["final_error_m"]:.3f} | {figures["rms_error_m"]:.3f} | '
            f'{figures["position_nees"]:.1f} | {figures["measured_track_life"]:.1f} | {lost} |'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
