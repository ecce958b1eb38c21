"""Fault table (issue 23), mapper row: SIGKILL of em_sam_mapper mid-run with respawn: true.

Runs em_sam_office_respawn.yaml (``slam_run --processes``, bags/office_moveable.mcap) once
uninterrupted and ``--runs`` times with the mapper killed at a different moment after its
first checkpoint that holds keyframes, each in its own ROS domain, one after the other. A
killed run PASSes when slam_run restarted the mapper, the mapper resumed from its
checkpoint, its final moveable set and landmark map equal the uninterrupted run's (positions
within 1 mm), and the work lost with the process, what came after the last checkpoint, was
at most one checkpoint period old. Prints a markdown table.

    python bench/fault_mapper.py [--runs 3] [--rate 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from bench_common import source_revision

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))
from mapper_fault import (
    BAG,
    CHECKPOINT_PERIOD_S,
    MapperRun,
    landmark_difference_m,
    lost_inputs,
    run,
)

TOLERANCE_M = 1e-3
SAVE_SLACK_S = 1.0  # a save in progress at the kill: its file is the one before


def verdict(killed: MapperRun, reference: MapperRun) -> tuple[bool, str]:
    """PASS/FAIL of one killed run against the uninterrupted one, with the reason."""
    checks = [
        (killed.status == 0, f'slam_run exit {killed.status}'),
        (not lost_inputs(killed.log), 'a node lost inputs'),
        (killed.killed_at_s is not None, 'mapper not killed'),
        ('respawning in' in killed.log, 'no respawn'),
        ('resumed from' in killed.log, 'no resume'),
        (killed.moveable_ids == reference.moveable_ids, 'moveable set differs'),
        (killed.num_keyframes == reference.num_keyframes, 'keyframes differ'),
        (landmark_difference_m(killed, reference) <= TOLERANCE_M, 'landmark map differs'),
        (
            killed.checkpoint_age_s is not None
            and killed.checkpoint_age_s <= CHECKPOINT_PERIOD_S + SAVE_SLACK_S,
            'lost more than a checkpoint period',
        ),
    ]
    failed = [reason for ok, reason in checks if not ok]
    return not failed, ', '.join(failed)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=3, help='killed runs')
    parser.add_argument('--rate', type=float, default=5.0, help='playback rate')
    args = parser.parse_args()
    if not BAG.is_file():
        print(f'{BAG} is missing; see bags/README.md', file=sys.stderr)
        return 2
    domain = 101 + os.getpid() % 120
    with tempfile.TemporaryDirectory(prefix='fault_mapper-') as scratch:
        reference = run(
            Path(scratch) / 'whole', rate=args.rate, kill_after_s=None, domain_id=domain
        )
        if reference.status != 0 or lost_inputs(reference.log):
            print(reference.log[-3000:], file=sys.stderr)
            return 1
        rows = []
        for index in range(args.runs):
            kill_after_s = 1.0 + 2.5 * index
            killed = run(
                Path(scratch) / f'killed{index}',
                rate=args.rate,
                kill_after_s=kill_after_s,
                domain_id=domain,
            )
            rows.append((kill_after_s, killed, *verdict(killed, reference)))
            if not rows[-1][2]:  # what the mapper and slam_run said, for the failure
                lines = [
                    line
                    for line in killed.log.splitlines()
                    if ('em_sam_mapper' in line or 'slam_run' in line) and 'EM-SAM (' not in line
                ]
                print(f'run {index + 1}:', *lines[-40:], sep='\n', file=sys.stderr)
    print(
        f'revision {source_revision()}, {BAG.name} at rate {args.rate:g}, checkpoint '
        f'period {CHECKPOINT_PERIOD_S:g} s; uninterrupted: {reference.num_keyframes} '
        f'keyframes, {len(reference.positions)} landmarks, moveable {reference.moveable_ids}\n'
    )
    print(
        '| run | killed at (s after start) | checkpoint age at kill (s) | keyframes | '
        'moveable set | max landmark difference (m) | result |'
    )
    print('|---|---|---|---|---|---|---|')
    for index, (_, killed, ok, reason) in enumerate(rows):
        killed_at = f'{killed.killed_at_s:.1f}' if killed.killed_at_s is not None else '-'
        age = f'{killed.checkpoint_age_s:.2f}' if killed.checkpoint_age_s is not None else '-'
        same = 'equal' if killed.moveable_ids == reference.moveable_ids else 'differs'
        difference = landmark_difference_m(killed, reference)
        print(
            f'| {index + 1} | {killed_at} | {age} | {killed.num_keyframes} | {same} | '
            f'{difference:.2g} | {"PASS" if ok else "FAIL: " + reason} |'
        )
    return 0 if all(row[2] for row in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
