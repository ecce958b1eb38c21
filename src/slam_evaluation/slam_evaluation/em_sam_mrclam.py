"""em_sam_evaluate --mrclam: EM-SAM on UTIAS MRCLAM robots, scored where there is truth.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import shutil
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em_types import EmResult
from em_sam_node.offline import GroundTruth, read_ground_truth, replay_bag
from slam_core.progress import ProgressReporter
from slam_evaluation.em_sam_metrics import MapError, ate_rmse, robust_map_error
from slam_evaluation.em_sam_runs import (
    flagged_ids,
    run_em_modes,
    solve_all_static,
    timed,
    window_label,
)
from slam_evaluation.mrclam_positives import (
    MIN_PLACE_SIGHTINGS,
    MIN_SEPARATION_M,
    MIN_SIGHTINGS,
    mrclam_positives,
)
from slam_sim.core.mrclam import MrclamRun
from slam_sim.mrclam_bag import load_run, write_mrclam_bag

# Static map errors after alignment are ~0.05-0.2 m on MRCLAM (data set 1 fits to about
# 5 cm once 11 and 17 are exchanged); 0.5 m is several times that: a landmark that far off
# has a wrong identity or a failed solve, not noise.
MAP_OUTLIER_M = 0.5
METHODS = ('plain_sam', 'em_sam_paper', 'em_sam_robust')
NO_VICON = 'n/a: no RobotN_Groundtruth.dat (no Vicon track of the robot)'


@dataclass(frozen=True)
class MrclamScore:
    """One method on one robot and window; ids are MRCLAM subjects; NaN where undefined."""

    dataset: str
    robot: int
    window: str
    method: str
    keyframes: int
    sightings: int
    positives: list[int]
    flagged_robots: list[int]
    robots_missed: list[int]
    static_flagged: list[int]
    ate_m: float
    ate_note: str
    map_median_m: float
    map_max_m: float
    map_far: list[int]
    runtime_s: float


@dataclass
class MrclamRunResult:
    """What one robot and window gave: scores, the data and what the figure needs."""

    name: str
    scores: list[MrclamScore]
    data: MappingData
    truth: GroundTruth
    robust: EmResult
    robust_map: MapError | None
    extras: dict[str, Any] = field(default_factory=dict)


def _map_error(
    ids: np.ndarray, positions: np.ndarray, truth: GroundTruth, negatives: set[int]
) -> MapError | None:
    static_truth = dict(zip(truth.landmark_ids.tolist(), truth.positions_before, strict=True))
    keep = [i for i, lid in enumerate(ids.tolist()) if lid in negatives]
    if len(keep) < 2:
        return None
    truth_xy = np.array([static_truth[int(ids[i])] for i in keep])
    return robust_map_error(ids[keep], positions[keep], truth_xy, outlier_m=MAP_OUTLIER_M)


def _ate(poses: np.ndarray, data: MappingData, truth: GroundTruth) -> tuple[float, str]:
    if not truth.has_poses:
        return float('nan'), NO_VICON
    covered = truth.covers(data.keyframe_stamps_ns)
    if np.count_nonzero(covered) < 2:
        return float('nan'), 'n/a: the Vicon track covers fewer than 2 keyframes'
    true_xy = truth.poses_at(data.keyframe_stamps_ns[covered])[:, :2]
    share = np.count_nonzero(covered) / len(covered)
    note = '' if share == 1.0 else f'over the {100 * share:.0f} % of keyframes Vicon covers'
    return ate_rmse(poses[covered, :2], true_xy), note


def score_run(
    dataset: str,
    robot: int,
    window: str,
    data: MappingData,
    truth: GroundTruth,
    positives: list[int],
) -> MrclamRunResult:
    """Run the methods on one replayed robot and score them against ``positives``."""
    others = [int(i) for i in truth.landmark_ids[truth.moveable].tolist()]
    negatives = set(truth.landmark_ids[~truth.moveable].tolist())
    static = solve_all_static(data)
    outputs: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, set[int] | None, float]] = [
        (
            'plain_sam',
            static.poses,
            static.landmark_ids,
            static.positions,
            None,
            static.runtime_s,
        )
    ]
    em = run_em_modes(data)
    for mode, (runtime, result) in em.items():
        kept = ~result.moveable
        outputs.append(
            (
                f'em_sam_{mode}',
                result.poses,
                result.landmark_ids[kept],
                result.positions[kept],
                flagged_ids(result),
                runtime,
            )
        )
    scores, maps = [], {}
    for method, poses, ids, positions, flagged, runtime in outputs:
        ate, note = _ate(poses, data, truth)
        maps[method] = _map_error(ids, positions, truth, negatives)
        error = maps[method]
        scores.append(
            MrclamScore(
                dataset=dataset,
                robot=robot,
                window=window,
                method=method,
                keyframes=data.num_keyframes,
                sightings=len(data.obs_z),
                positives=positives,
                flagged_robots=sorted(set(others) & flagged) if flagged is not None else [],
                robots_missed=sorted(set(positives) - (flagged or set())),
                static_flagged=sorted(negatives & flagged) if flagged is not None else [],
                ate_m=ate,
                ate_note=note,
                map_median_m=error.median_m if error else float('nan'),
                map_max_m=error.max_m if error else float('nan'),
                map_far=error.far_ids if error else [],
                runtime_s=runtime,
            )
        )
    name = f'{dataset}_robot{robot}_{window.replace(" ", "")}'
    return MrclamRunResult(name, scores, data, truth, em['robust'][1], maps['em_sam_robust'])


def evaluate_run(run: MrclamRun, window_s: float | None, scratch: Path) -> MrclamRunResult:
    """Import one robot's window as a bag in ``scratch``, replay it and score the methods."""
    windowed = run if window_s is None else run.first_seconds(window_s)
    bag = scratch / f'robot{run.robot}_{window_label(window_s).replace(" ", "")}'
    import_s, _ = timed(lambda: write_mrclam_bag(windowed, bag))
    replay_s, replay = timed(lambda: replay_bag(bag))
    truth = read_ground_truth(bag)
    positives = mrclam_positives(windowed, replay.data, whole_run=window_s is None)
    result = score_run(
        run.dataset_dir.name, run.robot, window_label(window_s), replay.data, truth, positives
    )
    result.extras.update(import_s=import_s, replay_s=replay_s, warnings=len(replay.warnings))
    return result


