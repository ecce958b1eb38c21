"""Unit tests of the ROS-free playback pieces: time mapping, lateness, progress, prefetch."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam_core.errors import BagError
from slam_core.progress import ProgressReporter, format_seconds
from slam_ros.bag.playback import LatenessStats, Prefetcher, TimeMapping
from slam_ros.bag.source import BagSource
from slam_ros.testing.messages import BagTopic, write_bag


@settings(derandomize=True, max_examples=200)
@given(
    bag_start=st.integers(0, 2**62),
    offset_ns=st.integers(0, 10**12),
    rate=st.floats(0.05, 20.0),
)
def test_time_mapping_round_trips(bag_start: int, offset_ns: int, rate: float) -> None:
    mapping = TimeMapping(bag_start, 10**9, rate)
    wall = mapping.wall_deadline_ns(bag_start + offset_ns)
    assert wall - 10**9 == pytest.approx(offset_ns / rate, abs=1)
    assert abs(mapping.bag_time_ns(wall) - (bag_start + offset_ns)) <= rate + 1


def test_time_mapping_scales_with_rate() -> None:
    assert TimeMapping(100, 0, 2.0).wall_deadline_ns(100 + 10**9) == 5 * 10**8
    assert TimeMapping(100, 0, 0.5).wall_deadline_ns(100 + 10**9) == 2 * 10**9


def test_lateness_summary() -> None:
    stats = LatenessStats()
    for value_ms in (1, 2, 3, 4, 100):
        stats.add(value_ms * 10**6)
    summary = stats.summary_ms()
    assert summary['count'] == 5
    assert summary['median_ms'] == 3.0
    assert summary['max_ms'] == 100.0


def test_progress_line_has_rate_and_eta() -> None:
    now = [0.0]
    lines: list[str] = []
    progress = ProgressReporter(
        100.0, label='replay', unit='s', log=lines.append, period_s=1.0, clock=lambda: now[0]
    )
    now[0] = 10.0
    progress.update(25.0, items=50)
    assert '25.0%' in lines[-1]
    assert 'rate 2.50s/s' in lines[-1]
    assert 'ETA 30.0s' in lines[-1]
    assert '50 msgs (5.0/s)' in lines[-1]


def test_progress_bar_on_terminal() -> None:
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    stream = Terminal()
    progress = ProgressReporter(10.0, label='x', stream=stream, clock=lambda: 1.0)
    progress.update(5.0, force=True)
    progress.finish()
    assert '\r' in stream.getvalue() and '[##############' in stream.getvalue()


def test_format_seconds() -> None:
    assert format_seconds(12.34) == '12.3s'
    assert format_seconds(185) == '3m05s'
    assert format_seconds(3720) == '1h02m'
    assert format_seconds(float('inf')) == '--'


def test_prefetcher_yields_in_order_and_reraises_errors(tmp_path: Path) -> None:
    written = write_bag(
        tmp_path / 'bag', (BagTopic('/odom', 'nav_msgs/msg/Odometry', 100.0),), duration_s=2.0
    )
    with BagSource(tmp_path / 'bag') as source:
        prefetch = Prefetcher(source, None, None, max_bytes=4096)
        stamps = [m.timestamp_ns for m in prefetch]
        prefetch.close()
    assert stamps == [m.timestamp_ns for m in written]

    (mcap,) = (tmp_path / 'bag').glob('*.mcap')
    mcap.write_bytes(mcap.read_bytes()[:-2000])  # cut into the summary section
    with pytest.raises(BagError, match='bag'), BagSource(mcap) as source:
        list(Prefetcher(source, None, None))
