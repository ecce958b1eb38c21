"""MapperProcessor: attaching observations to keyframes, bad input, solving and queries."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synthetic_room import MOVEABLE_IDS, SECOND_NS, make_room, mapper_inputs

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em_types import EmConfig, EmResult
from em_sam_node.core.inputs import Increment, Observation
from em_sam_node.mapper import processor as mapper_module
from em_sam_node.mapper.processor import MapperConfig, MapperProcessor
from slam_core.geometry.se2 import apply_increment, compose, increment_between, wrap_angle

MS_NS = 1_000_000
OBS_COV = np.diag([0.03**2, 0.01**2])
STEP_COV = np.diag([0.03**2, 0.03**2, 0.01**2])


class Recorder:
    """A warn() sink that keeps the messages."""

    def __init__(self) -> None:
        self.messages: list[str] = []

    def __call__(self, message: str) -> None:
        self.messages.append(message)


def make_mapper(**overrides: object) -> tuple[MapperProcessor, Recorder]:
    warnings = Recorder()
    config = MapperConfig(em=EmConfig(), **overrides)  # type: ignore[arg-type]
    return MapperProcessor(config, warn=warnings), warnings


def increment(
    from_s: float, to_s: float, pose_from: list[float], pose_to: list[float]
) -> Increment:
    start, end = np.array(pose_from, dtype=float), np.array(pose_to, dtype=float)
    return Increment(
        round(from_s * SECOND_NS),
        round(to_s * SECOND_NS),
        increment_between(start, end),
        STEP_COV.copy(),
        start,
        end,
    )


def line_chain(count: int, *, start_s: float = 0.0) -> list[Increment]:
    """Increments between ``count + 1`` keyframes one second and one metre apart along x."""
    return [
        increment(start_s + i, start_s + i + 1, [float(i), 0.0, 0.0], [i + 1.0, 0.0, 0.0])
        for i in range(count)
    ]


def observation(
    stamp_ns: int, landmark_id: int = 7, z: tuple[float, float] = (2.0, 0.3)
) -> Observation:
    return Observation(stamp_ns, landmark_id, np.array(z), OBS_COV.copy())


def fed(data: MappingData, *, warnings: Recorder | None = None) -> MapperProcessor:
    processor = MapperProcessor(MapperConfig(em=EmConfig()), warn=warnings)
    increments, observations = mapper_inputs(data)
    for item in increments:
        processor.add_increment(item)
    for item in observations:
        processor.add_observation(item)
    return processor


# --- attaching observations -----------------------------------------------------------------


def test_observations_attach_to_the_keyframe_with_their_stamp_within_tolerance() -> None:
    mapper, warnings = make_mapper(stamp_tolerance_s=0.005)
    for item in line_chain(3):
        mapper.add_increment(item)
    mapper.add_observation(observation(2 * SECOND_NS + 3 * MS_NS, landmark_id=1))
    mapper.add_observation(observation(1 * SECOND_NS - 4 * MS_NS, landmark_id=2))
    mapper.add_observation(observation(3 * SECOND_NS, landmark_id=3))
    mapper.add_observation(observation(1 * SECOND_NS + 6 * MS_NS, landmark_id=4))  # too far
    data = mapper.data()
    assert dict(zip(data.obs_landmark_id.tolist(), data.obs_keyframe.tolist(), strict=True)) == {
        1: 2,
        2: 1,
        3: 3,
    }
    assert [o.landmark_id for o in mapper.pending] == [4]
    assert warnings.messages == []


def test_an_observation_before_its_keyframe_waits_and_attaches_when_it_arrives() -> None:
    mapper, warnings = make_mapper()
    chain = line_chain(3)
    for item in chain[:2]:
        mapper.add_increment(item)
    mapper.add_observation(observation(3 * SECOND_NS, landmark_id=9))
    assert len(mapper.pending) == 1 and len(mapper.data().obs_keyframe) == 0
    mapper.add_increment(chain[2])
    data = mapper.data()
    assert mapper.pending == []
    assert data.obs_keyframe.tolist() == [3] and data.obs_landmark_id.tolist() == [9]
    assert warnings.messages == []


def test_an_observation_before_any_increment_attaches_to_the_first_keyframe() -> None:
    mapper, _ = make_mapper()
    mapper.add_observation(observation(0, landmark_id=5))
    for item in line_chain(2):
        mapper.add_increment(item)
    assert mapper.data().obs_keyframe.tolist() == [0]


def test_an_observation_older_than_the_chain_is_counted_before_the_start_naming_it() -> None:
    mapper, warnings = make_mapper()
    mapper.add_observation(observation(5 * SECOND_NS, landmark_id=42))
    for item in line_chain(2, start_s=10.0):
        mapper.add_increment(item)
    assert mapper.pending == [] and mapper.before_start_observations == 1
    assert mapper.dropped_observations == 0  # not lost by the pipeline: the map had no pose
    assert len(warnings.messages) == 1
    assert 'landmark 42' in warnings.messages[0] and str(5 * SECOND_NS) in warnings.messages[0]
    assert 'older than the first keyframe' in warnings.messages[0]
    assert len(mapper.data().obs_keyframe) == 0


def test_an_observation_whose_keyframe_never_comes_is_dropped_after_the_timeout() -> None:
    mapper, warnings = make_mapper(pending_timeout_s=3.0)
    chain = line_chain(6)
    mapper.add_increment(chain[0])
    mapper.add_observation(observation(SECOND_NS + SECOND_NS // 2, landmark_id=17))  # 1.5 s
    for item in chain[1:4]:  # keyframes up to 4 s: 2.5 s after it, still waiting
        mapper.add_increment(item)
    assert len(mapper.pending) == 1 and warnings.messages == []
    mapper.add_increment(chain[4])  # 5 s: 3.5 s after it
    assert mapper.pending == [] and mapper.dropped_observations == 1
    assert len(warnings.messages) == 1 and 'landmark 17' in warnings.messages[0]


# --- bad increments and observations --------------------------------------------------------


def test_an_increment_that_does_not_start_at_the_latest_keyframe_is_dropped() -> None:
    mapper, warnings = make_mapper()
    chain = line_chain(4)
    mapper.add_increment(chain[0])
    mapper.add_increment(chain[2])  # 2 s -> 3 s, but the chain ends at 1 s
    assert mapper.num_keyframes == 2
    assert len(warnings.messages) == 1
    assert str(2 * SECOND_NS) in warnings.messages[0] and str(SECOND_NS) in warnings.messages[0]
    mapper.add_increment(chain[1])  # the chain goes on where it ended
    assert mapper.stamps_ns == [0, SECOND_NS, 2 * SECOND_NS]


def test_an_increment_that_does_not_go_forward_in_time_is_dropped() -> None:
    mapper, warnings = make_mapper()
    mapper.add_increment(line_chain(1)[0])
    mapper.add_increment(increment(1.0, 1.0, [1.0, 0.0, 0.0], [1.5, 0.0, 0.0]))
    assert mapper.num_keyframes == 2 and len(mapper.increments) == 1
    assert len(warnings.messages) == 1 and 'forward in time' in warnings.messages[0]


@pytest.mark.parametrize(
    ('field', 'index'), [('u', (0,)), ('u', (2,)), ('covariance', (1, 1)), ('covariance', (0, 2))]
)
@pytest.mark.parametrize('bad', [math.nan, math.inf])
def test_a_non_finite_increment_is_dropped(field: str, index: tuple[int, ...], bad: float) -> None:
    mapper, warnings = make_mapper()
    chain = line_chain(2)
    mapper.add_increment(chain[0])
    broken = getattr(chain[1], field).copy()
    broken[index] = bad
    mapper.add_increment(
        Increment(
            chain[1].stamp_from_ns,
            chain[1].stamp_to_ns,
            broken if field == 'u' else chain[1].u,
            broken if field == 'covariance' else chain[1].covariance,
            chain[1].odom_pose_from,
            chain[1].odom_pose_to,
        )
    )
    assert mapper.num_keyframes == 2 and len(mapper.increments) == 1
    assert len(warnings.messages) == 1 and 'non-finite' in warnings.messages[0]


@pytest.mark.parametrize(
    ('z', 'covariance'),
    [
        ((math.nan, 0.1), OBS_COV),
        ((2.0, math.inf), OBS_COV),
        ((0.0, 0.1), OBS_COV),
        ((-1.0, 0.1), OBS_COV),
        ((2.0, 0.1), np.array([[math.nan, 0.0], [0.0, 1e-4]])),
    ],
)
def test_an_invalid_observation_is_dropped_naming_the_landmark(
    z: tuple[float, float], covariance: np.ndarray
) -> None:
    mapper, warnings = make_mapper()
    for item in line_chain(2):
        mapper.add_increment(item)
    mapper.add_observation(Observation(SECOND_NS, 23, np.array(z), covariance))
    assert mapper.dropped_observations == 1 and mapper.pending == []
    assert len(mapper.data().obs_keyframe) == 0
    assert len(warnings.messages) == 1 and 'landmark 23' in warnings.messages[0]


# --- data and solving -----------------------------------------------------------------------


def test_data_has_consistent_shapes_and_the_first_odometry_pose_as_prior() -> None:
    mapper, _ = make_mapper(prior_sigma=(0.1, 0.2, 0.3))
    chain = [increment(0.0, 1.0, [2.0, 1.0, 0.5], [3.0, 1.5, 0.7])]
    chain.append(increment(1.0, 2.5, [3.0, 1.5, 0.7], [3.5, 2.5, 1.0]))
    for item in chain:
        mapper.add_increment(item)
    mapper.add_observation(observation(int(2.5 * SECOND_NS), landmark_id=4))
    mapper.add_observation(observation(0, landmark_id=3))
    mapper.add_observation(observation(SECOND_NS, landmark_id=4))
    data = mapper.data()
    assert data.num_keyframes == 3
    assert data.keyframe_stamps_ns.tolist() == [0, SECOND_NS, int(2.5 * SECOND_NS)]
    assert data.odometry_from.tolist() == [0, 1] and data.odometry_to.tolist() == [1, 2]
    assert data.odometry_u.shape == (2, 3) and data.odometry_cov.shape == (2, 3, 3)
    np.testing.assert_array_equal(data.odometry_u[1], chain[1].u)
    assert data.obs_keyframe.tolist() == [0, 1, 2]  # ordered by keyframe
    assert data.obs_landmark_id.tolist() == [3, 4, 4]
    assert data.obs_z.shape == (3, 2) and data.obs_cov.shape == (3, 2, 2)
    for array in (data.keyframe_stamps_ns, data.odometry_from, data.obs_keyframe):
        assert array.dtype == np.int64
    np.testing.assert_array_equal(data.prior_pose, [2.0, 1.0, 0.5])
    np.testing.assert_allclose(data.prior_cov, np.diag([0.01, 0.04, 0.09]))


def test_data_of_an_empty_mapper_has_empty_shapes() -> None:
    mapper, _ = make_mapper()
    data = mapper.data()
    assert data.num_keyframes == 0
    assert data.odometry_u.shape == (0, 3) and data.odometry_cov.shape == (0, 3, 3)
    assert data.obs_z.shape == (0, 2) and data.obs_cov.shape == (0, 2, 2)


def test_optimize_with_fewer_than_two_keyframes_warns_and_returns_none() -> None:
    mapper, warnings = make_mapper()
    assert mapper.optimize() is None
    # A first increment that goes nowhere leaves a single keyframe.
    mapper.add_increment(increment(1.0, 1.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    assert mapper.num_keyframes == 1
    assert mapper.optimize() is None
    assert mapper.result is None and mapper.map_to_odom() is None
    assert sum('fewer than two keyframes' in m for m in warnings.messages) == 2


def test_a_second_optimize_is_warm_started_from_the_first(monkeypatch: pytest.MonkeyPatch) -> None:
    room = make_room(3, loops=1, moving=False)
    increments, observations = mapper_inputs(room.data)
    mapper = MapperProcessor(MapperConfig(em=EmConfig()))
    starts: list[np.ndarray | None] = []
    original = mapper_module.run_em

    def recording_run_em(
        data: MappingData,
        config: EmConfig,
        *,
        initial_poses: np.ndarray | None = None,
        record_snapshots: bool = True,
    ) -> EmResult:
        starts.append(None if initial_poses is None else initial_poses.copy())
        return original(
            data, config, initial_poses=initial_poses, record_snapshots=record_snapshots
        )

    monkeypatch.setattr(mapper_module, 'run_em', recording_run_em)
    half = 20
    for item in increments[:half]:
        mapper.add_increment(item)
    for item in observations:
        mapper.add_observation(item)
    first = mapper.optimize()
    assert first is not None and starts == [None]
    for item in increments[half:]:
        mapper.add_increment(item)
    second = mapper.optimize()
    assert second is not None and mapper.result_keyframes == len(increments) + 1
    warm = starts[1]
    assert warm is not None and warm.shape == (len(increments) + 1, 3)
    np.testing.assert_array_equal(warm[: half + 1], first.poses)
    # New keyframes: the odometry composed onto the last solved pose.
    expected = apply_increment(first.poses[half], increments[half].u)
    np.testing.assert_allclose(warm[half + 1], expected, atol=1e-12)


# --- queries --------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def solved_room() -> MapperProcessor:
    mapper = fed(make_room(0).data)
    result = mapper.optimize()
    assert result is not None
    assert sorted(result.landmark_ids[result.moveable].tolist()) == list(MOVEABLE_IDS)
    return mapper


@pytest.mark.parametrize('landmark_id', [2, 5, *MOVEABLE_IDS])
def test_find_landmark_returns_every_sighting_most_recent_first(
    solved_room: MapperProcessor, landmark_id: int
) -> None:
    sightings = solved_room.find_landmark(landmark_id)
    assert sightings is not None
    data = solved_room.data()
    expected = np.sort(data.obs_stamp_ns[data.obs_landmark_id == landmark_id])[::-1]
    np.testing.assert_array_equal(sightings.stamps_ns, expected)
    assert np.all(np.diff(sightings.stamps_ns) < 0)
    assert sightings.positions.shape == (len(expected), 2)
    assert sightings.covariances.shape == (len(expected), 2, 2)
    np.testing.assert_array_equal(sightings.covariances, np.swapaxes(sightings.covariances, 1, 2))
    assert np.all(np.linalg.eigvalsh(sightings.covariances) > 0.0)


def test_find_landmark_of_a_moved_landmark_shows_both_positions(
    solved_room: MapperProcessor,
) -> None:
    sightings = solved_room.find_landmark(100)
    assert sightings is not None
    np.testing.assert_allclose(sightings.positions[0], [3.0, 3.0], atol=0.3)  # after the move
    np.testing.assert_allclose(sightings.positions[-1], [3.0, 0.0], atol=0.3)  # before it


def test_find_landmark_of_an_unknown_landmark_is_none(solved_room: MapperProcessor) -> None:
    assert solved_room.find_landmark(999) is None
    assert make_mapper()[0].find_landmark(2) is None  # nothing solved yet


def test_find_landmark_answers_from_the_last_solution_while_new_data_arrives() -> None:
    room = make_room(0)
    increments, observations = mapper_inputs(room.data)
    mapper = MapperProcessor(MapperConfig(em=EmConfig()))
    half = 50
    for item in increments[:half]:
        mapper.add_increment(item)
    for item in observations:
        mapper.add_observation(item)
    assert mapper.optimize() is not None
    before = mapper.find_landmark(2)
    for item in increments[half:]:  # more keyframes, not solved yet
        mapper.add_increment(item)
    after = mapper.find_landmark(2)
    assert before is not None and after is not None
    np.testing.assert_array_equal(after.stamps_ns, before.stamps_ns)
    np.testing.assert_allclose(after.positions, before.positions, atol=1e-9)


def test_map_to_odom_is_the_identity_when_the_map_equals_the_odometry() -> None:
    room = make_room(1, loops=1, moving=False, noise=0.0)
    mapper = fed(room.data)
    assert mapper.optimize() is not None
    transform = mapper.map_to_odom()
    assert transform is not None
    np.testing.assert_allclose(transform[:2], 0.0, atol=1e-6)
    assert wrap_angle(transform[2]) == pytest.approx(0.0, abs=1e-6)


def test_map_to_odom_takes_the_latest_odometry_pose_to_the_solved_pose() -> None:
    room = make_room(2)
    mapper = fed(room.data)
    result = mapper.optimize()
    assert result is not None
    transform = mapper.map_to_odom()
    assert transform is not None
    latest = compose(transform, mapper.odom_poses[-1])
    np.testing.assert_allclose(latest[:2], result.poses[-1, :2], atol=1e-9)
    assert wrap_angle(latest[2] - result.poses[-1, 2]) == pytest.approx(0.0, abs=1e-9)
    assert np.hypot(*transform[:2]) > 0.01  # the odometry drifted: not the identity
