"""``diagnostics``: a node's counts, processing time and lag on /diagnostics, and WARN while
it drops inputs (a real rclpy node; its status is read, the timer is not waited for)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo

from slam_core.stamps import ns_to_stamp
from slam_ros.diagnostics import IDLE_KEY, OK_AGAIN_REPORTS, Diagnostics


@pytest.fixture
def node(ros_context: None) -> Iterator[Node]:
    node = Node('diagnosed')
    try:
        yield node
    finally:
        node.destroy_node()


def values(status: DiagnosticStatus) -> dict[str, str]:
    return {value.key: value.value for value in status.values}


def test_inputs_counts_time_and_lag(node: Node) -> None:
    counts = {'processed': 0, 'dropped': 0}
    diagnostics = Diagnostics(node, lambda: counts, period_s=3600.0)
    seen: list[int] = []

    def on_info(message: CameraInfo) -> None:
        seen.append(message.width)
        counts['processed'] += 1

    on_info_timed = diagnostics.timed(on_info, 'camera_info')
    now_ns = node.get_clock().now().nanoseconds
    for k, age_s in enumerate((3.0, 2.0)):
        message = CameraInfo(width=640 + k)
        ns_to_stamp(now_ns - int(age_s * 1e9), message.header.stamp)
        on_info_timed(message, {'publication_sequence_number': k + 1})
    assert seen == [640, 641]
    status = diagnostics.status()
    assert status.name == '/diagnosed' and status.level == DiagnosticStatus.OK
    shown = values(status)
    assert shown['received camera_info'] == '2' and shown['processed'] == '2'
    assert shown['lost camera_info'] == '0'
    assert shown['dropped'] == '0'
    assert 2.0 <= float(shown['lag s']) < 3.0  # the latest stamp's age
    assert float(shown['processing ms mean']) >= 0.0 and 'busy %' in shown
    assert float(shown['processing s']) == pytest.approx(diagnostics.processing_s, abs=1e-3)
    assert status.message == '2 received, 0 lost, 0 dropped'


def test_a_node_that_drops_inputs_warns_until_it_stops(node: Node) -> None:
    counts = {'dropped': 0}
    diagnostics = Diagnostics(node, lambda: counts, period_s=3600.0)
    assert diagnostics.status().level == DiagnosticStatus.OK
    assert values(diagnostics.status())['lag s'] == 'nan'  # no stamped input yet
    counts['dropped'] = 3
    status = diagnostics.status()
    assert status.level == DiagnosticStatus.WARN
    assert status.message == 'dropping inputs (3 since the last)'
    assert diagnostics.status().level == DiagnosticStatus.OK  # none dropped since


def test_a_callback_that_raises_is_still_counted_and_timed(node: Node) -> None:
    diagnostics = Diagnostics(node, dict, period_s=3600.0)

    def broken(message: CameraInfo) -> None:
        raise ValueError('bad input')

    with pytest.raises(ValueError, match='bad input'):
        diagnostics.timed(broken, 'camera_info')(CameraInfo(), {})
    assert diagnostics.received == {'camera_info': 1} and diagnostics.processing_s > 0.0


def test_gaps_in_the_publishers_sequence_numbers_are_lost_messages(node: Node) -> None:
    """The node joins at number 40 (the 39 before are not its losses); 41, 44, 45, 49 arrive:
    2 + 3 were lost (DDS dropped them from the queue), the status warns once; then a number
    that goes back (a second publisher) makes the losses unknown from then on."""
    diagnostics = Diagnostics(node, dict, period_s=3600.0)
    on_info = diagnostics.timed(lambda message: None, 'camera_info')
    for sequence in (40, 41, 44, 45, 49):
        on_info(CameraInfo(), {'publication_sequence_number': sequence})
    status = diagnostics.status()
    assert values(status)['lost camera_info'] == '5' and status.level == DiagnosticStatus.WARN
    assert values(status)['first sequence camera_info'] == '40'
    assert status.message.startswith('lost 5 messages before taking them')
    assert diagnostics.status().level == DiagnosticStatus.OK
    on_info(CameraInfo(), {'publication_sequence_number': 3})
    on_info(CameraInfo(), {'publication_sequence_number': 50})
    assert values(diagnostics.status())['lost camera_info'] == 'unknown'


def test_the_wait_in_the_queue_tells_an_overflow_from_a_message_never_delivered(
    node: Node,
) -> None:
    """rmw's received stamp gives how long each message waited in the queue: the longest in
    the window is shown, and the wait of the message after a gap is kept with the loss
    (0.5 s: the queue overflowed; about 0: DDS never delivered the ones before)."""
    diagnostics = Diagnostics(node, dict, period_s=3600.0)
    on_info = diagnostics.timed(lambda message: None, 'camera_info')
    for sequence, waited_s in ((1, 0.0), (2, 0.1), (5, 0.5), (6, 0.0), (9, 0.0)):
        received_ns = time.time_ns() - int(waited_s * 1e9)
        info = {'publication_sequence_number': sequence, 'received_timestamp': received_ns}
        on_info(CameraInfo(), info)
        if sequence == 5:
            assert 500.0 <= diagnostics.gap_wait_ms['camera_info'] < 1500.0
    assert diagnostics.gap_wait_ms['camera_info'] < 500.0  # the last gap: never delivered
    status = values(diagnostics.status())
    assert status['lost camera_info'] == '4'
    assert 500.0 <= float(status['queue wait ms max']) < 1500.0
    assert float(values(diagnostics.status())['queue wait ms max']) == 0.0  # a new window


def test_idle_counts_from_the_last_input_taken(node: Node) -> None:
    """``idle s`` (what slam_run's drain reads) grows while no input is taken, from the
    node's start, and starts over with each input; timer callbacks do not reset it."""
    diagnostics = Diagnostics(node, dict, period_s=3600.0)
    diagnostics.last_input_s -= 5.0  # as if started 5 s ago
    assert float(values(diagnostics.status())[IDLE_KEY]) >= 5.0
    diagnostics.timed(lambda: None)()
    assert float(values(diagnostics.status())[IDLE_KEY]) >= 5.0
    diagnostics.timed(lambda message: None, 'camera_info')(CameraInfo(), {})
    assert float(values(diagnostics.status())[IDLE_KEY]) < 5.0


def test_a_node_without_inputs_reports_its_counts_and_values(node: Node) -> None:
    diagnostics = Diagnostics(
        node, lambda: {'published /odom': 3}, period_s=3600.0, values=lambda: {'late ms': '1.5'}
    )
    status = diagnostics.status()
    assert values(status)['published /odom'] == '3' and values(status)['late ms'] == '1.5'
    assert status.message == 'published /odom 3' and status.level == DiagnosticStatus.OK


def test_the_log_says_each_change_of_state_once(node: Node) -> None:
    """A problem is logged when it starts, not at every report while it lasts; the return to
    OK after OK_AGAIN_REPORTS quiet reports; a problem back within them is not logged again."""
    counts = {'dropped': 0}
    logged: list[tuple[str, str]] = []
    diagnostics = Diagnostics(
        node, lambda: counts, period_s=3600.0, log=lambda *line: logged.append(line)
    )
    on_info = diagnostics.timed(lambda message: None, 'camera_info')
    diagnostics.status()
    assert logged == []
    for _ in range(3):  # dropping in three reports in a row
        counts['dropped'] += 2
        diagnostics.status()
    assert logged == [('warning', 'WARN on /diagnostics: dropping inputs (2 since the last)')]
    for sequence in (1, 4):  # 2 lost: a new kind of problem
        on_info(CameraInfo(), {'publication_sequence_number': sequence})
    diagnostics.status()
    assert len(logged) == 2 and logged[1][1].startswith(
        'WARN on /diagnostics: lost 2 messages before taking them (2 so far, by input: '
        'camera_info 2, the message after the last gap waited'
    )
    for _ in range(OK_AGAIN_REPORTS - 1):
        diagnostics.status()
    counts['dropped'] += 1  # back before the node was OK long enough: not logged again
    diagnostics.status()
    assert len(logged) == 2
    for _ in range(OK_AGAIN_REPORTS):
        diagnostics.status()
    assert logged[2] == (
        'info',
        'OK again on /diagnostics (was: dropping, lost); 2 lost and 7 dropped so far',
    )
    counts['dropped'] += 1
    diagnostics.status()
    assert logged[3] == ('warning', 'WARN on /diagnostics: dropping inputs (1 since the last)')


def test_the_node_logger_takes_both_severities(node: Node) -> None:
    """Through the node's own logger (rclpy refuses one call site at two severities)."""
    counts = {'dropped': 0}
    diagnostics = Diagnostics(node, lambda: counts, period_s=3600.0)
    counts['dropped'] = 1
    diagnostics.status()  # a warning
    for _ in range(OK_AGAIN_REPORTS):
        diagnostics.status()  # then OK again: an info
    counts['dropped'] = 2
    diagnostics.status()  # a warning again


@pytest.mark.parametrize('paced', [False, True])
def test_busy_is_a_warning_only_when_free_running(
    node: Node, paced: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In a paced replay the player waits for the nodes: a node busy all the time is the
    replay going as fast as it can, not a node falling behind."""
    from slam_ros.progress import PACED_ENV

    if paced:
        monkeypatch.setenv(PACED_ENV, '1')
    else:
        monkeypatch.delenv(PACED_ENV, raising=False)
    diagnostics = Diagnostics(node, dict, period_s=3600.0)
    diagnostics._add_time(1e6)  # busy all of the window
    status = diagnostics.status()
    assert float(values(status)['busy %']) > 90.0
    assert (status.level == DiagnosticStatus.WARN) is not paced
