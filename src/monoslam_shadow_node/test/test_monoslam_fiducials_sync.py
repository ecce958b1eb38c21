"""monoslam's pairing of features frames with their fiducials (``fiducials_sync``): a frame
waits for its own fiducials however far the detector lags, as long as they keep coming."""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.common.frame_sync import StampSync
from monoslam_shadow_node.monoslam.conversions import TargetSighting
from monoslam_shadow_node.monoslam.processor import SYNC_NAMES, fiducials_sync

MS = 1_000_000
PERIOD_NS = 33 * MS  # a 30 Hz camera
HORIZON_NS = 300 * MS


def _features(frame: int) -> Features:
    return Features(frame * PERIOD_NS, 'camera', np.array([1]), np.array([[1.0, 2.0]]))


def _sighting(frame: int) -> TargetSighting:
    return TargetSighting(frame * PERIOD_NS, 'camera', None, ())


def _lagging_run(sync: StampSync[Features, TargetSighting], skipped: int) -> list[tuple]:
    """Frames 0-59, and their fiducials coming at half the frames' pace, so 1 s behind by the
    last frame (none for ``skipped``); the pairs handed out as (frame, with fiducials), as a
    started filter takes them."""
    out = []
    fiducials = [k for k in range(60) if k != skipped]
    for step in range(120):
        if step < 60:
            sync.add_primary(_features(step))
        if (step % 2 == 0 or step >= 60) and fiducials:
            sync.add_partner(_sighting(fiducials.pop(0)))
        pairs, _ = sync.pop(alone=True)
        out += [(f.stamp_ns // PERIOD_NS, s is not None) for f, s in pairs]
    return out


def test_a_frame_waits_for_fiducials_that_lag_past_the_horizon_while_they_keep_coming() -> None:
    sync = fiducials_sync(0, HORIZON_NS, 100)
    handed = _lagging_run(sync, skipped=33)
    assert [frame for frame, _ in handed] == list(range(60))
    assert [frame for frame, paired in handed if not paired] == [33]
    # the frame whose fiducials the detector skipped went as soon as a later one came
    assert sync.missing_reason(33 * PERIOD_NS) == f'before a later one (stamp {59 * PERIOD_NS} ns)'
    # pairing by the horizon alone (not in order) lets the lagging frames go without them
    plain = StampSync(tolerance_ns=0, horizon_ns=HORIZON_NS, max_entries=100, names=SYNC_NAMES)
    alone = [frame for frame, paired in _lagging_run(plain, skipped=33) if not paired]
    assert len(alone) > 30


def test_frames_go_alone_once_no_fiducials_come_for_the_horizon() -> None:
    sync = fiducials_sync(0, HORIZON_NS, 100)
    for frame in range(6):
        sync.add_primary(_features(frame))
        sync.add_partner(_sighting(frame))
    assert [s is not None for _, s in sync.pop(alone=True)[0]] == [True] * 6
    handed = []
    for frame in range(6, 30):  # the detector stopped after frame 5
        sync.add_primary(_features(frame))
        handed += [f.stamp_ns // PERIOD_NS for f, s in sync.pop(alone=True)[0] if s is None]
    # a frame goes once the frames came 0.3 s past the last fiducials and past it
    assert handed == list(range(6, 29 - HORIZON_NS // PERIOD_NS))
    assert sync.missing_reason(6 * PERIOD_NS) == (
        'while frames came for sync_horizon_s (0.3 s) of stamps after the last '
        f'(stamp {5 * PERIOD_NS} ns)'
    )
    # before the start the same frames are dropped with that reason
    waiting = fiducials_sync(0, HORIZON_NS, 100)
    waiting.add_primary(_features(0))
    waiting.add_partner(_sighting(0))
    for frame in range(1, 30):
        waiting.add_primary(_features(frame))
    pairs, drops = waiting.pop()
    assert len(pairs) == 1 and drops[0].kind == 'no_fiducials'
    assert drops[0].text.endswith(f'of stamps after the last (stamp {0} ns)')
    # fiducials that come back late, after their frame went without them, are named so
    sync.add_partner(_sighting(6))
    sync.add_primary(_features(40))
    _, drops = sync.pop(alone=True)
    assert [d.text for d in drops if d.kind == 'no_features'] == [
        f'fiducials at stamp {6 * PERIOD_NS} ns on fiducials came after its features frame had '
        'gone without it; dropped'
    ]


def test_fiducials_ahead_of_their_frames_wait_for_them() -> None:
    """The detector 1 s ahead of a tracker that skips every third image: each frame the tracker
    made pairs with its fiducials, and those of the skipped images go once a later frame came."""
    sync = fiducials_sync(0, HORIZON_NS, 100)
    made = [k for k in range(90) if k % 3 != 1]
    handed, drops = [], []
    for step in range(120):
        if step < 90:
            sync.add_partner(_sighting(step))
        if step >= 30 and made:
            sync.add_primary(_features(made.pop(0)))
        pairs, dropped = sync.pop(alone=True)
        handed += [(f.stamp_ns // PERIOD_NS, s is not None) for f, s in pairs]
        drops += dropped
    assert handed == [(k, True) for k in range(90) if k % 3 != 1]
    # those of the skipped images once a later frame came and the horizon passed them
    assert sorted(d.stamp_ns // PERIOD_NS for d in drops) == [k for k in range(80) if k % 3 == 1]
    assert sync.waiting_partners == 3
    assert {d.kind for d in drops} == {'no_features'}
