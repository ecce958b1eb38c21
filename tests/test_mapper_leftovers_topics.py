"""A mapper run leaves what a user expects in its report directory: a fresh run moves the
last run's report aside instead of overwriting it, and a run that received nothing writes
no checkpoint."""

from __future__ import annotations

from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray

from slam_ros.testing.harness import RosHarness

pytestmark = pytest.mark.topic


def test_a_fresh_run_keeps_the_last_one_and_an_empty_run_leaves_nothing(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    report_dir = tmp_path / 'em_sam_live'
    report_dir.mkdir()
    (report_dir / 'em_sam_report.json').write_text('{"last": "run"}')
    (report_dir / 'em_sam_map.png').write_bytes(b'figure')
    diagnostics = ros_harness.collect('/diagnostics', DiagnosticArray)
    mapper = ros_harness.start_process(
        'em_sam_mapper', ['em_sam_mapper', '--ros-args', '-p', f'report_dir:={report_dir}']
    )
    moved_line = mapper.wait_for_line(60.0, 'the previous run in', 'was moved to')
    # Spinning, not only constructing: its diagnostics come from a timer of its executor
    # (a Ctrl-C during construction ends the process before there is a node to finalize).
    diagnostics.wait_for(
        lambda array: any('em_sam_mapper' in status.name for status in array.status),
        timeout_s=60.0,
    )
    assert mapper.stop() == 0, mapper.log()
    kept = [p for p in tmp_path.iterdir() if p.name.startswith('em_sam_live.')]
    assert len(kept) == 1 and str(kept[0]) in moved_line
    assert (kept[0] / 'em_sam_report.json').read_text() == '{"last": "run"}'
    assert (kept[0] / 'em_sam_map.png').read_bytes() == b'figure'
    leftovers = sorted(p.name for p in report_dir.iterdir()) if report_dir.exists() else []
    assert leftovers == [], leftovers  # nothing received: no report, no checkpoint
    log = mapper.log()
    assert 'no checkpoint written: nothing was received' in log
    # said on the console after Ctrl-C, without an attempt at the dead /rosout
    assert 'Failed to publish log message to rosout' not in log, log
