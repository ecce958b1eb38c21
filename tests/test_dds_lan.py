"""Robot and laptop over a network: the LAN DDS profile (``SLAM_DDS_PROFILE=lan`` in
scripts/env.sh) carries the robot's data to the mapper on another machine, here two Linux
network namespaces joined by a veth pair that the test creates (root only).

The robot side (namespace 1) plays the office bag's odometry and landmark observations, as
its drivers and detector would publish them; the laptop side (namespace 2) runs
odometry_ingest and em_sam_mapper (``slam_run`` on a GRAPH without a player) and a probe
that waits for the mapper's landmark map. Each side is started through ``scripts/env.sh``
with the one setting, as the README's recipe does. With the loopback profile (the default),
the same two sides must not see each other: the data in the first run crossed the veth.

Without root (or where namespaces cannot be made) the test skips with the reason, except
when ``SLAM_REQUIRE_NETNS_TEST`` is set (``.ci/run`` sets it: CI must run it), where it
fails with that reason.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = [pytest.mark.topic, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_moveable.mcap'
SUBNET = '10.213.77'
MIN_LANDMARKS = 10
MAP_TIMEOUT_S = 120.0
NO_MAP_TIMEOUT_S = 30.0

PROBE = """\
import sys, time
import rclpy
from slam_interfaces.msg import LandmarkMap
from slam_ros.qos import latched_qos
rclpy.init()
node = rclpy.create_node('laptop_probe')
sizes = []
node.create_subscription(LandmarkMap, 'em_sam/landmarks',
                         lambda m: sizes.append(len(m.landmarks)), latched_qos())
deadline = time.monotonic() + float(sys.argv[1])
while time.monotonic() < deadline and not (sizes and sizes[-1] >= int(sys.argv[2])):
    rclpy.spin_once(node, timeout_sec=0.2)
