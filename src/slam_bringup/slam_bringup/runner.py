"""slam_run: run a GRAPH's nodes, in one process or one per node (docs/design/bringup.md)."""

from __future__ import annotations

import argparse
import ctypes
import importlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import try_shutdown

from slam_bringup.bag_player import BagPlayerNode
from slam_bringup.bag_recorder import DRAIN_TIMEOUT_S, BagRecorderNode
from slam_bringup.drain import DrainWatch, listen
from slam_bringup.graph import load_graph
from slam_bringup.graph_nodes import (
    NodeDescription,
    bundled_graphs_help,
    find_graph,
    node_descriptions,
    ros_arguments,
    with_overrides,
)
from slam_bringup.graph_types import Graph
from slam_bringup.keep_up import KeepUpHint, keep_up_options, start_note
from slam_bringup.supervise import Respawner, failing_node, warn_if_respawn_ignored
from slam_core.blas import single_threaded_blas
from slam_core.cli import EXIT_INTERRUPTED, EXIT_USER_ERROR, console_main, positive_float
from slam_core.errors import SlamError
from slam_ros.diagnostics import Diagnostics
from slam_ros.progress import PACED_ENV
from slam_ros.spin import TakeSafeExecutor

EXIT_NODE_FAILED = 1
POLL_S = 0.05
QUIET_S = 0.25  # the recorder has drained when nothing new arrived for this long
NODES_DRAIN_TIMEOUT_S = 60.0  # the longest the nodes may take to work off their queued inputs
NODES_QUIET_S = 2.0  # drained: no input for this long, twice odometry_ingest's idle flush (1 s)
INTERRUPT_TIMEOUT_S = 60.0  # then SIGTERM; the mapper's last solve and report take this long
WAIT_LOG_PERIOD_S = 10.0  # meanwhile the nodes still running are named this often
TERMINATE_TIMEOUT_S = 5.0  # then SIGKILL
SPIN_WAKE_S = 0.1  # the executor thread looks for a stop this often when idle
CLEAN_STOP_CODES = frozenset({0, 130, 143, -signal.SIGINT, -signal.SIGTERM})
STOP_ORDER = {'player': 0, 'node': 1, 'recorder': 2}


