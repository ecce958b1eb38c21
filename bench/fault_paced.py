"""Fault table, paced replay: the same result on an idle and on a fully loaded machine.

    python bench/fault_paced.py [--runs 5] [--graph em_sam_office_camera.yaml]
                                [--bag bags/office_camera.mcap] [--processes]
                                [--idle-runs N] [--loaded-runs N] [--json FILE]

Runs ``slam_run GRAPH --bag BAG --paced --exit-when-player-done`` ``--runs`` times on an idle
machine (``--idle-runs``), then ``--runs`` times (``--loaded-runs``) with one busy-loop
process pinned to each core (taskset), each
run in its own temporary directory and ROS domain, and reads the mapper's report
(out/<report_dir>/em_sam_report.json): keyframes, landmarks and the moveable set. PASS when
every run gives the same keyframe stamps and the same moveable set, and no run's player
timed out waiting for the graph. Prints a markdown table; exits 1 on FAIL.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUN_TIMEOUT_S = 1800.0


def busy_loop() -> None:
    while True:
        pass


def start_load() -> list[multiprocessing.Process]:
    """One busy loop per core, pinned to it."""
    loads = []
    for core in range(os.cpu_count() or 1):
        process = multiprocessing.Process(target=busy_loop, daemon=True)
        process.start()
        assert process.pid is not None
        os.sched_setaffinity(process.pid, {core})
        loads.append(process)
    return loads


def one_run(args: argparse.Namespace, index: int, loaded: bool) -> dict[str, object]:
    with tempfile.TemporaryDirectory(prefix='fault_paced-') as scratch:
        command = [
            sys.executable, '-m', 'slam_bringup.runner', args.graph, '--bag', str(args.bag),
            '--paced', '--exit-when-player-done', *(['--processes'] if args.processes else []),
        ]  # fmt: skip
        env = {**os.environ, 'ROS_DOMAIN_ID': str(150 + index), 'PYTHONUNBUFFERED': '1'}
        loads = start_load() if loaded else []
        started = time.monotonic()
        try:
            result = subprocess.run(
                command, cwd=scratch, env=env, capture_output=True, text=True,
                timeout=RUN_TIMEOUT_S, check=False,
            )  # fmt: skip
        finally:
            for load in loads:
                load.kill()
        elapsed = time.monotonic() - started
        reports = list(Path(scratch, 'out').glob('*/em_sam_report.json'))
        if result.returncode != 0 or len(reports) != 1:
            return {'ok': False, 'why': f'exit {result.returncode}: {result.stderr[-400:]}'}
        report = json.loads(reports[0].read_text())
        text = result.stdout + result.stderr
        return {
            'ok': 'paced (0 waits for the graph timed out)' in text,
            'loaded': loaded,
            'seconds': elapsed,
            'keyframes': report['num_keyframes'],
            'stamps': report['trajectory']['stamps_ns'],
            'landmarks': report['num_landmarks'],
            'moveable': report['moveable_ids'],
        }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--graph', default='em_sam_office_camera.yaml')
    parser.add_argument('--bag', type=Path, default=ROOT / 'bags' / 'office_camera.mcap')
    parser.add_argument('--processes', action='store_true', help='one process per node')
    parser.add_argument('--idle-runs', type=int, help='runs without load (default --runs)')
    parser.add_argument('--loaded-runs', type=int, help='runs with load (default --runs)')
    parser.add_argument('--json', type=Path, help='write every run here')
    args = parser.parse_args()
    idle = args.runs if args.idle_runs is None else args.idle_runs
    loaded_runs = args.runs if args.loaded_runs is None else args.loaded_runs
    runs = []
    plan = [False] * idle + [True] * loaded_runs
    for index, loaded in enumerate(plan):
        run = one_run(args, index, loaded)
        state = 'loaded' if loaded else 'idle'
        print(
            f'fault_paced: run {index + 1}/{len(plan)} ({state}): '
            f'{ {k: v for k, v in run.items() if k != "stamps"} }',
            flush=True,
        )
        runs.append(run)
        if args.json is not None:
            args.json.write_text(json.dumps(runs))
    good = [run for run in runs if run.get('ok')]
    same = bool(good) and all(
        run['stamps'] == good[0]['stamps'] and run['moveable'] == good[0]['moveable']
        for run in good
    )
    verdict = 'PASS' if len(good) == len(runs) and same else 'FAIL'
    print('\n| runs | state | seconds | keyframes | landmarks | moveable | ok |')
    print('|---:|---|---:|---:|---:|---|---|')
    for index, run in enumerate(runs, start=1):
        state = 'loaded' if run.get('loaded') else 'idle'
        print(
            f'| {index} | {state} | {run.get("seconds", 0):.0f} | {run.get("keyframes", "-")} '
            f'| {run.get("landmarks", "-")} | {run.get("moveable", "-")} | {run.get("ok")} |'
        )
    print(
        f'\n**{verdict}**: {args.graph} on {args.bag.name}, paced, '
        f'{"--processes" if args.processes else "one process"}: identical keyframe stamps '
        f'and moveable set on {len(runs)} runs ({idle} idle, {loaded_runs} with a busy '
        'loop on each core), no wait for the graph timed out'
    )
    return 0 if verdict == 'PASS' else 1


if __name__ == '__main__':
    sys.exit(main())
