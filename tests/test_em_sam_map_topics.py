"""Topic-level: the office bag played paced through odometry_ingest and em_sam_mapper once,
and read as users read it (real rclpy): the online moveable set as it changed, then, solved,
the latched moveable set and map, the find_landmark service, and ~/save_map's files."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from em_sam_office import MOVED, call, play_office
from std_srvs.srv import Trigger

from em_sam_node.mapper.map_files import read_map
from em_sam_node.mapper.node import EmSamMapperNode
from em_sam_node.odometry_ingest.node import OdometryIngestNode
from slam_interfaces.msg import LandmarkMap, MoveableLandmarkArray
from slam_interfaces.srv import FindLandmark
from slam_ros.qos import latched_qos
from slam_ros.testing.harness import Collector, RosHarness, wait_until

pytestmark = [pytest.mark.topic, pytest.mark.slow]


@dataclass
class OfficeRun:
    """The shared run: its harness, the two nodes, and em_sam/moveable_online as it came."""

    harness: RosHarness
    ingest: OdometryIngestNode
    mapper: EmSamMapperNode
    online: Collector


@pytest.fixture(scope='module')
def office(ros_context: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[OfficeRun]:
    """Play the office bag paced through both nodes (``online`` on, as by default) and solve
    once at the end; the module's tests only read the result (topics, services, files)."""
    directory = tmp_path_factory.mktemp('office')
    harness = RosHarness(directory)
    try:
        online = harness.collect('em_sam/moveable_online', MoveableLandmarkArray, latched_qos())
        with pytest.MonkeyPatch.context() as monkeypatch:  # the nodes read it when built
            ingest, mapper = play_office(harness, directory, monkeypatch, online=True)
        yield OfficeRun(harness, ingest, mapper, online)
    finally:
        harness.close()


@pytest.fixture(scope='module')
def mapped(office: OfficeRun) -> tuple[RosHarness, EmSamMapperNode]:
    """The shared run, solved once at the end (``~/optimize``)."""
    reply = call(office.harness, Trigger, '/em_sam_mapper/optimize', Trigger.Request())
    assert reply.success, reply.message  # type: ignore[attr-defined]
    return office.harness, office.mapper


def test_online_the_moveable_set_is_published_as_it_changes(office: OfficeRun) -> None:
    """With ``online``, em_sam/moveable_online carries the smoother's set each time it
    changes; once every keyframe is in, it is the moved markers, each placed where it was
    seen, most recent first."""
    ingest, mapper, online = office.ingest, office.mapper, office.online
    wait_until(
        lambda: mapper.mapper.num_keyframes == ingest.published + 1,
        timeout_s=120,
        what='em_sam_mapper to take every keyframe',
    )
    smoothed = mapper.mapper.num_keyframes - 1  # the last waits for the next one
    wait_until(
        lambda: (
            mapper.mapper.online is not None and mapper.mapper.online.num_keyframes == smoothed
        ),
        timeout_s=120,
        what='the smoother to take every keyframe but the last',
    )
    assert mapper.mapper.online_moveable == MOVED
    wait_until(
        lambda: (
            bool(online.messages)
            and {m.landmark_id for m in online.messages[-1].landmarks} == MOVED
        ),
        timeout_s=30,
        what='the online set to be published',
    )
    assert len(online.messages) >= 2  # it changed on the way
    for landmark in online.messages[-1].landmarks:
        stamps = [s.stamp.sec * 10**9 + s.stamp.nanosec for s in landmark.sightings]
        assert stamps == sorted(stamps, reverse=True) and len(stamps) > 20
        assert landmark.weight < 0.5


