"""em_sam_mapper checkpoints: save, load, validation, and a resumed run equal to an
uninterrupted one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_room import MOVEABLE_IDS, make_room, mapper_inputs

from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.inputs import Increment, Observation
from em_sam_node.mapper import checkpoint as checkpoint_module
from em_sam_node.mapper.checkpoint import (
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
    state_arrays,
)
from em_sam_node.mapper.processor import MapperConfig, MapperProcessor

Inputs = list[tuple[int, Increment | Observation]]


def new_mapper() -> MapperProcessor:
    return MapperProcessor(MapperConfig(em=EmConfig()))


def room_inputs(seed: int = 0) -> Inputs:
    """The room's increments and observations in arrival order: by stamp, an increment
    when its end keyframe is passed (as odometry_ingest emits them)."""
    increments, observations = mapper_inputs(make_room(seed).data)
    items: Inputs = [(i.stamp_to_ns, i) for i in increments]
    items += [(o.stamp_ns, o) for o in observations]
    return sorted(items, key=lambda item: item[0])


def feed(mapper: MapperProcessor, items: Inputs) -> None:
    for _, item in items:
        if isinstance(item, Increment):
            mapper.add_increment(item)
        else:
            mapper.add_observation(item)


def assert_same_state(resumed: MapperProcessor, reference: MapperProcessor) -> None:
    assert resumed.stamps_ns == reference.stamps_ns
    assert np.array_equal(np.array(resumed.odom_poses), np.array(reference.odom_poses))
    assert [(k, o.stamp_ns, o.landmark_id) for k, o in resumed.observations] == [
        (k, o.stamp_ns, o.landmark_id) for k, o in reference.observations
    ]
    assert [(o.stamp_ns, o.landmark_id) for o in resumed.pending] == [
        (o.stamp_ns, o.landmark_id) for o in reference.pending
    ]
    for name in ('dropped_observations', 'before_start_observations', 'dropped_increments'):
        assert getattr(resumed, name) == getattr(reference, name), name


def test_a_checkpoint_round_trips_the_whole_state(tmp_path: Path) -> None:
    mapper = new_mapper()
    items = room_inputs()
    feed(mapper, items[: len(items) // 2])
    mapper.optimize()
    path = tmp_path / 'state' / 'em_sam_checkpoint.npz'
    save_checkpoint(mapper, path)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary left behind

    restored = new_mapper()
    load_checkpoint(restored, path)
    assert_same_state(restored, mapper)
    assert restored.seen_observations == mapper.seen_observations
    assert restored.result is not None and mapper.result is not None
    assert restored.result_keyframes == mapper.result_keyframes
    for name in ('poses', 'landmark_ids', 'positions', 'weights', 'moveable', 'weight_history'):
        assert np.array_equal(getattr(restored.result, name), getattr(mapper.result, name)), name
    assert np.array_equal(restored.map_to_odom(), mapper.map_to_odom())  # type: ignore[arg-type]


def test_a_resumed_mapper_ends_as_an_uninterrupted_one(tmp_path: Path) -> None:
    items = room_inputs()
    half = len(items) // 2
    reference = new_mapper()
    feed(reference, items[:half])
    reference.optimize()
    feed(reference, items[half:])
    reference.optimize()

    first = new_mapper()
    feed(first, items[:half])
    first.optimize()
    path = tmp_path / 'em_sam_checkpoint.npz'
    save_checkpoint(first, path)
    resumed = new_mapper()
    load_checkpoint(resumed, path)
    feed(resumed, items)  # the publishers' history again, then what was missed
    resumed.optimize()

    assert_same_state(resumed, reference)
    assert resumed.duplicate_increments == sum(isinstance(i, Increment) for _, i in items[:half])
    assert resumed.duplicate_observations == sum(
        isinstance(i, Observation) for _, i in items[:half]
    )
    assert reference.duplicate_increments == reference.duplicate_observations == 0
    assert resumed.result is not None and reference.result is not None
    assert np.array_equal(resumed.result.landmark_ids, reference.result.landmark_ids)
    assert np.array_equal(resumed.result.moveable, reference.result.moveable)
    ids = reference.result.landmark_ids[reference.result.moveable].tolist()
    assert set(ids) == set(MOVEABLE_IDS)
    assert np.allclose(resumed.result.weights, reference.result.weights, rtol=0, atol=1e-9)
    assert np.allclose(resumed.result.poses, reference.result.poses, rtol=0, atol=1e-9)
    assert np.allclose(resumed.result.positions, reference.result.positions, rtol=0, atol=1e-9)


def test_replayed_inputs_are_skipped_not_dropped() -> None:
    mapper = new_mapper()
    items = room_inputs()[:40]
    feed(mapper, items)
    before = (mapper.num_keyframes, len(mapper.observations), len(mapper.pending))
    feed(mapper, items)
    assert (mapper.num_keyframes, len(mapper.observations), len(mapper.pending)) == before
    assert mapper.dropped_increments == mapper.dropped_observations == 0
    assert mapper.duplicate_increments + mapper.duplicate_observations == len(items)


def test_a_failed_save_leaves_the_previous_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mapper = new_mapper()
    feed(mapper, room_inputs()[:30])
    path = tmp_path / 'em_sam_checkpoint.npz'
    save_checkpoint(mapper, path)
    saved = path.read_bytes()
    feed(mapper, room_inputs()[30:60])

    def broken(*args: object, **kwargs: object) -> None:
        raise OSError('disk full')

    monkeypatch.setattr(checkpoint_module.np, 'savez', broken)
    with pytest.raises(OSError, match='disk full'):
        save_checkpoint(mapper, path)
    assert path.read_bytes() == saved
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def write_arrays(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    with path.open('wb') as stream:
        np.savez(stream, **arrays)  # type: ignore[arg-type]
    return path


def valid_arrays() -> dict[str, np.ndarray]:
    mapper = new_mapper()
    feed(mapper, room_inputs()[:60])
    mapper.optimize()
    return state_arrays(mapper)


def with_meta(arrays: dict[str, np.ndarray], **changes: object) -> dict[str, np.ndarray]:
    meta = json.loads(str(arrays['meta']))
    meta.update(changes)
    return {**arrays, 'meta': np.array(json.dumps(meta))}


@pytest.mark.parametrize(
    ('change', 'message'),
    [
        (lambda a: with_meta(a, version=99), 'version 99; this mapper reads version 1'),
        (lambda a: with_meta(a, format='other'), "format 'other', not 'em_sam_mapper checkpoint'"),
        (lambda a: {k: v for k, v in a.items() if k != 'odom_poses'}, "'odom_poses' is missing"),
        (lambda a: {**a, 'increment_u': a['increment_u'][:-1]}, "'increment_u' has shape"),
        (lambda a: {**a, 'stamps_ns': a['stamps_ns'][::-1].copy()}, 'do not increase'),
        (
            lambda a: {**a, 'result_weights': np.full_like(a['result_weights'], np.nan)},
            "'result_weights' has non-finite values",
        ),
        (
            lambda a: {**a, 'observation_keyframe': a['observation_keyframe'] + 10_000},
            'attached to a keyframe outside',
        ),
    ],
)
def test_a_bad_checkpoint_is_refused_naming_the_file_and_the_problem(
    tmp_path: Path, change: object, message: str
) -> None:
    path = write_arrays(tmp_path / 'bad.npz', change(valid_arrays()))  # type: ignore[operator]
    mapper = new_mapper()
    with pytest.raises(CheckpointError, match=r'bad\.npz') as error:
        load_checkpoint(mapper, path)
    assert message in str(error.value)
    assert mapper.num_keyframes == 0  # nothing half-restored


def test_a_missing_or_unreadable_checkpoint_is_refused(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match='no such file'):
        load_checkpoint(new_mapper(), tmp_path / 'none.npz')
    garbage = tmp_path / 'garbage.npz'
    garbage.write_bytes(b'not a zip file at all')
    with pytest.raises(CheckpointError, match=r'garbage\.npz.*not a readable \.npz'):
        load_checkpoint(new_mapper(), garbage)


def test_a_resumed_online_mapper_smooths_what_it_held_as_an_uninterrupted_one(
    tmp_path: Path,
) -> None:
    """The smoother is not in the checkpoint: a resumed mapper puts every keyframe and
    observation it holds into a new one, and ends with the uninterrupted one's moveable
    set, its map within a millimetre."""
    items = room_inputs()
    half = len(items) // 2
    online = MapperConfig(em=EmConfig(), online=True)
    reference = MapperProcessor(online)
    feed(reference, items)
    first = MapperProcessor(online)
    feed(first, items[:half])
    path = tmp_path / 'em_sam_checkpoint.npz'
    save_checkpoint(first, path)
    resumed = MapperProcessor(online)
    load_checkpoint(resumed, path)
    feed(resumed, items)
    assert resumed.online is not None and reference.online is not None
    assert resumed.online.num_keyframes == reference.online.num_keyframes
    assert resumed.online_moveable == reference.online_moveable == set(MOVEABLE_IDS)
    kept, again = reference.online.landmark_positions(), resumed.online.landmark_positions()
    assert kept.keys() == again.keys()
    for landmark, position in kept.items():
        assert np.linalg.norm(again[landmark] - position) < 1e-3