def evaluate_mrclam(
    dataset: Path,
    robots: list[int],
    windows: list[float | None],
    *,
    log: Callable[[str], None] | None = None,
) -> list[MrclamRunResult]:
    """Evaluate every robot in every window of an MRCLAM data set; log progress."""
    say = log if log is not None else (lambda text: print(text, file=sys.stderr))  # noqa: T201
    runs = {robot: load_run(dataset, robot) for robot in robots}
    # the work is the data replayed and solved: seconds of data per run, not the run count
    # (a whole run is 4-6 times a 300 s window)
    seconds = {
        (robot, window_s): _data_seconds(runs[robot], window_s)
        for robot in robots
        for window_s in windows
    }
    progress = ProgressReporter(
        sum(seconds.values()), label='em_sam_evaluate mrclam', unit=' s of data', period_s=0.0
    )
    results = []
    done_s = 0.0
    with tempfile.TemporaryDirectory(prefix='em_sam_mrclam_') as scratch:
        for robot in robots:
            for window_s in windows:
                result = evaluate_run(runs[robot], window_s, Path(scratch))
                robust = next(s for s in result.scores if s.method == 'em_sam_robust')
                say(
                    f'em_sam_evaluate: {result.name}: {robust.keyframes} keyframes, '
                    f'{robust.sightings} sightings; import {result.extras["import_s"]:.1f} s, '
                    f'replay {result.extras["replay_s"]:.1f} s, EM robust '
                    f'{robust.runtime_s:.1f} s'
                )
                results.append(result)
                done_s += seconds[robot, window_s]
                progress.update(done_s)
                for path in Path(scratch).iterdir():  # bags are big; keep one at a time
                    shutil.rmtree(path)
    progress.finish()
    return results


def _data_seconds(run: MrclamRun, window_s: float | None) -> float:
    """Seconds of odometry in ``run``'s window (the whole run for None)."""
    stamps = run.odometry.stamps_ns
    whole_s = (int(stamps[-1]) - int(stamps[0])) / 1e9 if len(stamps) else 0.0
    return whole_s if window_s is None else min(window_s, whole_s)


def _ids(values: list[int]) -> str:
    return ', '.join(str(v) for v in values) if values else '-'


def _metre(value: float) -> str:
    return 'n/a' if not np.isfinite(value) else f'{value:.3f}'


def markdown(results: list[MrclamRunResult]) -> str:
    """Return the MRCLAM results as a Markdown table with notes."""
    lines = [
        '| run | window | method | keyframes | robots flagged / positives | robots missed '
        '| static flagged | ATE m | map median m | map max m | landmarks > '
        f'{MAP_OUTLIER_M} m off | runtime s |',
        '|---|---|---|---:|---:|---|---|---:|---:|---:|---|---:|',
    ]
    notes: set[str] = set()
    for result in results:
        for s in result.scores:
            em = s.method != 'plain_sam'
            hits = f'{len(set(s.flagged_robots) & set(s.positives))} / {len(s.positives)}'
            lines.append(
                f'| {s.dataset} robot {s.robot} | {s.window} | {s.method} | {s.keyframes} | '
                f'{hits if em else "-"} | {_ids(s.robots_missed) if em else "-"} | '
                f'{_ids(s.static_flagged) if em else "-"} | {_metre(s.ate_m)} | '
                f'{_metre(s.map_median_m)} | {_metre(s.map_max_m)} | {_ids(s.map_far)} | '
                f'{s.runtime_s:.2f} |'
            )
            if s.ate_note:
                notes.add(f'{s.dataset} robot {s.robot} ({s.window}): ATE {s.ate_note}')
    lines += [
        '',
        f'Positives: the other robots that the Vicon tracks put at two places more than '
        f'{MIN_SEPARATION_M} m apart with {MIN_PLACE_SIGHTINGS} sightings each; without '
        f'tracks, in whole runs only, those sighted at least {MIN_SIGHTINGS} times; '
        'negatives: the static barcodes (subjects 6-20). Map errors after an SE(2) alignment '
        f'fitted on the landmarks within {MAP_OUTLIER_M} m (those further off are named).',
        '',
        *[f'- {note}' for note in sorted(notes)],
        '',
        'Odometry calibration the robust mode estimated (translation scale, rotation scale):',
        '',
        *[
            f'- {r.scores[0].dataset} robot {r.scores[0].robot} ({r.scores[0].window}): '
            + ', '.join(f'{v:.3f}' for v in r.robust.odometry_calibration)
            for r in results
            if r.scores
        ],
    ]
    return '\n'.join(lines)