def say(message: str) -> None:
    """Print a status line of the runner on stderr."""
    print(f'slam_run: {message}', file=sys.stderr, flush=True)  # noqa: T201


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """Set ``stop`` on SIGINT and SIGTERM inside the block (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def request_stop(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


# -- in one process -----------------------------------------------------------------------
class Spinner:
    """Spins an executor in a background thread; keeps the exception that ended it."""

    def __init__(self, executor: SingleThreadedExecutor) -> None:
        self.executor = executor
        self.error: BaseException | None = None
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._spin, name='slam_run-executor', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            while not self._stopping.is_set() and self.executor.context.ok():
                self.executor.spin_once(timeout_sec=SPIN_WAKE_S)
        except ExternalShutdownException:
            pass
        except BaseException as err:  # a node callback raised; reported by the runner
            self.error = err

    def stop(self) -> None:
        """Stop spinning, wait for the thread, then shut the executor down (its shutdown
        destroys the guard conditions a spinning thread waits on)."""
        self._stopping.set()
        self._thread.join(timeout=TERMINATE_TIMEOUT_S)
        self.executor.shutdown(timeout_sec=TERMINATE_TIMEOUT_S)


def node_class(graph: Graph, description: NodeDescription) -> Callable[..., Node]:
    """Import the ``module:Class`` of a node (raises GraphError naming the plugin key)."""
    key = f'{description.key}.plugin'
    if description.plugin is None:
        raise graph.error(
            key,
            'not set; running in one process needs the node class '
            "('module:Class'), or run with --processes",
        )
    module_name, _, class_name = description.plugin.partition(':')
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise graph.error(key, f'cannot import {module_name!r}: {err}') from None
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise graph.error(key, f'{description.plugin!r} is not an rclpy Node class')
    return cls


def construct(graph: Graph, description: NodeDescription, context: Context, scratch: Path) -> Node:
    """Construct one node; a SlamError or a rejected argument becomes a GraphError."""
    cls = node_class(graph, description)
    try:
        return cls(
            context=context,
            cli_args=ros_arguments(description, scratch),
            use_global_arguments=False,
        )
    except SlamError as err:
        raise graph.error(description.key, f'node {description.name!r}: {err}') from None
    except _rclpy.RCLError as err:
        first_line = str(err).strip().splitlines()[0]
        raise graph.error(description.key, f'node {description.name!r}: {first_line}') from None


def wait_for_end(
    graph: Graph, player: BagPlayerNode | None, spinner: Spinner, stop: threading.Event
) -> bool:
    """Wait for a stop request, a failed callback or the player; True if the player ended it."""
    announced = False
    while not stop.wait(POLL_S):
        if spinner.error is not None:
            return False
        if player is not None and player.finished.is_set():
            if player.error is not None or graph.exit_when_player_done:
                return True
            if not announced:
                say('the player has finished; Ctrl-C stops the graph')
                announced = True
    return False


def wait_until_drained(recorder: BagRecorderNode) -> None:
    """Wait until the recorder got nothing new for QUIET_S (at most DRAIN_TIMEOUT_S)."""
    deadline = time.monotonic() + DRAIN_TIMEOUT_S
    count = recorder.writer.message_count
    quiet_since = time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - quiet_since < QUIET_S:
        time.sleep(POLL_S)
        if recorder.writer.message_count != count:
            count = recorder.writer.message_count
            quiet_since = time.monotonic()


def processing_nodes(descriptions: Sequence[NodeDescription]) -> list[str]:
    """The fully qualified names of the graph's nodes (not its player and recorder)."""
    return [d.fully_qualified_name for d in descriptions if d.role == 'node']


def wait_until_quiet(
    watch: DrainWatch, stop: threading.Event, failed: Callable[[], bool] = lambda: False
) -> None:
    """Wait until the nodes are quiet (``drain``), a stop, ``failed()`` or the drain timeout."""
    since = time.monotonic()
    while not stop.wait(POLL_S):
        now = time.monotonic()
        busy = watch.busy(since, now)
        if failed():
            return
        if not busy:
            silent = watch.silent()
            if silent:
                say(f'not waited for (no report on /diagnostics): {", ".join(silent)}')
            return
        if now - since >= NODES_DRAIN_TIMEOUT_S:
            say(
                f'warning: still busy after {NODES_DRAIN_TIMEOUT_S:g} s (an input taken in '
                f'the last {NODES_QUIET_S:g} s, or no recent report on /diagnostics): '
                f'{", ".join(busy)}; stopping the graph with their queued inputs unprocessed'
            )
            return
    say('interrupted: stopping the nodes without waiting for their queued inputs')


def publish_final_reports(nodes: Sequence[Node]) -> None:
    """Have each node's ``Diagnostics`` publish its whole-run report; give it QUIET_S to go out."""
    reports = [getattr(node, 'diagnostics', None) for node in nodes]
    published = [report for report in reports if isinstance(report, Diagnostics)]
    for diagnostics in published:
        diagnostics.publish()
    if published:
        time.sleep(QUIET_S)


