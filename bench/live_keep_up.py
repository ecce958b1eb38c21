"""Does a live pipeline keep up? A live GRAPH run for a while, one process per node and in one
process, with every node's /diagnostics read back.

    python bench/live_keep_up.py [--graph peoplebot_sim_em_sam.yaml] [--duration-s 120]
                                 [--modes processes,one] [--output bench/results]
                                 [--bag BAG [--rate 1.0]]

For each mode, ``slam_run GRAPH`` (``--processes`` or not) runs as a separate process in a
temporary directory; a probe node in this process subscribes to /diagnostics. From the first
camera frame on it waits WARM_UP_S (discovery, the robot starting), then counts over
``--duration-s`` seconds of wall time, then stops the graph with Ctrl-C. The reference, in
the same run, is what the source offered: the frames the simulated camera published
(``peoplebot_sim`` or ``dynamic_scene_sim``). Reported per node, over the window (its last
report minus the one at the start): inputs received and lost (DDS dropped them from a full
queue, or a best-effort sample never came), the node's own drops, its busy share of one core
(time in callbacks over the window) and mean processing time, and the longest processing
time and queue wait (how long a message had waited in its subscription's queue when taken)
of any report in the window; and the ratio of frames the first image node took to the
frames offered. PASS when no node lost or dropped an input in the window with one
process per node, MonoSLAM never lost tracking (its 'lost' count) and the first image node
took frames (from a bag: every image the player published, by an image node of the graph:
a simulator's graph given a bag fails); a graph whose nodes never report fails. ``--modes
one`` alone gives no verdict.

With ``--bag`` the source is a recorded camera: the GRAPH plays BAG at ``--rate`` (1: the
camera's own rate; ``slam_run --bag --rate``, not paced), and the window is the whole bag
(``--duration-s`` defaults to its length at that rate) from the player's first message, with
no warm-up. The reference is then the images the player published, and the feature tracker's
images tracked without MonoSLAM's prediction for them (missing, of which late) are reported
beside it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import run_meta  # noqa: E402

START_TIMEOUT_S = 600.0  # a simulated camera may render its frames first (dynamic_scene_sim)
WARM_UP_S = 10.0  # after the first frame: discovery done, the robot under way
STOP_TIMEOUT_S = 120.0


Snapshot = dict[str, dict[str, str]]
PEAKS = ('processing ms max', 'queue wait ms max')  # per report; their maximum over the window
IMAGE_TOPICS = ('published /camera/image_raw', 'published /camera/image_raw/compressed')


def with_settings(graph: str, settings: list[str], directory: Path) -> str:
    """Return ``graph``, or a copy in ``directory`` with ``node.parameter=value`` settings
    (YAML values) added to the nodes' inline parameters."""
    if not settings:
        return graph
    import yaml

    from slam_bringup.graph_nodes import find_graph

    content = yaml.safe_load(find_graph(graph).read_text(encoding='utf-8'))
    nodes = {node['name']: node for node in content['graph']['nodes']}
    for setting in settings:
        key, _, value = setting.partition('=')
        name, _, parameter = key.partition('.')
        if name not in nodes or not parameter or not value:
            raise SystemExit(
                f'--set {setting!r}: expected node.parameter=value, node in {sorted(nodes)}'
            )
        nodes[name].setdefault('parameters', []).append({parameter: yaml.safe_load(value)})
    path = directory / Path(graph).name
    path.write_text(yaml.safe_dump(content, sort_keys=False), encoding='utf-8')
    return str(path)


def bag_duration_s(bag: Path) -> float:
    """Return the span of a bag's messages, s."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        return float(reader.duration) * 1e-9


def source_started(values: dict[str, str]) -> bool:
    """Whether a source's diagnostics show its first frame: a simulated camera's ``frames
    published`` or the bag player's ``published <topic>``."""
    return any(
        (key == 'frames published' or key.startswith('published ')) and value not in ('', '0')
        for key, value in values.items()
    )


