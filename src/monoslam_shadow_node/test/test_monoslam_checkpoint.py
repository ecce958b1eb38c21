"""monoslam's checkpoint without ROS: what it saves and restores, the refusal of bad files
(each named with its problem, the processor unchanged), and what a resumed filter does over
a gap its motion model cannot bridge (keeps the map, re-localises from the target)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.common.notices import Notice
from monoslam_shadow_node.monoslam.checkpoint import (
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
)
from monoslam_shadow_node.monoslam.conversions import PoseFields, TargetSighting
from monoslam_shadow_node.monoslam.core.monoslam_model import CAMERA_SIZE
from monoslam_shadow_node.monoslam.core.monoslam_snapshot import gap_verdict, rotation_limit_rad
from monoslam_shadow_node.monoslam.core.monoslam_types import TRACKING, WAITING, MonoSlamConfig
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor, MonoSlamStep
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
CORNERS_M = 0.08 * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
KNOWN = {k: (float(x), float(y), float(z)) for k, (x, y, z) in enumerate(CORNERS_M)}
CENTRE = np.array([0.0, 0.0, -1.0])  # R_world_camera = I: looking along the world z axis
MS = 1_000_000
IDS = list(range(1, 31))
_RNG = np.random.default_rng(7)
POINTS = np.column_stack([_RNG.uniform(-0.8, 0.8, (30, 2)), _RNG.uniform(1.0, 2.0, 30)])


def _processor(**config: object) -> MonoSlamProcessor:
    settings = MonoSlamConfig(
        known_points=KNOWN, initialize='all', min_new_spacing_px=0.0, **config  # type: ignore[arg-type]
    )  # fmt: skip
    return MonoSlamProcessor(settings, target_text='the test marker', sync_horizon_ns=100 * MS)


def _feed(processor: MonoSlamProcessor, index: int, target: bool = True) -> list:
    """One frame of the static camera at CENTRE: the 30 points, and the target if asked."""
    stamp = index * 33 * MS
    pixels = CAMERA.project(POINTS - CENTRE) + np.random.default_rng(index).normal(0, 0.5, (30, 2))
    corners = CAMERA.project(CORNERS_M - CENTRE) if target else None
    outcomes = processor.add_features(Features(stamp, 'camera', np.array(IDS), pixels))
    return outcomes + processor.add_sighting(TargetSighting(stamp, 'camera', corners, ()))


def _steps(outcomes: list) -> list[MonoSlamStep]:
    return [o for o in outcomes if isinstance(o, MonoSlamStep)]


@pytest.fixture
def tracking() -> MonoSlamProcessor:
    """A processor that tracks, with features in its map, after 8 frames."""
    processor = _processor()
    processor.set_camera(CAMERA)
    for index in range(8):
        _feed(processor, index)
    assert processor.status == TRACKING and len(processor.map_points()) > 20
    return processor


def test_a_checkpoint_restores_the_whole_state(
    tracking: MonoSlamProcessor, tmp_path: Path
) -> None:
    path = tmp_path / 'map.npz'
    pose = PoseFields(5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), tuple(float(v) for v in range(36)))
    save_checkpoint(tracking, path, [pose])
    assert [p.name for p in tmp_path.iterdir()] == ['map.npz']  # no temporary file left
    resumed = _processor()
    assert load_checkpoint(resumed, path) == [pose]
    a, b = tracking.slam, resumed.slam
    assert a is not None and b is not None and b.camera == a.camera
    assert np.array_equal(a._state.x, b._state.x) and np.array_equal(a._state.p, b._state.p)
    assert len(a._state.features) == len(b._state.features)
    for f, g in zip(a._state.features, b._state.features, strict=True):
        assert (f.id, f.start, f.size, f.source, f.searches, f.found, f.attempts) == (
            g.id, g.start, g.size, g.source, g.searches, g.found, g.attempts)  # fmt: skip
        assert (f.reference is None) == (g.reference is None)
    assert a._views._views.keys() == b._views._views.keys() and a.owned_ids == b.owned_ids
    assert a._rng.bit_generator.state == b._rng.bit_generator.state
    assert (resumed.status, resumed.sync.last_ns) == (TRACKING, 7 * 33 * MS)
    assert resumed.counts == tracking.counts


def test_frames_up_to_the_saved_one_are_refused_after_a_resume(
    tracking: MonoSlamProcessor, tmp_path: Path
) -> None:
    save_checkpoint(tracking, tmp_path / 'map.npz')
    resumed = _processor()
    load_checkpoint(resumed, tmp_path / 'map.npz')
    assert _steps(_feed(resumed, 7)) == [] and resumed.counts.processed == 8


def test_no_checkpoint_before_the_camera(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match='no map yet'):
        save_checkpoint(_processor(), tmp_path / 'map.npz')


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as loaded:
        return {name: loaded[name] for name in loaded.files}


def _with_meta(arrays: dict[str, np.ndarray], change) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
    meta = json.loads(str(arrays['meta']))
    change(meta)
    return {**arrays, 'meta': np.array(json.dumps(meta))}


@pytest.mark.parametrize(
    ('change', 'message'),
    [
        (lambda a: _with_meta(a, lambda m: m.update(version=2)),
         'version 2; this monoslam reads version 1'),
        (lambda a: _with_meta(a, lambda m: m.update(format='em_sam_mapper checkpoint')),
         "format 'em_sam_mapper checkpoint', not 'monoslam checkpoint'"),
        (lambda a: {**a, 'x': a['x'][:-1]}, 'state of'),
        (lambda a: {**a, 'p': a['p'][:-1]}, "array 'p' has shape"),
        (lambda a: {**a, 'p': np.full_like(a['p'], np.nan)}, "array 'p' has non-finite values"),
        (lambda a: {k: v for k, v in a.items() if k != 'view_pixel'}, "'view_pixel' is missing"),
        (lambda a: {**a, 'feature_reference': a['feature_reference'][1:]},
         "'feature_reference' has shape"),
        (lambda a: _with_meta(a, lambda m: m['filter'].update(status='lost')),
         "tracking state 'lost'"),
        (lambda a: _with_meta(a, lambda m: m['filter']['known_points'][0].__setitem__(1, 9.0)),
         'initialization target'),
        (lambda a: _with_meta(a, lambda m: m['counts'].pop('lost')), "counts ['lost']"),
        (lambda a: {**a, 'camera_k': np.zeros((3, 3))}, 'focal lengths must be > 0'),
    ],
)  # fmt: skip
def test_a_bad_checkpoint_is_refused_with_its_problem(  # type: ignore[no-untyped-def]
    tracking: MonoSlamProcessor, tmp_path: Path, change, message: str
) -> None:
    good = tmp_path / 'good.npz'
    save_checkpoint(tracking, good)
    bad = tmp_path / 'bad.npz'
    np.savez(bad, **change(_arrays(good)))
    resumed = _processor()
    with pytest.raises(CheckpointError, match=f"checkpoint '{bad}': ") as raised:
        load_checkpoint(resumed, bad)
    assert message in str(raised.value)
    assert resumed.slam is None and resumed.counts.processed == 0  # unchanged


def test_an_unreadable_or_missing_file_is_named(tmp_path: Path) -> None:
    garbage = tmp_path / 'garbage.npz'
    garbage.write_bytes(b'not a zip file')
    with pytest.raises(CheckpointError, match=r"'.*garbage\.npz': not a readable \.npz file"):
        load_checkpoint(_processor(), garbage)
    with pytest.raises(CheckpointError, match=r"'.*missing\.npz': no such file"):
        load_checkpoint(_processor(), tmp_path / 'missing.npz')


def test_a_checkpoint_of_other_tracker_offsets_is_refused(tmp_path: Path) -> None:
    """Declared offsets (estimate_noise off) must match the saved run's."""
    declared = _processor(estimate_noise=False)
    declared.set_camera(CAMERA)
    for index in range(8):
        _feed(declared, index)
    save_checkpoint(declared, tmp_path / 'map.npz')
    with pytest.raises(CheckpointError, match='tracking_offset_px differs'):
        load_checkpoint(
            _processor(tracking_offset_px=1.5, estimate_noise=False), tmp_path / 'map.npz'
        )