def run_in_process(
    graph: Graph, descriptions: Sequence[NodeDescription], scratch: Path, stop: threading.Event
) -> int:
    """Run every node in this process until the graph ends; return the exit status."""
    warn_if_respawn_ignored(descriptions, say)
    context = Context()
    single_threaded_blas()
    rclpy.init(args=['slam_run'], context=context, signal_handler_options=SignalHandlerOptions.NO)
    executor = TakeSafeExecutor(context=context)
    watch = DrainWatch(processing_nodes(descriptions), NODES_QUIET_S)
    hint = KeepUpHint(watch.names, keep_up_options(graph.player, processes=False), say)
    listener = listen(context, watch, hint.add)
    executor.add_node(listener)
    nodes: list[tuple[NodeDescription, Node]] = []
    spinner: Spinner | None = None
    try:
        for description in descriptions:
            node = construct(graph, description, context, scratch)
            nodes.append((description, node))
            executor.add_node(node)
        player = next((n for _, n in nodes if isinstance(n, BagPlayerNode)), None)
        recorder = next((n for _, n in nodes if isinstance(n, BagRecorderNode)), None)
        spinner = running = Spinner(executor)
        player_ended = wait_for_end(graph, player, spinner, stop)
        if player is not None:
            player.stop()
            if player_ended and player.error is None:
                wait_until_quiet(watch, stop, lambda: running.error is not None)
        publish_final_reports([node for _, node in nodes if node is not recorder])
        summary = finish_playback_and_recording(player, recorder)
    finally:
        if spinner is not None:
            spinner.stop()
        else:
            executor.shutdown(timeout_sec=TERMINATE_TIMEOUT_S)
        for _, node in sorted(nodes, key=lambda item: STOP_ORDER[item[0].role]):
            node.destroy_node()  # a recorder finalizes its bag here if still open
        listener.destroy_node()
        try_shutdown(context=context)
    for line in summary:
        print(f'slam_run: {line}')  # noqa: T201
    if spinner.error is not None:
        traceback.print_exception(spinner.error)
        culprit = failing_node(spinner.error, nodes)
        say(
            f'error: {culprit or "a node"}: a callback raised '
            f'{type(spinner.error).__name__}: {spinner.error}'
        )
        return EXIT_NODE_FAILED
    if player is not None and player.error is not None:
        raise player.error
    return EXIT_INTERRUPTED if graph.exit_when_player_done and not player_ended else 0


def finish_playback_and_recording(
    player: BagPlayerNode | None, recorder: BagRecorderNode | None
) -> list[str]:
    """Stop the player, drain and finalize the recorder (executor spinning); return summaries."""
    summary = []
    if player is not None:
        player.stop()
        summary.append(f'bag_player: {player.summary()}')
    if recorder is not None:
        wait_until_drained(recorder)
        path = recorder.finalize()
        publish_final_reports([recorder])
        counts = ', '.join(f'{t}: {n}' for t, n in sorted(recorder.writer.counts.items()))
        summary.append(
            f'bag_recorder: wrote {recorder.writer.message_count} messages to '
            f'{str(path)!r} ({counts or "no topics"})'
        )
    return summary


# -- one process per node -----------------------------------------------------------------
@dataclass
class Child:
    """A node process and what is known about its end."""

    description: NodeDescription
    process: subprocess.Popen[bytes]
    reported: bool = False


def executable(graph: Graph, description: NodeDescription) -> str:
    """Find ``lib/<package>/<executable>`` under AMENT_PREFIX_PATH, else on PATH."""
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        candidate = Path(prefix) / 'lib' / description.package / description.executable
        if prefix and candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    found = shutil.which(description.executable)
    if found is None:
        raise graph.error(
            f'{description.key}.executable',
            f'{description.executable!r} is in neither lib/{description.package}/ of '
            'AMENT_PREFIX_PATH nor PATH; build the workspace and source scripts/env.sh',
        )
    return found


def _die_with_parent() -> Callable[[], None] | None:
    """A pre-exec hook that gives the child SIGTERM when slam_run dies (Linux; else None)."""
    if sys.platform != 'linux':
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl
    set_parent_death_signal = 1  # PR_SET_PDEATHSIG
    return lambda: prctl(set_parent_death_signal, signal.SIGTERM)


def start_children(
    graph: Graph, descriptions: Sequence[NodeDescription], scratch: Path, children: list[Child]
) -> None:
    """Start one process per node, appending each to ``children`` as it starts."""
    for description in descriptions:
        executable(graph, description)  # every executable found before any starts
    for description in descriptions:
        children.append(start_child(graph, description, scratch))