def test_moveable_landmarks_and_map(mapped: tuple[RosHarness, EmSamMapperNode]) -> None:
    harness, _ = mapped
    moveable = harness.collect('em_sam/moveable', MoveableLandmarkArray, latched_qos())
    landmarks = harness.collect('em_sam/landmarks', LandmarkMap, latched_qos())
    moveable_message = moveable.wait_for_count(1)[-1]
    map_message = landmarks.wait_for_count(1)[-1]

    assert {m.landmark_id for m in moveable_message.landmarks} == MOVED
    for landmark in moveable_message.landmarks:
        stamps = [s.stamp.sec * 10**9 + s.stamp.nanosec for s in landmark.sightings]
        assert stamps == sorted(stamps, reverse=True)  # most recent first
        assert len(stamps) > 20
        assert landmark.weight < 0.5

    by_id = {e.landmark_id: e for e in map_message.landmarks}
    assert len(by_id) == 39
    assert {i for i, e in by_id.items() if e.moveable} == MOVED
    static = [e for i, e in by_id.items() if i not in MOVED]
    assert all(e.weight > 0.5 and e.num_observations > 0 for e in static)
    assert all(e.covariance[0] > 0 and e.covariance[3] > 0 for e in static)
    assert map_message.header.frame_id == 'map'


def test_find_landmark(mapped: tuple[RosHarness, EmSamMapperNode]) -> None:
    harness, mapper = mapped
    request = FindLandmark.Request(landmark_id=104)
    reply = call(harness, FindLandmark, '/em_sam_mapper/find_landmark', request)
    assert reply.found and reply.moveable  # type: ignore[attr-defined]
    stamps = [s.stamp.sec * 10**9 + s.stamp.nanosec for s in reply.sightings]  # type: ignore[attr-defined]
    assert stamps == sorted(stamps, reverse=True) and len(stamps) > 20
    # The most recent sightings are in office 2, the oldest in office 1 (about 12 m apart).
    newest, oldest = reply.sightings[0].position, reply.sightings[-1].position  # type: ignore[attr-defined]
    assert ((newest.x - oldest.x) ** 2 + (newest.y - oldest.y) ** 2) ** 0.5 > 8.0

    static = call(
        harness, FindLandmark, '/em_sam_mapper/find_landmark', FindLandmark.Request(landmark_id=3)
    )
    assert static.found and not static.moveable  # type: ignore[attr-defined]
    missing = call(
        harness,
        FindLandmark,
        '/em_sam_mapper/find_landmark',
        FindLandmark.Request(landmark_id=999),
    )
    assert not missing.found and '999' in missing.message  # type: ignore[attr-defined]

    report = mapper.write_report()
    assert {p.name for p in report} >= {'em_sam_report.json', 'em_sam_map.png'}


def test_save_map_writes_a_map_readable_without_numpy(
    mapped: tuple[RosHarness, EmSamMapperNode],
) -> None:
    """~/save_map writes the checkpoint and, beside it, the YAML + CSV map: the same
    landmarks, moveable flags and trajectory as the mapper's result, and plain CSV text."""
    harness, mapper = mapped
    reply = call(harness, Trigger, '/em_sam_mapper/save_map', Trigger.Request())
    assert reply.success and 'em_sam_map.yaml' in reply.message  # type: ignore[attr-defined]
    assert mapper.checkpoint_file is not None
    saved = read_map(mapper.checkpoint_file.parent)
    result = mapper.mapper.result
    assert result is not None
    assert saved.ids.tolist() == result.landmark_ids.tolist()
    assert saved.moveable.tolist() == result.moveable.tolist()
    assert set(saved.ids[saved.moveable].tolist()) == set(range(100, 110))
    assert np.array_equal(saved.positions, result.positions)  # repr() round-trips floats
    assert np.array_equal(saved.poses, result.poses[: len(saved.poses)])
    assert saved.stamps_ns.tolist() == mapper.mapper.stamps_ns[: len(saved.stamps_ns)]
    # the static landmarks' joint covariance, which localization on this map tests against
    static = saved.ids[~saved.moveable]
    assert saved.joint_ids is not None and saved.joint_ids.tolist() == sorted(static.tolist())
    assert saved.joint is not None and saved.joint.shape == (2 * len(static), 2 * len(static))
    assert np.all(np.linalg.eigvalsh(saved.joint) > 0)
    with (mapper.checkpoint_file.parent / 'em_sam_landmarks.csv').open() as rows:
        header = next(csv.reader(rows))
    assert header[:3] == ['id', 'x_m', 'y_m']