def test_a_checkpoint_keeps_the_estimated_noise_and_its_mixed_offset_states(
    tracking: MonoSlamProcessor, tmp_path: Path
) -> None:
    """With estimate_noise the noise in force changed mid-run: the features added under the
    first noise carry no offset states, those added once offsets were taken have them; the
    checkpoint restores both and the noise in force, which the resumed run holds until its
    own estimate is confident."""
    slam = tracking.slam
    assert slam is not None and tracking.noise is not None
    assert {f.offset_size for f in slam._state.features} == {0}
    slam.config = dataclasses.replace(
        slam.config, tracking_offset_px=1.2, tracking_offset_time_s=0.7, pixel_sigma_px=1.1
    )
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.8, 0.8, (12, 2)), rng.uniform(1.0, 2.0, 12)])
    for index in range(8, 14):  # 12 new points, 20 of the old ones out of view
        stamp = index * 33 * MS
        seen = np.vstack([POINTS[:10], points])
        pixels = CAMERA.project(seen - CENTRE) + rng.normal(0, 0.5, (22, 2))
        ids = np.array([*IDS[:10], *range(101, 113)])
        tracking.add_features(Features(stamp, 'camera', ids, pixels))
        tracking.add_sighting(
            TargetSighting(stamp, 'camera', CAMERA.project(CORNERS_M - CENTRE), ())
        )
    offsets = {f.offset_size for f in slam._state.features}
    assert offsets == {0, 2}
    save_checkpoint(tracking, tmp_path / 'map.npz')
    resumed = _processor()
    load_checkpoint(resumed, tmp_path / 'map.npz')
    assert resumed.slam is not None and resumed.noise is not None
    assert {f.offset_size for f in resumed.slam._state.features} == offsets
    restored = resumed.slam.config
    assert (restored.tracking_offset_px, restored.tracking_offset_time_s) == (1.2, 0.7)
    assert restored.pixel_sigma_px == 1.1 and resumed.noise.held == restored
    assert np.array_equal(resumed.slam._state.x, slam._state.x)


