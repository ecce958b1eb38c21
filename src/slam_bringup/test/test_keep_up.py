"""slam_run's word on a graph that does not keep up: the options at start, then once per
node that reports a loss on /diagnostics."""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from slam_bringup.keep_up import KeepUpHint, remedies, start_note


def report(name: str, level: bytes, message: str) -> DiagnosticArray:
    array = DiagnosticArray()
    array.status.append(DiagnosticStatus(name=name, level=level, message=message))
    return array


def test_remedies_depend_on_the_run() -> None:
    free = remedies(has_player=True, paced=False, processes=False)
    assert [option.split()[0] for option in free] == ['--paced', '--processes', 'a']
    assert remedies(has_player=True, paced=True, processes=False) == []  # nothing is lost
    assert [o.split()[0] for o in remedies(has_player=False, paced=False, processes=False)] == [
        '--processes'
    ]
    assert remedies(has_player=True, paced=True, processes=True) == []
    assert remedies(has_player=False, paced=False, processes=True) == []  # live, one per node
    assert start_note([]) is None
    note = start_note(free)
    assert note is not None and note.startswith('free-running: a node that cannot keep up')
    assert 'to keep every one use --paced' in note


def test_the_hint_names_each_losing_node_once() -> None:
    said: list[str] = []
    options = remedies(has_player=True, paced=False, processes=False)
    hint = KeepUpHint(['/marker_detector', '/em_sam_mapper'], options, said.append)
    hint.add(report('/marker_detector', DiagnosticStatus.WARN, 'falling behind (busy 97 %)'))
    hint.add(report('/other_graph/node', DiagnosticStatus.WARN, 'lost 3 messages before'))
    hint.add(report('/em_sam_mapper', DiagnosticStatus.OK, '10 received, 0 lost, 0 dropped'))
    assert said == []  # busy is not a loss; another graph's node; 'lost' in an OK summary
    loss = 'lost 12 messages before taking them'
    hint.add(report('/marker_detector', DiagnosticStatus.WARN, loss))
    hint.add(report('/marker_detector', DiagnosticStatus.WARN, loss))
    hint.add(report('/em_sam_mapper', DiagnosticStatus.WARN, 'dropping inputs (2 since the last)'))
    assert len(said) == 2
    assert said[0].startswith(f'/marker_detector cannot keep up ({loss}); to keep every')
    assert '--paced' in said[0] and '--processes' in said[0] and 'a lower --rate' in said[0]
    assert said[1].startswith('/em_sam_mapper cannot keep up (dropping inputs')


def test_nothing_to_say_when_paced_in_processes() -> None:
    said: list[str] = []
    hint = KeepUpHint(['/n'], [], said.append)
    hint.add(report('/n', DiagnosticStatus.WARN, 'lost 1 messages before taking them'))
    assert said == []
