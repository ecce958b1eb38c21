"""The drain rule of slam_run (``slam_bringup.drain``): which nodes of a graph are still busy,
from what they report on /diagnostics (statuses built here, with the times they arrive)."""

from __future__ import annotations

import threading

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from slam_bringup import runner
from slam_bringup.drain import DrainWatch
from slam_bringup.graph_nodes import NodeDescription
from slam_ros.diagnostics import IDLE_KEY

QUIET_S = 2.0


def report(name: str, idle_s: float | None, **values: str) -> DiagnosticArray:
    """A /diagnostics message with the status of node ``name``."""
    if idle_s is not None:
        values[IDLE_KEY] = f'{idle_s:.3f}'
    status = DiagnosticStatus(
        name=name, values=[KeyValue(key=key, value=value) for key, value in values.items()]
    )
    return DiagnosticArray(status=[status])


def feed(watch: DrainWatch, name: str, reports: list[tuple[float, float]]) -> None:
    """Reports of ``name`` as (arrival time, idle seconds)."""
    for at_s, idle_s in reports:
        watch.add(report(name, idle_s), at_s)


def test_a_node_is_quiet_after_two_regular_reports_without_input() -> None:
    watch = DrainWatch(['/ingest'], QUIET_S)
    feed(watch, '/ingest', [(10.0, 0.1), (11.0, 1.1), (12.0, 2.1)])
    assert watch.busy(0.0, 12.1) == ['/ingest']  # the report before said 1.1 s
    feed(watch, '/ingest', [(13.0, 3.1)])
    assert watch.busy(0.0, 13.1) == []
    assert watch.busy(0.0, 14.6) == ['/ingest']  # no report for longer than a period and jitter
    feed(watch, '/ingest', [(15.0, 0.2)])  # took an input again
    assert watch.busy(0.0, 15.1) == ['/ingest']


def test_reports_far_apart_mean_a_long_callback_in_between() -> None:
    """A 3 s solve held the executor between the two reports: messages may have queued for
    the node meanwhile, which it takes after the second report; wait for the next pair."""
    watch = DrainWatch(['/mapper'], QUIET_S)
    feed(watch, '/mapper', [(10.0, 2.5), (13.0, 5.5)])
    assert watch.busy(0.0, 13.1) == ['/mapper']
    feed(watch, '/mapper', [(14.0, 0.5)])  # it took the queued messages
    assert watch.busy(0.0, 14.1) == ['/mapper']
    feed(watch, '/mapper', [(15.0, 1.5), (16.0, 2.5), (17.0, 3.5)])
    assert watch.busy(0.0, 17.1) == []


def test_every_node_must_be_quiet_and_only_the_graphs_nodes_count() -> None:
    watch = DrainWatch(['/ingest', '/mapper'], QUIET_S)
    feed(watch, '/ingest', [(10.0, 3.0), (11.0, 4.0)])
    feed(watch, '/mapper', [(10.5, 1.0), (11.5, 2.0)])
    assert watch.busy(0.0, 11.6) == ['/mapper']
    # the recorder records /diagnostics: it takes an input every second, for ever; the
    # player, other graphs' nodes, and a node of the graph that reports without IDLE_KEY
    # (not slam_ros.diagnostics) are not waited for either
    for at_s in (10.2, 11.2, 12.2):
        watch.add(report('/bag_recorder', 0.01), at_s)
        watch.add(report('/bag_player', 0.0), at_s)
        watch.add(report('/other_graph/mapper', 0.0), at_s)
        watch.add(report('/mapper', None, **{'frequency hz': '10'}), at_s)
    feed(watch, '/mapper', [(12.5, 3.0)])
    feed(watch, '/ingest', [(12.0, 5.0)])
    assert watch.busy(0.0, 12.6) == []


def test_a_node_that_has_not_reported_is_waited_for_a_while() -> None:
    """Its first report comes a period after it started; one that never reports (no
    slam_ros.diagnostics) is not waited for after ``silent_s``."""
    watch = DrainWatch(['/ingest', '/driver'], QUIET_S, silent_s=3.0)
    assert watch.busy(10.0, 10.0) == ['/driver', '/ingest']
    feed(watch, '/ingest', [(11.0, 0.5), (12.0, 2.5)])
    assert watch.busy(10.0, 12.9) == ['/driver', '/ingest']
    feed(watch, '/ingest', [(13.0, 3.5)])
    assert watch.busy(10.0, 13.1) == []
    assert watch.silent() == ['/driver']


def test_the_gap_must_be_shorter_than_the_quiet_time() -> None:
    with pytest.raises(ValueError, match='max_gap_s'):
        DrainWatch(['/a'], quiet_s=1.0, max_gap_s=1.5)


def test_processing_nodes_are_the_graphs_nodes_without_player_and_recorder() -> None:
    def description(role: str, name: str, namespace: str = '') -> NodeDescription:
        return NodeDescription(
            key=role, role=role, name=name, package='p', executable='e', plugin=None,
            namespace=namespace, parameters=(), remappings=(),
        )  # fmt: skip

    descriptions = [
        description('player', 'bag_player'),
        description('node', 'mapper', '/robot'),
        description('node', 'ingest'),
        description('recorder', 'bag_recorder'),
    ]
    assert runner.processing_nodes(descriptions) == ['/robot/mapper', '/ingest']


def test_waiting_ends_with_a_warning_naming_the_busy_nodes(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(runner, 'NODES_DRAIN_TIMEOUT_S', 0.0)
    watch = DrainWatch(['/ingest', '/mapper'], QUIET_S, silent_s=0.0)  # /ingest: silent
    watch.add(report('/mapper', 0.0))  # it reported (now), and took an input just before
    runner.wait_until_quiet(watch, threading.Event())
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith('slam_run: warning: still busy after 0 s')
    assert line.endswith(': /mapper; stopping the graph with their queued inputs unprocessed')


def test_waiting_ends_when_quiet_or_a_node_failed(
    capsys: pytest.CaptureFixture[str],
) -> None:
    watch = DrainWatch(['/mapper'], QUIET_S, silent_s=0.0)
    runner.wait_until_quiet(watch, threading.Event())  # it never reports
    assert capsys.readouterr().err == (
        'slam_run: not waited for (no report on /diagnostics): /mapper\n'
    )
    watch.add(report('/mapper', 0.0))
    runner.wait_until_quiet(watch, threading.Event(), failed=lambda: True)
    assert capsys.readouterr().err == ''