def measure(
    graph: str,
    processes: bool,
    duration_s: float,
    keep_log: Path,
    bag: tuple[Path, float] | None = None,
) -> tuple[Snapshot, Snapshot]:
    """Run ``graph`` live for ``duration_s`` s (``bag``: playing that bag at that rate, no
    warm-up); return each node's /diagnostics values at the start and at the end of the
    window. The graph's log is copied to ``keep_log``."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor

    from slam_ros.qos import output_qos

    rclpy.init()
    node = rclpy.create_node('live_keep_up_probe')
    last: dict[str, dict[str, str]] = {}
    peaks: dict[str, dict[str, float]] = {}  # per node, the window's maximum of PEAKS

    def on_diagnostics(array: DiagnosticArray) -> None:
        for status in array.status:
            values = {value.key: value.value for value in status.values}
            last[status.name] = values
            node_peaks = peaks.setdefault(status.name, {})
            for key in PEAKS:
                if key in values:
                    node_peaks[key] = max(node_peaks.get(key, 0.0), float(values[key]))

    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, output_qos(100))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    command = [sys.executable, '-m', 'slam_bringup.runner', str(graph)]
    command += ['--processes'] if processes else []
    if bag is not None:
        command += ['--bag', str(bag[0].resolve()), '--rate', str(bag[1])]
    with tempfile.TemporaryDirectory(prefix='live_keep_up-') as scratch:
        log = Path(scratch) / 'slam_run.log'
        (Path(scratch) / 'out').mkdir()  # where GRAPH files put their recordings
        with log.open('wb') as out:
            run = subprocess.Popen(command, cwd=scratch, stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + START_TIMEOUT_S
            while not any(source_started(values) for values in last.values()):
                executor.spin_once(timeout_sec=0.1)
                if time.monotonic() > deadline or run.poll() is not None:
                    raise RuntimeError(f'the graph did not start:\n{log.read_text()[-3000:]}')
            warm = time.monotonic() + (WARM_UP_S if bag is None else 0.0)
            while time.monotonic() < warm:
                executor.spin_once(timeout_sec=0.1)
            # a bag is counted from its first message: nothing before it is left out
            first = {} if bag is not None else {k: dict(v) for k, v in last.items()}
            peaks.clear()
            started = time.monotonic()
            next_line = started
            while time.monotonic() - started < duration_s:
                executor.spin_once(timeout_sec=0.1)
                if time.monotonic() >= next_line:
                    done = time.monotonic() - started
                    print(
                        f'live_keep_up: {"processes" if processes else "one process"} '
                        f'{done:.0f}/{duration_s:g} s, ETA {duration_s - done:.0f} s',
                        flush=True,
                    )
                    next_line += 30.0
            snapshot = {name: dict(values) for name, values in last.items()}
            for name, node_peaks in peaks.items():
                snapshot[name].update({key: f'{value:.2f}' for key, value in node_peaks.items()})
        finally:
            run.send_signal(signal.SIGINT)
            try:
                run.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                run.kill()
            executor.shutdown()
            node.destroy_node()
            rclpy.shutdown()
            keep_log.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(log, keep_log)
    return first, snapshot


def _count(values: dict[str, str], prefix: str) -> int:
    return sum(int(v) for k, v in values.items() if k.startswith(prefix) and v.isdigit())


def _number(values: dict[str, str], key: str) -> int:
    value = values.get(key, '0')
    return int(value) if value.isdigit() else 0


def rows(mode: str, first: Snapshot, last: Snapshot, window_s: float) -> tuple[list[str], bool]:
    """Return the table rows of one mode (counts over the ``window_s`` s window: last minus
    first) and whether nothing was lost or dropped in the window."""
    lines, clean = [], True
    for name in sorted(last):
        values, before = last[name], first.get(name, {})
        received = _count(values, 'received ') - _count(before, 'received ')
        lost = _count(values, 'lost ') - _count(before, 'lost ')
        by_input = {
            key.removeprefix('lost '): _number(values, key) - _number(before, key)
            for key in values
            if key.startswith('lost ')
        }
        where = ', '.join(f'{k} {v}' for k, v in sorted(by_input.items()) if v)
        dropped = int(values.get('dropped', '0')) - int(before.get('dropped', '0'))
        # monoslam's 'lost' counts times tracking was lost (the inputs lost are 'lost <input>')
        tracking_lost = _number(values, 'lost') - _number(before, 'lost')
        clean &= lost == 0 and dropped == 0 and tracking_lost == 0
        spent_s = float(values.get('processing s', 0.0)) - float(before.get('processing s', 0.0))
        busy = 100.0 * spent_s / window_s
        if tracking_lost:
            where = ', '.join(filter(None, [where, f'tracking lost {tracking_lost} times']))
        lines.append(
            f'| {mode} | {name} | {received} | {lost}{f" ({where})" if where else ""} '
            f'| {dropped} | {busy:.1f} '
            f'| {values.get("processing ms mean", "")} | {values.get("processing ms max", "")} '
            f'| {values.get("queue wait ms max", "")} |'
        )

    def change(node: str, key: str) -> int:  # a count over the window
        return _number(last.get(node, {}), key) - _number(first.get(node, {}), key)

    pairs = 0  # source/sink pairs found: none when the graph's nodes never reported
    from_bag = False  # a node took the played bag's images (a simulator's graph does not)
    for source, sink, taken_key in (
        ('/peoplebot_sim', '/marker_detector', 'processed'),
        ('/dynamic_scene_sim', '/feature_tracker', 'received image'),
        ('/dynamic_scene_sim', '/monoslam', 'received features'),
        ('/bag_player', '/feature_tracker', 'received image'),
        ('/bag_player', '/monoslam', 'received features'),
    ):
        if source in last and sink in last:
            published = next(
                (key for key in ('frames published', *IMAGE_TOPICS) if key in last[source]), None
            )
            if published is None:
                continue
            offered, taken = change(source, published), change(sink, taken_key)
            pairs += 1
            from_bag |= source == '/bag_player'
            # a node that took nothing is not keeping up; from a bag every image counts
            clean &= taken > 0 and (source != '/bag_player' or taken >= offered)
            late_keys = ('frames late', 'frames skipped', 'skipped')
            late_key = next((key for key in late_keys if key in last[source]), 'frames late')
            late = change(source, late_key)
            lines.append(
                f'| {mode} | {sink} {taken_key} / {source} frames | {taken} / {offered} = '
                f'{taken / max(offered, 1):.3f} | | | {late_key} {late} | | | |'
            )

    if 'predictions skipped (behind)' in last.get('/monoslam', {}):
        lines.append(
            f'| {mode} | /monoslam predictions sent empty (behind: the image before not '
            f'filtered yet) | {change("/monoslam", "predictions skipped (behind)")} | | | | | | |'
        )
    if 'predictions missing' in last.get('/feature_tracker', {}):
        missing, late, tracked = (
            change('/feature_tracker', key)
            for key in ('predictions missing', 'predictions late', 'processed')
        )
        lines.append(
            f'| {mode} | /feature_tracker images tracked without their prediction | '
            f'{missing} of {tracked}; predictions that came after their image: {late} '
            '| | | | | | |'
        )
    if '/bag_player' in last and not from_bag:
        clean = False
        lines.append(
            f"| {mode} | no image node took the bag's images (none in the graph?) | | | | | | | |"
        )
    if not pairs:
        lines.append(
            f'| {mode} | no source and image node reported: nothing measured | | | | | | | |'
        )
    return lines, clean and pairs > 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--graph', default='peoplebot_sim_em_sam.yaml')
    parser.add_argument(
        '--duration-s', type=float, help='window, s (default 120; with --bag the bag at --rate)'
    )
    parser.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='NODE.PARAM=VALUE',
        help='a parameter of a node (repeatable), e.g. dynamic_scene_sim.duration_s=40',
    )
    parser.add_argument('--modes', default='processes,one', help='processes, one, or both')
    parser.add_argument('--bag', type=Path, help='play this bag as the camera (module doc)')
    parser.add_argument('--rate', type=float, default=1.0, help='with --bag: playback rate')
    parser.add_argument(
        '--output',
        type=Path,
        default=ROOT / 'bench' / 'results',
        help="the report (.md) and each mode's graph log (.log) go here",
    )
    args = parser.parse_args()
    bag = None
    if args.bag is not None:
        if not args.bag.exists() or not args.rate > 0:
            raise SystemExit(f'--bag {args.bag}: not found, or --rate {args.rate} not > 0')
        bag = (args.bag, args.rate)
    if args.duration_s is None:
        args.duration_s = 120.0 if bag is None else bag_duration_s(args.bag) / args.rate
    os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 100))
    meta = run_meta('not pinned (the graph uses both cores)')
    table = [
        '| mode | node | received | lost | dropped | busy % | ms mean | ms max '
        '| queue wait ms max |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    verdicts = []
    with tempfile.TemporaryDirectory(prefix='live_keep_up-graph-') as directory:
        graph = with_settings(args.graph, args.set, Path(directory))
        for mode in args.modes.split(','):
            processes = mode.strip() == 'processes'
            name = 'processes' if processes else 'one'
            keep_log = args.output / f'live_keep_up_{Path(args.graph).stem}_{name}.log'
            lines, clean = rows(
                'processes' if processes else 'one process',
                *measure(graph, processes, args.duration_s, keep_log, bag),
                args.duration_s,
            )
            table += lines
            verdicts.append((processes, clean))
    judged = [clean for processes, clean in verdicts if processes]
    passed = bool(judged) and all(judged)
    verdict = 'PASS' if passed else 'FAIL' if judged else 'NO VERDICT (no run with --processes)'

    report = [
        f'# live_keep_up: {args.graph}, {args.duration_s:g} s live'
        + (f', {args.bag.name} at rate {args.rate:g}' if args.bag is not None else '')
        + (f' ({", ".join(args.set)})' if args.set else ''),
        '',
        ', '.join(f'{k} {v}' for k, v in meta.items()),
        '',
        *table,
        '',
        f'**{verdict}**: nothing lost or dropped, tracking never lost, with one process per node',
    ]
    text = '\n'.join(report) + '\n'
    print(text)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / f'live_keep_up_{Path(args.graph).stem}.md').write_text(text, encoding='utf-8')
    return 0 if passed or not judged else 1


if __name__ == '__main__':
    sys.exit(main())
