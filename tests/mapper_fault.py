"""Run em_sam_office_respawn.yaml with ``slam_run --processes``, optionally SIGKILL its
em_sam_mapper mid-run, and read the final map (shared by the topic test and
bench/fault_mapper.py); or compute offline the map an uninterrupted run ends with.

The mapper is found among slam_run's own children (its command line names the node), so
only the process this run started is killed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from graph_checks import graph_node_parameters

from em_sam_node.core.em import run_em
from em_sam_node.mapper import settings as mapper_settings
from em_sam_node.odometry_ingest import settings as odometry_ingest_settings
from em_sam_node.offline import replay_bag
from slam_ros.diagnostics import LOST_TEXT

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'office_moveable.mcap'
GRAPH = 'em_sam_office_respawn.yaml'
GRAPH_FILE = ROOT / 'src' / 'slam_bringup' / 'graphs' / GRAPH
REPORT = Path('out') / 'em_sam_respawn' / 'em_sam_report.json'
CHECKPOINT = Path('out') / 'em_sam_respawn' / 'em_sam_checkpoint.npz'
CHECKPOINT_PERIOD_S = 2.0  # as the GRAPH sets it
RUN_TIMEOUT_S = 240.0


@dataclass
class MapperRun:
    """What one run ended with."""

    status: int
    log: str
    num_keyframes: int = 0
    moveable_ids: list[int] = field(default_factory=list)
    positions: dict[int, np.ndarray] = field(default_factory=dict)
    killed_at_s: float | None = None  # wall time of the SIGKILL, from the run's start
    checkpoint_age_s: float | None = None  # how old the last checkpoint was at the SIGKILL


def _mapper_pid(parent: int) -> int | None:
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            status = (entry / 'status').read_text()
            command = (entry / 'cmdline').read_bytes().split(b'\0')
        except OSError:
            continue
        ppid = next(
            (line.split()[1] for line in status.splitlines() if line.startswith('PPid')), ''
        )
        if ppid == str(parent) and b'__node:=em_sam_mapper' in command:
            return int(entry.name)
    return None


def run(workdir: Path, *, rate: float, kill_after_s: float | None, domain_id: int) -> MapperRun:
    """Run the graph in ``workdir``; SIGKILL the mapper ``kill_after_s`` after its first
    checkpoint that holds keyframes (None: never)."""
    workdir.mkdir(parents=True, exist_ok=True)
    log_path = workdir / 'slam_run.log'
    env = {**os.environ, 'PYTHONUNBUFFERED': '1', 'ROS_DOMAIN_ID': str(domain_id)}
    command = [
        sys.executable, '-m', 'slam_bringup.runner', GRAPH, '--processes',
        '--bag', str(BAG), '--rate', str(rate),
    ]  # fmt: skip
    started = time.monotonic()
    result = MapperRun(status=-1, log='')
    with log_path.open('wb') as output:
        process = subprocess.Popen(
            command, cwd=workdir, stdout=output, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=env,
        )  # fmt: skip
        try:
            if kill_after_s is not None:
                _kill_mapper(process, workdir / CHECKPOINT, kill_after_s, started, result)
            result.status = process.wait(timeout=RUN_TIMEOUT_S)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    result.log = log_path.read_text(errors='replace')
    report_path = workdir / REPORT
    if report_path.is_file():
        report = json.loads(report_path.read_text())
        result.num_keyframes = int(report['num_keyframes'])
        result.moveable_ids = sorted(int(i) for i in report['moveable_ids'])
        result.positions = {
            int(item['id']): np.array(item['position_m']) for item in report['landmarks']
        }
    return result


def _kill_mapper(
    process: subprocess.Popen[bytes],
    checkpoint: Path,
    kill_after_s: float,
    started: float,
    result: MapperRun,
) -> None:
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while not _holds_keyframes(checkpoint):
        if process.poll() is not None or time.monotonic() > deadline:
            return
        time.sleep(0.05)
    time.sleep(kill_after_s)
    pid = _mapper_pid(process.pid)
    if pid is None:
        return
    age = time.time() - checkpoint.stat().st_mtime
    os.kill(pid, signal.SIGKILL)
    result.killed_at_s = time.monotonic() - started
    result.checkpoint_age_s = age


def _holds_keyframes(checkpoint: Path) -> bool:
    """Whether the checkpoint exists and holds keyframes: from then on the bag's inputs
    change the mapper's state in every checkpoint period, so the checkpoint's age at the kill
    is the work lost (the mapper writes one only when its state changed: before its inputs
    flow, an old checkpoint loses nothing)."""
    try:
        with np.load(checkpoint) as arrays:
            return len(arrays['stamps_ns']) > 0
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return False  # not there yet


def lost_inputs(log: str) -> list[str]:
    """The log lines where a node said its queues lost messages (``slam_ros.diagnostics``)."""
    return [line for line in log.splitlines() if LOST_TEXT in line]


def landmark_difference_m(a: MapperRun, b: MapperRun) -> float:
    """The largest distance between the two runs' positions of a landmark (inf when the
    landmark sets differ)."""
    if set(a.positions) != set(b.positions) or not a.positions:
        return float('inf')
    return max(float(np.linalg.norm(a.positions[i] - b.positions[i])) for i in a.positions)


def offline_reference() -> MapperRun:
    """The map an uninterrupted run of the graph ends with, computed offline: the bag through
    OdometryIngest and MapperProcessor in bag order with the graph's settings for the two
    nodes (``offline.replay_bag``), then EM-SAM on all of it, as the mapper's last solve.

    An uninterrupted run's report equals it exactly: the same 1802 keyframes and moveable
    set, every landmark 0.0 m apart (measured on the runs the topic test made before it
    used this)."""
    ingest = odometry_ingest_settings.config_from_parameters(
        graph_node_parameters(GRAPH_FILE, 'odometry_ingest', odometry_ingest_settings.PARAMETERS)
    )
    mapper = mapper_settings.config_from_parameters(
        graph_node_parameters(GRAPH_FILE, 'em_sam_mapper', mapper_settings.PARAMETERS)
    )
    replay = replay_bag(BAG, ingest=ingest, mapper=mapper)
    result = run_em(replay.data, mapper.em)
    ids = result.landmark_ids.tolist()
    return MapperRun(
        status=0,
        log='\n'.join(replay.warnings),
        num_keyframes=replay.data.num_keyframes,
        moveable_ids=sorted(int(i) for i in result.landmark_ids[result.moveable]),
        positions={int(i): np.array(result.positions[k]) for k, i in enumerate(ids)},
    )