def start_child(graph: Graph, description: NodeDescription, scratch: Path) -> Child:
    """Start one node's process."""
    command = [
        executable(graph, description),
        *description.arguments,
        *ros_arguments(description, scratch),
    ]
    process = subprocess.Popen(
        command, stdin=subprocess.DEVNULL, process_group=0, preexec_fn=_die_with_parent()
    )
    return Child(description, process)


def exited(children: Sequence[Child]) -> Iterator[tuple[Child, int]]:
    """Yield the children that have exited since the last call, with their exit code."""
    for child in children:
        code = child.process.poll()
        if code is not None and not child.reported:
            child.reported = True
            yield child, code


def watch_children(
    graph: Graph, children: list[Child], stop: threading.Event, respawner: Respawner
) -> tuple[bool, Child | None]:
    """Wait for a stop, the player's end or a failed child: (player ended it, failed child)."""
    while not stop.wait(POLL_S):
        respawner.poll(children)  # type: ignore[arg-type]
        for child, code in exited(children):
            if respawner.exited(children, children.index(child), code):
                continue
            if code != 0:
                return False, child
            if child.description.role == 'player' and graph.exit_when_player_done:
                return True, None
            say(f'node {child.description.name!r} exited')
        if all(child.reported for child in children) and not respawner.waiting:
            return False, None
    return False, None


def drain_children(
    children: list[Child], watch: DrainWatch, stop: threading.Event, respawner: Respawner
) -> Child | None:
    """Wait until the nodes are quiet; return a child that failed meanwhile, if any."""
    failure: list[Child] = []

    def failed() -> bool:
        respawner.poll(children)  # type: ignore[arg-type]
        for child, code in exited(children):
            if respawner.exited(children, children.index(child), code):
                continue
            if code != 0:
                failure.append(child)
                return True
            say(f'node {child.description.name!r} exited')
            watch.forget(child.description.fully_qualified_name)
        return False

    wait_until_quiet(watch, stop, failed)
    return failure[0] if failure else None


def wait_for(children: Sequence[Child], timeout_s: float) -> None:
    """Wait up to ``timeout_s`` for ``children`` to exit, naming those still running."""
    deadline = (start := time.monotonic()) + timeout_s
    while True:
        say_at = min(time.monotonic() + WAIT_LOG_PERIOD_S, deadline)
        for child in children:
            with suppress(subprocess.TimeoutExpired):
                child.process.wait(timeout=max(say_at - time.monotonic(), 0.0))
        running = [c.description.name for c in children if c.process.poll() is None]
        if not running or time.monotonic() >= deadline:
            return
        say(f'waiting for {", ".join(running)} to finish ({time.monotonic() - start:.0f} s)')


def stop_children(children: Sequence[Child]) -> list[Child]:
    """Stop the player, nodes, recorder in turn (SIGINT, TERM, KILL); return those that failed."""
    failed: list[Child] = []
    for rank in sorted(set(STOP_ORDER.values())):
        group = [c for c in children if STOP_ORDER[c.description.role] == rank]
        for sig, timeout_s in (
            (signal.SIGINT, INTERRUPT_TIMEOUT_S),
            (signal.SIGTERM, TERMINATE_TIMEOUT_S),
            (signal.SIGKILL, TERMINATE_TIMEOUT_S),
        ):
            running = [c for c in group if c.process.poll() is None]
            for child in running:
                if sig != signal.SIGINT:
                    say(f'node {child.description.name!r} did not stop; sending {sig.name}')
                with suppress(ProcessLookupError):
                    os.killpg(child.process.pid, sig)
            wait_for(running, timeout_s)
        failed += [
            c for c in group if not c.reported and c.process.returncode not in CLEAN_STOP_CODES
        ]
    return failed