print('landmarks', sizes[-1] if sizes else 0, flush=True)
sys.exit(0 if sizes and sizes[-1] >= int(sys.argv[2]) else 1)
"""

LAPTOP_GRAPH = """\
graph:
  description: the laptop side, the mapper on the robot's odometry and observations
  nodes:
    - name: odometry_ingest
      package: em_sam_node
      executable: odometry_ingest
      plugin: em_sam_node.odometry_ingest.node:OdometryIngestNode
      parameters: [package://em_sam_node/config/odometry_ingest.yaml]
    - name: em_sam_mapper
      package: em_sam_node
      executable: em_sam_mapper
      plugin: em_sam_node.mapper.node:EmSamMapperNode
      parameters:
        - package://em_sam_node/config/em_sam_mapper.yaml
        - {optimize_period_s: 2.0}
"""


REQUIRE_ENV = 'SLAM_REQUIRE_NETNS_TEST'


def _cannot_run(reason: str) -> None:
    """Skip with ``reason``, or fail with it where the test is required (module docstring)."""
    if os.environ.get(REQUIRE_ENV):
        pytest.fail(f'{reason} ({REQUIRE_ENV} is set: this test must run here)')
    pytest.skip(reason)


@dataclass(frozen=True)
class Sides:
    """One run of both sides: the largest landmark map the laptop's probe received, and the
    logs of every process (for the failure message)."""

    landmarks: int
    logs: str


def _ip(*arguments: str) -> None:
    subprocess.run(['ip', *arguments], check=True, capture_output=True, text=True)


@pytest.fixture
def namespaces() -> Iterator[tuple[str, str]]:
    """Two network namespaces joined by a veth pair (SUBNET.1 and SUBNET.2, multicast routed
    on the link); removed after the test."""
    if os.geteuid() != 0:
        _cannot_run('creating network namespaces needs root')
    if shutil.which('ip') is None:
        _cannot_run("creating network namespaces needs iproute2's ip")
    tag = os.getpid() % 100000
    names = (f'slam_robot_{tag}', f'slam_laptop_{tag}')
    links = (f'vrob{tag}', f'vlap{tag}')
    try:
        _ip('netns', 'add', names[0])
    except subprocess.CalledProcessError as error:
        _cannot_run(f'cannot create a network namespace here: {error.stderr.strip()}')
    try:
        _ip('netns', 'add', names[1])
        _ip('link', 'add', links[0], 'netns', names[0], 'type', 'veth',
            'peer', 'name', links[1], 'netns', names[1])  # fmt: skip
        for k, (name, link) in enumerate(zip(names, links, strict=True)):
            _ip('-n', name, 'addr', 'add', f'{SUBNET}.{k + 1}/24', 'dev', link)
            _ip('-n', name, 'link', 'set', 'lo', 'up')
            _ip('-n', name, 'link', 'set', link, 'up', 'multicast', 'on')
            _ip('-n', name, 'route', 'add', '224.0.0.0/4', 'dev', link)
        yield names
    finally:
        for name in names:
            subprocess.run(['ip', 'netns', 'del', name], check=False, capture_output=True)


def _in_namespace(name: str, profile: str, command: str) -> list[str]:
    """The command line that runs ``command`` in namespace ``name`` with scripts/env.sh's
    DDS profile ``profile``."""
    script = f'export SLAM_DDS_PROFILE={profile}; source scripts/env.sh >/dev/null; {command}'
    return ['ip', 'netns', 'exec', name, 'bash', '-c', script]


def _run_sides(names: tuple[str, str], profile: str, tmp_path: Path, timeout_s: float) -> Sides:
    """Start the laptop side and the probe, then the robot side; return the largest map the
    probe received (-1: the probe printed no count) and the logs."""
    graph = tmp_path / 'laptop.yaml'
    graph.write_text(LAPTOP_GRAPH)
    probe = tmp_path / 'probe.py'
    probe.write_text(PROBE)
    env = {**os.environ, 'PYTHONUNBUFFERED': '1', 'RCUTILS_COLORIZED_OUTPUT': '0'}
    for key in ('SLAM_DDS_PROFILE', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_STATIC_PEERS'):
        env.pop(key, None)
    logs = {side: (tmp_path / f'{profile}_{side}.log').open('w') for side in ('robot', 'laptop')}
    mapper = subprocess.Popen(
        _in_namespace(names[1], profile, f'exec slam_run {graph}'),
        cwd=ROOT, env=env, stdout=logs['laptop'], stderr=subprocess.STDOUT,
    )  # fmt: skip
    robot = subprocess.Popen(
        _in_namespace(
            names[0], profile,
            f'exec bag_player {BAG} --rate 10 --topics /odom /landmark_observations',
        ),
        cwd=ROOT, env=env, stdout=logs['robot'], stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        probe_run = subprocess.run(
            _in_namespace(names[1], profile, f'exec {sys.executable} {probe} {timeout_s} '
                                             f'{MIN_LANDMARKS}'),
            cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout_s + 60,
        )  # fmt: skip
    finally:
        for process in (robot, mapper):
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        for log in logs.values():
            log.close()
    detail = textwrap.indent(
        ''.join(
            f'--- {path.name}\n{path.read_text()[-3000:]}'
            for path in sorted(tmp_path.glob(f'{profile}_*.log'))
        ),
        '  ',
    )
    words = probe_run.stdout.split()
    landmarks = int(words[1]) if len(words) == 2 and words[0] == 'landmarks' else -1
    logs = f'probe: {probe_run.stdout.strip()} {probe_run.stderr[-2000:]}\n{detail}'
    return Sides(landmarks, logs)


def test_the_lan_profile_carries_the_robot_data_to_the_laptops_mapper(
    namespaces: tuple[str, str], tmp_path: Path
) -> None:
    lan = _run_sides(namespaces, 'lan', tmp_path, MAP_TIMEOUT_S)
    assert lan.landmarks >= MIN_LANDMARKS, lan.logs
    loopback = _run_sides(namespaces, 'loopback', tmp_path, NO_MAP_TIMEOUT_S)
    assert loopback.landmarks == 0, loopback.logs
