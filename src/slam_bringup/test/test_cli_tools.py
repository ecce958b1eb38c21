"""The command-line tools' pieces without a graph: messages to YAML and back, name matching,
the diagnostics table and slam_echo's rate limit."""

from __future__ import annotations

import argparse
import io

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import CameraInfo

from slam_bringup.diag_monitor import DiagnosticsTable, exit_code
from slam_bringup.graph_lookup import DiscoveryError, match_name, wait_for
from slam_bringup.message_yaml import MessageFieldError, fill_message, message_to_data, to_yaml
from slam_bringup.service_call import outcome
from slam_bringup.topic_echo import Echo, build_parser, select_field
from slam_interfaces.srv import FindLandmark


def test_message_to_data_keeps_field_order_numbers_and_octets() -> None:
    info = CameraInfo(width=640, height=480, distortion_model='plumb_bob')
    info.k = np.arange(9, dtype=float)
    info.d = [0.1, -0.2, 0.0, 0.0, 0.0]
    data = message_to_data(info)
    assert list(data)[:5] == ['header', 'height', 'width', 'distortion_model', 'd']
    assert data['k'] == [float(i) for i in range(9)] and data['d'][1] == -0.2
    assert yaml.safe_load(to_yaml(data)) == data
    status = DiagnosticStatus(level=DiagnosticStatus.ERROR, name='n')
    assert message_to_data(status)['level'] == 2  # an octet prints as a number, not bytes


def test_message_to_data_truncates_and_hides_arrays() -> None:
    info = CameraInfo()
    info.d = list(np.linspace(0, 1, 300))
    assert len(message_to_data(info)['d']) == 129 and message_to_data(info)['d'][-1] == '...'
    assert len(message_to_data(info, truncate=None)['d']) == 300
    assert message_to_data(info, arrays=False)['d'] == '<sequence of 300>'


def test_fill_message_sets_nested_fields_and_names_bad_ones() -> None:
    request = fill_message(FindLandmark.Request(), {'landmark_id': 12})
    assert request.landmark_id == 12
    info = fill_message(CameraInfo(), {'header': {'frame_id': 'cam'}, 'k': [1.0] * 9})
    assert info.header.frame_id == 'cam' and list(info.k) == [1.0] * 9
    status = fill_message(DiagnosticStatus(), {'level': 1, 'values': [{'key': 'a', 'value': 'b'}]})
    assert status.level == DiagnosticStatus.WARN and status.values[0].key == 'a'
    with pytest.raises(MessageFieldError, match="did you mean 'landmark_id'"):
        fill_message(FindLandmark.Request(), {'landmark': 3})
    with pytest.raises(MessageFieldError, match=r'landmark_id: expected an integer \(int32\)'):
        fill_message(FindLandmark.Request(), {'landmark_id': 2.5})
    with pytest.raises(MessageFieldError, match=r'header\.frame_id: expected a string'):
        fill_message(CameraInfo(), {'header': {'frame_id': 3}})
    with pytest.raises(MessageFieldError, match='expected a mapping'):
        fill_message(FindLandmark.Request(), [1, 2])
    with pytest.raises(MessageFieldError, match='level: expected 0-255'):
        fill_message(DiagnosticStatus(), {'level': 300})


def test_match_name_exact_tail_and_ambiguous() -> None:
    names = ['/em_sam_mapper/optimize', '/monoslam/save_map', '/em_sam_mapper/save_map']
    assert match_name('/em_sam_mapper/optimize', names) == '/em_sam_mapper/optimize'
    assert match_name('em_sam_mapper/optimize', names) == '/em_sam_mapper/optimize'
    assert match_name('optimize', names) == '/em_sam_mapper/optimize'
    assert match_name('save_map', names) is None  # two nodes offer one
    assert match_name('mize', names) is None  # a tail is whole segments
    with pytest.raises(DiscoveryError, match='is ambiguous: /em_sam_mapper/save_map, /monoslam'):
        wait_for('service', 'save_map', lambda: [(n, ['std_srvs/srv/Trigger']) for n in names], 0)
    with pytest.raises(DiscoveryError, match="did you mean '/em_sam_mapper/optimize'"):
        wait_for('service', '/em_sam_mapper/optimise', lambda: [(n, ['t']) for n in names], 0)


def diagnostic_array(**levels: bytes) -> DiagnosticArray:
    array = DiagnosticArray()
    for name, level in levels.items():
        status = DiagnosticStatus(name=name, level=level, message='m')
        status.values = [KeyValue(key='k', value='v')]
        array.status.append(status)
    return array


def test_diagnostics_table_orders_by_severity_and_marks_stale() -> None:
    table = DiagnosticsTable(stale_s=5.0)
    table(diagnostic_array(a=DiagnosticStatus.OK, b=DiagnosticStatus.WARN), now_s=0.0)
    table(diagnostic_array(c=DiagnosticStatus.ERROR), now_s=4.0)
    rows = table.render(4.0).splitlines()
    assert [row.split()[:2] for row in rows[1:4]] == [['ERROR', 'c'], ['WARN', 'b'], ['OK', 'a']]
    assert exit_code(table.worst(4.0)) == 3
    later = table.render(6.0).splitlines()  # a and b not updated for 6 s
    assert [row.split()[:2] for row in later[1:4]] == [
        ['ERROR', 'c'],
        ['STALE', 'a'],
        ['STALE', 'b'],
    ]
    assert later[-1] == '3 statuses: 1 ERROR, 2 STALE'
    assert exit_code(None) == 4 and exit_code('OK') == 0 and exit_code('WARN') == 1
    filtered = DiagnosticsTable(stale_s=5.0, name_filter='b')
    filtered(diagnostic_array(a=DiagnosticStatus.OK, b=DiagnosticStatus.WARN), now_s=0.0)
    assert list(filtered.statuses) == ['b']
    assert '\033[33m' in filtered.render(0.0, color=True)
    assert '   k: v' in filtered.render(0.0, verbose=True)


def test_echo_rate_limit_and_count() -> None:
    now = [0.0]
    out = io.StringIO()
    args = build_parser().parse_args(['/t', '--rate', '2', '--count', '3'])
    echo = Echo(args, out=out, clock=lambda: now[0])
    for step in range(20):  # 10 Hz for 2 s: printed at 0, 0.5 and 1.0 s, then done
        now[0] = step * 0.1
        echo(CameraInfo(width=step))
    assert echo.printed == 3 and echo.received == 20 and echo.skipped == 17 and echo.done
    widths = [doc['width'] for doc in yaml.safe_load_all(out.getvalue()) if doc]
    assert widths == [0, 5, 10]
    assert echo.summary('/t') == 'slam_echo: /t: 20 received, 3 printed, 17 skipped, 10.00 Hz'


def test_select_field_walks_messages_and_lists() -> None:
    array = diagnostic_array(a=DiagnosticStatus.OK)
    assert select_field(array, 'status.0.values.0.key') == 'k'
    with pytest.raises(Exception, match=r"no '1' here \(it has: 1 items\)"):
        select_field(array, 'status.1')
    with pytest.raises(Exception, match="no 'stats' here"):
        select_field(array, 'stats')


def test_call_outcome() -> None:
    assert outcome({'success': True, 'message': ''}) == 0
    assert outcome({'success': False}) == 1 and outcome({'found': False}) == 1
    assert outcome({'value': 3}) == 0


def test_parsers_reject_nonpositive_rates() -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(['/t', '--rate', '0'])
    assert isinstance(build_parser().parse_args(['/t']), argparse.Namespace)
