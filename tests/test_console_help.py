"""Every console script of every package answers -h/--help and exits 0 without starting ROS.

The scripts run as installed (from PATH, as a user would run them). Node executables (their
module declares a ``PARAMETERS`` table) must list every declared parameter and their
topics. rclpy.init writes a log file into ROS_LOG_DIR, so an empty ROS_LOG_DIR afterwards
shows that no ROS context was created.
"""

from __future__ import annotations

import ast
import importlib
import os
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from slam_core.params import ParamTable

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
NODE_EXECUTABLES = {
    'marker_detector',
    'odometry_ingest',
    'em_sam_mapper',
    'feature_tracker',
    'monoslam',
    'shadow_filter',
    'bag_player',
    'bag_recorder',
    'apriltag_bridge',
    'peoplebot_sim',
    'route_driver',
    'dynamic_scene_sim',
    'camera_mount',
    'label_gate',
}


def console_scripts() -> dict[str, str]:
    """Return ``{script: 'module:function'}`` from every src/*/setup.py."""
    scripts: dict[str, str] = {}
    for setup in sorted(ROOT.glob('src/*/setup.py')):
        for node in ast.walk(ast.parse(setup.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Dict):
                for key, value in zip(node.keys, node.values, strict=True):
                    if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                        for item in ast.literal_eval(value):
                            name, _, target = item.partition('=')
                            scripts[name.strip()] = target.strip()
    return scripts


SCRIPTS = console_scripts()


def run_help(script: str, log_dir: Path) -> subprocess.CompletedProcess[str]:
    executable = shutil.which(script)
    assert executable is not None, f'{script} is not on PATH (source scripts/env.sh)'
    env = {**os.environ, 'ROS_LOG_DIR': str(log_dir), 'PYTHONUNBUFFERED': '1'}
    return subprocess.run(
        [executable, '--help'], capture_output=True, text=True, timeout=120, env=env, check=False
    )


@pytest.fixture(scope='module')
def help_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[object, Path]]:
    """Run every script's --help once (two at a time), each with its own ROS_LOG_DIR."""
    base = tmp_path_factory.mktemp('help')
    log_dirs = {script: base / script for script in SCRIPTS}
    for directory in log_dirs.values():
        directory.mkdir()
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = dict(
            zip(SCRIPTS, pool.map(lambda s: run_help(s, log_dirs[s]), SCRIPTS), strict=True)
        )
    return {script: (results[script], log_dirs[script]) for script in SCRIPTS}


def test_every_expected_executable_is_a_console_script() -> None:
    assert set(SCRIPTS) >= NODE_EXECUTABLES
    assert len(SCRIPTS) >= 21


@pytest.mark.parametrize('script', sorted(SCRIPTS))
def test_help_exits_0_without_a_ros_context(
    script: str, help_runs: dict[str, tuple[subprocess.CompletedProcess[str], Path]]
) -> None:
    result, log_dir = help_runs[script]
    assert result.returncode == 0, result.stderr
    assert f'usage: {script}' in result.stdout
    assert list(log_dir.iterdir()) == [], 'rclpy.init ran (it wrote a ROS log file)'
    module = importlib.import_module(SCRIPTS[script].partition(':')[0])
    table = getattr(module, 'PARAMETERS', None)
    if script in NODE_EXECUTABLES:
        assert isinstance(table, ParamTable)
        missing = [p.name for p in table if f'{p.name} (' not in result.stdout]
        assert missing == []
        assert 'publishes' in result.stdout or 'subscribes' in result.stdout
