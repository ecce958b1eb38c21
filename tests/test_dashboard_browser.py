"""slam_dashboard in a real browser: headless Chromium opens the page of a running graph.

The graph is the README's first one (``slam_run em_sam_office.yaml`` on
bags/office_moveable.mcap, paced), ``slam_dashboard`` runs beside it as a user starts it,
and the browser loads its page over HTTP and the WebSocket. The test reads the page's DOM:
the landmark count must be the count of the map the mapper publishes, and the diagnostics
table must hold the graph's nodes. The screenshot goes to out/test/dashboard.png (under the
repository root, or $SLAM_TEST_OUTPUT).
"""

from __future__ import annotations

import json
import os
import re
import urllib.request
from pathlib import Path

import pytest
from browser import HeadlessChromium, find_chromium

from slam_interfaces.msg import LandmarkMap
from slam_ros.qos import latched_qos
from slam_ros.testing.harness import NodeProcess, RosHarness

pytestmark = pytest.mark.topic
ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_moveable.mcap'
CAMERA_BAG = ROOT / 'bags' / 'dynamic_camera.mcap'
MAP_TIMEOUT_S = 240.0  # the first solve: 5 s of bag time, paced, on a busy machine


def output_dir() -> Path:
    path = Path(os.environ.get('SLAM_TEST_OUTPUT', ROOT / 'out' / 'test'))
    path.mkdir(parents=True, exist_ok=True)
    return path


def start_dashboard(harness: RosHarness) -> tuple[NodeProcess, str]:
    """Start slam_dashboard on a free local port as a user does; it and its page's address."""
    dashboard = harness.start_process(
        'slam_dashboard',
        ['slam_dashboard', '--ros-args', '-p', 'host:=127.0.0.1', '-p', 'port:=0'],
    )
    line = dashboard.wait_for_line(60.0, 'open http://')
    url = re.search(r'(http://\S+/)', line)
    assert url is not None, line
    return dashboard, url.group(1)


COUNT = "+(document.getElementById('landmark-count').textContent) || 0"
ROWS = """Array.from(document.querySelectorAll('#diagnostics tbody tr')).map(
  (row) => [row.className, row.cells[0].textContent, row.cells[1].textContent])"""


def test_dashboard_shows_the_live_map_and_diagnostics(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    browser_binary = find_chromium()
    maps = ros_harness.collect('/em_sam/landmarks', LandmarkMap, latched_qos())
    dashboard, url = start_dashboard(ros_harness)
    graph = ros_harness.start_process(
        'slam_run',
        ['slam_run', 'em_sam_office.yaml', '--bag', str(BAG), '--paced'],
        cwd=tmp_path,
    )
    browser = HeadlessChromium(browser_binary)
    try:
        browser.navigate(url)
        browser.wait_for(
            "document.getElementById('connection').textContent", lambda v: v == 'live', 60.0
        )
        # the page's count follows the mapper's latest map
        browser.wait_for(COUNT, lambda v: v > 0, MAP_TIMEOUT_S)
        maps.wait_for_count(1, timeout_s=30.0)
        browser.wait_for(COUNT, lambda v: v == len(maps.messages[-1].landmarks), 30.0)
        rows = browser.wait_for(
            ROWS,
            lambda rows: (
                rows is not None
                and {'/em_sam_mapper', '/odometry_ingest', '/slam_dashboard'}
                <= {name for _, _, name in rows}
            ),
            60.0,
        )
        for class_name, level, name in rows:
            assert class_name == f'level-{level}', (name, class_name, level)
            assert level in ('OK', 'WARN', 'ERROR', 'STALE'), (name, level)
        # ids are drawn on the map: the moveable table and the canvas come from one state
        state = json.load(urllib.request.urlopen(url + 'state.json', timeout=10))
        assert browser.evaluate("document.getElementById('static-count').textContent") == str(
            state['map']['static']
        )
        screenshot = browser.screenshot(output_dir() / 'dashboard.png')
        assert screenshot.stat().st_size > 10_000
        assert graph.process.poll() is None, 'the graph ended before the page was read'
    finally:
        browser.close()
        graph.stop(timeout_s=30.0)
        dashboard.stop()
    assert 'Traceback' not in dashboard.log(), dashboard.log()[-3000:]


FEATURES = "+(document.getElementById('feature-count').textContent) || 0"
SUMMARY = "document.getElementById('feature-summary').textContent"


def test_dashboard_shows_the_camera_features_and_monoslam_path(
    ros_harness: RosHarness, tmp_path: Path
) -> None:
    browser_binary = find_chromium()
    dashboard, url = start_dashboard(ros_harness)
    graph = ros_harness.start_process(
        'slam_run',
        ['slam_run', 'monoslam_shadow.yaml', '--bag', str(CAMERA_BAG), '--paced'],
        cwd=tmp_path,
    )
    browser = HeadlessChromium(browser_binary)
    try:
        browser.navigate(url)
        browser.wait_for(FEATURES, lambda v: v > 0, MAP_TIMEOUT_S)
        browser.wait_for('shownImage !== null', lambda v: v is True, 60.0)
        # the Shadow filter's classes reach the overlay: some features are judged static
        summary = browser.wait_for(
            SUMMARY, lambda text: text and not text.startswith('0 static'), MAP_TIMEOUT_S
        )
        counts = dict(
            (name, int(number))
            for number, name in re.findall(r'(\d+) (static|dynamic|pending)', summary)
        )
        assert sum(counts.values()) <= browser.evaluate(FEATURES), summary
        points = browser.wait_for(
            'state.monoslam ? state.monoslam.points.length : 0', lambda v: v > 1, MAP_TIMEOUT_S
        )
        assert points > 1
        screenshot = browser.screenshot(output_dir() / 'dashboard_camera.png')
        assert screenshot.stat().st_size > 10_000
    finally:
        browser.close()
        graph.stop(timeout_s=30.0)
        dashboard.stop()
    assert 'Traceback' not in dashboard.log(), dashboard.log()[-3000:]