def run_processes(
    graph: Graph, descriptions: Sequence[NodeDescription], scratch: Path, stop: threading.Event
) -> int:
    """Run one process per node until the graph ends; return the exit status."""
    children: list[Child] = []
    failed: list[Child] = []
    failure: Child | None = None
    context = Context()
    rclpy.init(args=['slam_run'], context=context, signal_handler_options=SignalHandlerOptions.NO)
    watch = DrainWatch(processing_nodes(descriptions), NODES_QUIET_S)
    hint = KeepUpHint(watch.names, keep_up_options(graph.player, processes=True), say)
    listener = listen(context, watch, hint.add)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener)
    spinner = Spinner(executor)
    try:
        respawner = Respawner(lambda d: start_child(graph, d, scratch), say)
        start_children(graph, descriptions, scratch, children)
        player_ended, failure = watch_children(graph, children, stop, respawner)
        if player_ended and failure is None:
            failure = drain_children(children, watch, stop, respawner)
        if failure is not None:
            failed.append(failure)
    finally:
        failed += stop_children(children)
        spinner.stop()
        listener.destroy_node()
        try_shutdown(context=context)
    for child in children:
        print(  # noqa: T201
            f'slam_run: {child.description.name}: exit code {child.process.returncode}'
        )
    for index, child in enumerate(failed):
        error = graph.error(
            child.description.key,
            f'node {child.description.name!r} exited with code {child.process.returncode}',
        )
        if index == 0 or failure is None:
            say(f'error: {error}')
        else:
            # Stopped because of the first failure: a child still starting Python when it
            # gets SIGINT dies with code 1. Reported, but the error line names the cause.
            say(f'while stopping after that error: {error}')
    if failed:
        first = failed[0].process.returncode
        return EXIT_USER_ERROR if first == EXIT_USER_ERROR else EXIT_NODE_FAILED
    return EXIT_INTERRUPTED if graph.exit_when_player_done and not player_ended else 0


# -- command line -------------------------------------------------------------------------
def build_arg_parser() -> argparse.ArgumentParser:
    """Command-line options of slam_run."""
    parser = argparse.ArgumentParser(
        prog='slam_run',
        description='Run the nodes of a GRAPH file (the graph that graph.launch.py launches).',
        epilog=bundled_graphs_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument('graph', help="GRAPH file, or the name of one in slam_bringup's graphs/")
    parser.add_argument(
        '--processes', action='store_true', help='one process per node (default: one process)'
    )
    parser.add_argument(
        '--exit-when-player-done', action='store_true', help='stop once the bag has played'
    )
    parser.add_argument('--bag', type=Path, help="bag to play (replaces the GRAPH's player.bag)")
    parser.add_argument('--rate', type=positive_float, help='playback speed factor')
    parser.add_argument(
        '--paced',
        action='store_true',
        help='paced replay: the player publishes each message once the nodes are done with '
        'the last (the same result on an idle and on a loaded machine)',
    )
    parser.add_argument(
        '--record', type=Path, metavar='PATH', help='bag to record to (replaces recorder.output)'
    )
    return parser


@console_main('slam_run')
def main(argv: list[str] | None = None) -> int:
    """Run a GRAPH until it ends; exit 0 done, 1 a node failed, 2 a user error, 130 interrupted."""
    args = build_arg_parser().parse_args(sys.argv[1:] if argv is None else argv)
    graph = with_overrides(
        load_graph(find_graph(args.graph)),
        bag=args.bag,
        rate=args.rate,
        record=args.record,
        exit_when_player_done=args.exit_when_player_done,
        paced=args.paced,
    )
    descriptions = node_descriptions(graph)
    if graph.player is not None and graph.player.paced:
        os.environ[PACED_ENV] = '1'  # the nodes report their progress (slam_ros.progress)
    if not descriptions:
        raise graph.error('graph', 'has no nodes, player or recorder to run')
    mode = 'one process per node' if args.processes else 'one process'
    say(f'running {str(graph.path)!r} ({len(descriptions)} nodes, {mode})')
    note = start_note(keep_up_options(graph.player, processes=args.processes))
    if note is not None and graph.player is not None:
        say(note)
    stop = threading.Event()
    with tempfile.TemporaryDirectory(prefix='slam_run-') as scratch, stop_on_signals(stop):
        run = run_processes if args.processes else run_in_process
        return run(graph, descriptions, Path(scratch), stop)


if __name__ == '__main__':
    sys.exit(main())
