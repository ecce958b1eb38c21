"""shadow_filter's frame synchronizer: a features frame and SLAM's camera pose of the same
image go together, in stamp order, whatever order they come in; what cannot be paired is
dropped and named."""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from monoslam_shadow_node.common.frame_sync import FrameSynchronizer

MS = 1_000_000


def _sync(tolerance_ns: int = 0, horizon_ns: int = 300 * MS, size: int = 5) -> FrameSynchronizer:
    return FrameSynchronizer(
        tolerance_ns=tolerance_ns, horizon_ns=horizon_ns, max_entries=size, pose_topic='pose'
    )


def _features(stamp_ns: int) -> Features:
    return Features(stamp_ns, 'camera', np.array([1]), np.array([[1.0, 2.0]]))


def _pose(stamp_ns: int) -> CameraPose:
    return CameraPose(stamp_ns, 'map', np.eye(3), np.zeros(3), None)


def _stamps(pairs: list[tuple[Features, CameraPose]]) -> list[tuple[int, int]]:
    return [(f.stamp_ns, p.stamp_ns) for f, p in pairs]


def test_frames_pair_by_stamp_in_either_arrival_order() -> None:
    sync = _sync()
    assert sync.add_pose(_pose(100 * MS)) == []
    assert sync.pop() == ([], [])
    sync.add_features(_features(100 * MS))
    sync.add_features(_features(133 * MS))
    pairs, drops = sync.pop()
    assert _stamps(pairs) == [(100 * MS, 100 * MS)] and drops == []
    sync.add_pose(_pose(133 * MS))
    assert _stamps(sync.pop()[0]) == [(133 * MS, 133 * MS)]
    assert sync.waiting_features == sync.waiting_poses == 0


def test_tolerance_pairs_the_nearest_pose() -> None:
    sync = _sync(tolerance_ns=2 * MS)
    sync.add_pose(_pose(99 * MS))
    sync.add_pose(_pose(101 * MS + 500_000))
    sync.add_features(_features(100 * MS + 900_000))
    assert _stamps(sync.pop()[0]) == [(100 * MS + 900_000, 101 * MS + 500_000)]


def test_hold_waits_for_the_camera_then_releases_in_stamp_order() -> None:
    sync = _sync()
    for stamp in (200, 100):
        sync.add_features(_features(stamp * MS))
        sync.add_pose(_pose(stamp * MS))
    assert sync.pop(hold=True) == ([], [])
    assert _stamps(sync.pop()[0]) == [(100 * MS, 100 * MS), (200 * MS, 200 * MS)]


def test_unpaired_frames_and_poses_are_dropped() -> None:
    sync = _sync()
    sync.add_features(_features(100 * MS))  # its pose never comes: a later one comes first
    sync.add_pose(_pose(105 * MS))  # no features with this stamp
    sync.add_features(_features(133 * MS))
    sync.add_pose(_pose(133 * MS))
    pairs, drops = sync.pop()
    assert _stamps(pairs) == [(133 * MS, 133 * MS)]
    assert [(d.kind, d.stamp_ns) for d in drops] == [('no_pose', 100 * MS)]
    assert drops[0].text == (
        f'features frame at stamp {100 * MS} ns dropped: no camera pose with its stamp came '
        f'on pose before a later one (stamp {133 * MS} ns)'
    )
    sync.add_features(_features(450 * MS))  # the pose without features, after the horizon
    pairs, drops = sync.pop()
    assert pairs == [] and [(d.kind, d.stamp_ns) for d in drops] == [('no_features', 105 * MS)]
    assert drops[0].text.startswith(
        f'camera pose at stamp {105 * MS} ns on pose matches no features'
    )
    assert f'nearest features stamp {100 * MS} ns, -5.000 ms away' in drops[0].text
    sync.add_pose(_pose(900 * MS))  # a pose ahead of its frame waits for it past the horizon
    sync.add_features(_features(500 * MS))
    pairs, drops = sync.pop()
    assert pairs == [] and [(d.kind, d.stamp_ns) for d in drops] == [
        ('no_pose', 450 * MS),
        ('no_pose', 500 * MS),
    ]
    sync.add_features(_features(900 * MS))
    assert _stamps(sync.pop()[0]) == [(900 * MS, 900 * MS)]


def test_frames_wait_for_poses_later_than_the_horizon() -> None:
    """The poses come from the SLAM filter in stamp order, behind the features by its
    processing time: however far behind, each frame waits for its pose (within queue_size),
    and a frame whose pose did not come goes once a later one has."""
    sync = _sync(size=100)
    sync.add_features(_features(67 * MS))
    sync.add_pose(_pose(67 * MS))
    assert len(sync.pop()[0]) == 1
    for k in range(40):  # 1.3 s of frames at 30 Hz before the next pose (horizon 0.3 s)
        sync.add_features(_features((100 + 33 * k) * MS))
    assert sync.pop() == ([], [])
    for k in range(40):
        if k != 7:  # the SLAM filter skipped frame 7
            sync.add_pose(_pose((100 + 33 * k) * MS))
    pairs, drops = sync.pop()
    assert len(pairs) == 39 and [(d.kind, d.stamp_ns) for d in drops] == [('no_pose', 331 * MS)]
    # before the first pose, and for a frame that came after a later pose (the two topics'
    # arrival order is not guaranteed), the horizon holds
    late = _sync()
    late.add_features(_features(100 * MS))
    late.add_features(_features(500 * MS))
    assert [(d.kind, d.stamp_ns) for d in late.pop()[1]] == [('no_pose', 100 * MS)]
    late.add_pose(_pose(600 * MS))
    late.add_features(_features(550 * MS))
    late.add_pose(_pose(550 * MS))
    assert _stamps(late.pop()[0]) == [(550 * MS, 550 * MS)]


def test_flush_drops_frames_without_pose_when_the_inputs_stop() -> None:
    sync = _sync()
    sync.add_features(_features(100 * MS))
    sync.add_features(_features(133 * MS))
    sync.add_pose(_pose(133 * MS))
    pairs, drops = sync.pop(flush=True)
    assert _stamps(pairs) == [(133 * MS, 133 * MS)]
    assert [(d.kind, d.stamp_ns) for d in drops] == [('no_pose', 100 * MS)]


def test_out_of_order_repeated_and_overflowing_inputs_are_named() -> None:
    sync = _sync(size=2)
    sync.add_features(_features(200 * MS))
    sync.add_pose(_pose(200 * MS))
    sync.pop()
    sync.add_features(_features(100 * MS))
    _, drops = sync.pop()
    assert [str(d) for d in drops] == [
        f'features frame at stamp {100 * MS} ns dropped: not after the frame processed last '
        f'({200 * MS} ns); frames must come in stamp order'
    ]
    sync.add_pose(_pose(100 * MS))
    sync.add_features(_features(900 * MS))
    assert sync.pop()[1] == []  # the late frame's pose goes quietly: it was reported already
    assert sync.add_features(_features(900 * MS))[0].kind == 'repeated'
    assert sync.add_pose(_pose(950 * MS)) == []
    assert 'one with this stamp is waiting' in sync.add_pose(_pose(950 * MS))[0].text
    sync.add_features(_features(1000 * MS))
    overflow = sync.add_features(_features(1100 * MS))
    assert [str(d) for d in overflow] == [
        f'features frame at stamp {900 * MS} ns dropped: queue_size=2 frames are waiting already'
    ]


# --- launch file ---------------------------------------------------------------------------
