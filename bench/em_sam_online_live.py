"""Benchmark: EM-SAM online live through the nodes on simulated office runs, paced.

    python bench/em_sam_online_live.py [--seeds 0-9] [--output bench/results]

For each seed: ``office_sim --seed S --variant standard`` writes the run (two offices and a
corridor; 10 desk markers carried from office 1 to office 2 while the robot is in the
corridor), then ``slam_run em_sam_office.yaml --bag RUN --paced --processes
--exit-when-player-done --record REC`` plays it through odometry_ingest and em_sam_mapper
with their defaults (online on), one process per node, each message once the nodes are done
with the last (the same result on an idle and a loaded machine). From the record:

- **flag delay**: for each moved marker, the time (bag clock) of the first
  ``/em_sam/moveable_online`` message that holds it, minus the stamp of its 5th sighting
  after the move (``/landmark_observations``; the move is the second
  ``/ground_truth/landmarks`` message, the moved markers those whose position changed);
- **static flags**: static markers in any ``/em_sam/moveable_online`` message;
- **live = offline**: ``em_sam_evaluate RUN --live-report`` on the mapper's final report:
  the live mapper's moveable set and ATE against the offline EM-SAM robust row.

Acceptance (issue 44): every moved marker flagged within 10 s of its 5th sighting at the
new place; no static marker flagged at any time; the final moveable set equal to the
offline batch's and the ATE within 1 mm. PASS or FAIL per seed and point; any FAIL exits 1.
Writes ``em_sam_online_live.md`` and ``.json`` to ``--output``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import run_meta  # noqa: E402

from em_sam_node.core.em import run_em  # noqa: E402
from em_sam_node.core.em_types import EmConfig  # noqa: E402
from em_sam_node.offline import replay_bag  # noqa: E402
from slam_core.files import write_atomically, write_json  # noqa: E402
from slam_ros.bag.source import BagSource  # noqa: E402
from slam_ros.typesys import TypeRegistry  # noqa: E402

FLAG_DELAY_MAX_S, ATE_TOLERANCE_M, NTH_SIGHTING = 10.0, 1e-3, 5
ONLINE_TOPIC, OBSERVATIONS, TRUTH = (
    '/em_sam/moveable_online',
    '/landmark_observations',
    '/ground_truth/landmarks',
)


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def read(path: Path, topics: list[str]) -> dict[str, list[Any]]:
    """The decoded messages of ``topics`` in a bag, by topic."""
    registry = TypeRegistry()
    result: dict[str, list[Any]] = {topic: [] for topic in topics}
    with BagSource(path) as source:
        present = source.topics()
        wanted = [t for t in topics if t in present]
        for topic in wanted:
            registry.ensure(present[topic].msgtype)
        for message in source.messages(wanted):
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            result[message.topic].append(decoded)
    return result


def scene(run: Path) -> tuple[float, set[int], set[int], dict[int, float]]:
    """The move's time, the moved and the static markers, and each moved marker's
    NTH_SIGHTING-th sighting time after the move."""
    messages = read(run, [TRUTH, OBSERVATIONS])
    before, after = messages[TRUTH][0], messages[TRUTH][-1]
    first = {e.landmark_id: (e.position.x, e.position.y) for e in before.landmarks}
    moved = {
        e.landmark_id
        for e in after.landmarks
        if abs(e.position.x - first[e.landmark_id][0])
        + abs(e.position.y - first[e.landmark_id][1])
        > 1e-6
    }
    move_s = _stamp(after.header)
    seen: dict[int, list[float]] = {}
    for array in messages[OBSERVATIONS]:
        stamp = _stamp(array.header)
        if stamp >= move_s:
            for observation in array.observations:
                seen.setdefault(observation.landmark_id, []).append(stamp)
    nth = {i: seen[i][NTH_SIGHTING - 1] for i in moved if len(seen.get(i, [])) >= NTH_SIGHTING}
    return move_s, moved, set(first) - moved, nth


def run_seed(seed: int, work: Path, domain: int) -> dict[str, Any]:
    """Simulate, play through the nodes, evaluate; the seed's figures."""
    work.mkdir(parents=True, exist_ok=True)
    run, record = work / f'office_seed{seed}.mcap', work / 'record'
    subprocess.run(
        ['office_sim', '--seed', str(seed), '--variant', 'standard', '--output', str(run),
         '--single-file'],
        check=True, capture_output=True,
    )  # fmt: skip
    env = {**os.environ, 'ROS_DOMAIN_ID': str(domain)}
    started = time.perf_counter()
    with (work / 'slam_run.log').open('w') as log:
        subprocess.run(
            ['slam_run', 'em_sam_office.yaml', '--bag', str(run), '--paced', '--processes',
             '--exit-when-player-done', '--record', str(record)],
            check=True, cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
    seconds = time.perf_counter() - started
    report = work / 'out' / 'em_sam' / 'em_sam_report.json'
    evaluation = work / 'evaluation'
    subprocess.run(
        ['em_sam_evaluate', str(run), '--output', str(evaluation), '--no-figures',
         '--live-report', str(report)],
        check=True, capture_output=True,
    )  # fmt: skip
    _, moved, static, nth = scene(run)
    online = read(record, [ONLINE_TOPIC])[ONLINE_TOPIC]
    first_flag: dict[int, float] = {}
    static_flags: dict[int, float] = {}
    for message in online:
        stamp = _stamp(message.header)
        for entry in message.landmarks:
            first_flag.setdefault(entry.landmark_id, stamp)
            if entry.landmark_id in static:
                static_flags.setdefault(entry.landmark_id, stamp)
    delays = {i: (first_flag[i] - nth[i]) if i in first_flag and i in nth else None for i in moved}
    ates = _ates(evaluation)
    offline = run_em(replay_bag(run).data, EmConfig(), record_snapshots=False)
    live_ids = json.loads(report.read_text())['moveable_ids']
    return {
        'seed': seed,
        'wall_s': seconds,
        'moved': sorted(moved),
        'delays_s': {str(k): v for k, v in sorted(delays.items())},
        'static_flags': {str(k): v for k, v in sorted(static_flags.items())},
        'online_messages': len(online),
        'live_moveable': sorted(live_ids),
        'offline_moveable': sorted(offline.landmark_ids[offline.moveable].tolist()),
        'live_ate_m': ates['live_mapper'],
        'offline_ate_m': ates['em_sam_robust'],
    }


def _ates(evaluation: Path) -> dict[str, float]:
    """ATE (m) by method from em_sam_evaluate's results.json."""
    scores = json.loads((evaluation / 'results.json').read_text())['scores']
    return {row['method']: float(row['ate_m']) for row in scores if row['ate_m'] is not None}


def _seeds(text: str) -> list[int]:
    if '-' in text:
        low, high = text.split('-')
        return list(range(int(low), int(high) + 1))
    return [int(s) for s in text.split(',')]


def checks(result: dict[str, Any]) -> list[tuple[str, bool]]:
    """The acceptance points of one seed."""
    late = {k: v for k, v in result['delays_s'].items() if v is None or v > FLAG_DELAY_MAX_S}
    worst = max((v for v in result['delays_s'].values() if v is not None), default=float('nan'))
    ate_gap = abs(result['live_ate_m'] - result['offline_ate_m'])
    return [
        (
            f'every moved marker flagged within {FLAG_DELAY_MAX_S:g} s of its '
            f'{NTH_SIGHTING}th sighting there (worst {worst:.1f} s; late or never: '
            f'{sorted(late) or "none"})',
            not late,
        ),
        (
            f'no static flagged on the way ({result["static_flags"] or "none"})',
            not result['static_flags'],
        ),
        (
            f'live moveable set = offline ({result["live_moveable"]} vs '
            f'{result["offline_moveable"]})',
            result['live_moveable'] == result['offline_moveable'],
        ),
        (f'ATE live - offline {1e3 * ate_gap:.2f} mm <= 1 mm', ate_gap <= ATE_TOLERANCE_M),
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', default='0-9', help="e.g. '0-9' or '1,4'")
    parser.add_argument('--output', type=Path, default=ROOT / 'bench' / 'results')
    parser.add_argument('--work', type=Path, default=None, help='keep the runs here')
    args = parser.parse_args()
    seeds = _seeds(args.seeds)
    work = args.work or Path(tempfile.mkdtemp(prefix='em_sam_online_live_'))
    domain = 100 + os.getpid() % 100
    results, lines = (
        [],
        [
            '# EM-SAM online live through the nodes: simulated office runs, paced',
            '',
            ', '.join(f'{k} {v}' for k, v in run_meta('not pinned').items()),
            '',
        ],
    )
    all_ok = True
    started = time.perf_counter()
    for done, seed in enumerate(seeds):
        result = run_seed(seed, work / f'seed{seed}', domain)
        results.append(result)
        elapsed = time.perf_counter() - started
        eta = elapsed / (done + 1) * (len(seeds) - done - 1)
        print(
            f'em_sam_online_live: seed {seed} done ({done + 1}/{len(seeds)}), '
            f'{result["wall_s"]:.0f} s, ETA {eta:.0f} s',
            file=sys.stderr,
        )
        lines.append(f'## seed {seed} ({result["wall_s"]:.0f} s wall)')
        lines.append('')
        for text, ok in checks(result):
            all_ok &= ok
            lines.append(f'- {"PASS" if ok else "FAIL"}: {text}')
        lines.append('')
        args.output.mkdir(parents=True, exist_ok=True)
        write_atomically(args.output / 'em_sam_online_live.md', '\n'.join(lines))
        write_json(args.output / 'em_sam_online_live.json', {'seeds': results})
    print('\n'.join(lines))
    return 0 if all_ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