def test_after_a_long_gap_it_keeps_the_map_and_re_localises_from_the_target(
    tracking: MonoSlamProcessor, tmp_path: Path
) -> None:
    save_checkpoint(tracking, tmp_path / 'map.npz')
    resumed = _processor()
    load_checkpoint(resumed, tmp_path / 'map.npz')
    slam = resumed.slam
    assert slam is not None
    ids = sorted(p.id for p in resumed.map_points())
    verdict = gap_verdict(slam, 60 * 33 * MS)  # a 1.7 s gap
    assert verdict is not None and not verdict.predict
    assert verdict.rotation_sigma_rad > rotation_limit_rad(slam)
    # the first frame after the gap has no target: the filter waits for it, map kept
    outcomes = _feed(resumed, 60, target=False)
    (step,) = _steps(outcomes)
    assert step.resumed == verdict and step.result.status == WAITING
    (notice,) = [o for o in outcomes if isinstance(o, Notice) and o.kind == 'resumed']
    assert notice.level == 'warning' and 'too long for the motion model' in notice.text
    assert 're-localising from the target (the test marker)' in notice.text
    assert resumed.status == WAITING and resumed.resume_text.startswith('re-localised')
    assert sorted(p.id for p in resumed.map_points()) == ids
    # with the target it tracks again, from the target's pose, with the same map
    (step,) = _steps(_feed(resumed, 61))
    assert step.transition == 're-localised' and step.result.status == TRACKING
    assert step.pose is not None and np.allclose(step.pose.position, CENTRE, atol=0.01)
    assert sorted(p.id for p in resumed.map_points() if p.active) == ids
    assert np.all(slam._state.p[CAMERA_SIZE:, :CAMERA_SIZE] == 0.0)  # map, camera uncorrelated
    (step,) = _steps(_feed(resumed, 62))
    assert step.result.status == TRACKING and len(step.result.measured_ids) > 20
    assert resumed.counts.resumes_relocalised == 1 and resumed.counts.resumes_predicted == 0


def test_after_one_frame_it_predicts_and_says_so(
    tracking: MonoSlamProcessor, tmp_path: Path
) -> None:
    save_checkpoint(tracking, tmp_path / 'map.npz')
    resumed = _processor()
    load_checkpoint(resumed, tmp_path / 'map.npz')
    outcomes = _feed(resumed, 8)
    (step,) = _steps(outcomes)
    assert step.resumed is not None and step.resumed.predict and step.transition is None
    (notice,) = [o for o in outcomes if isinstance(o, Notice) and o.kind == 'resumed']
    assert notice.level == 'info' and 'predicted over the 0.033 s gap' in notice.text
    assert resumed.counts.resumes_predicted == 1
    assert _steps(_feed(resumed, 9))[0].resumed is None  # judged once
