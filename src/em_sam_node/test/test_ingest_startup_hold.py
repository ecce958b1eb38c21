"""OdometryIngest's startup hold: sightings the detector published before this node matched
it (its transient-local history, delivered late) still get their keyframes; with sightings on
time, the hold changes nothing but when the keyframes come out."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from test_ingest import (
    SETTINGS,
    STEP_NS,
    Recorder,
    assert_chained,
    stamps_to,
    straight_line,
)

from em_sam_node.core.inputs import Increment
from em_sam_node.odometry_ingest.processor import IngestConfig, OdometryIngest

SECOND_NS = 1_000_000_000


def make(hold_s: float) -> tuple[OdometryIngest, Recorder]:
    warnings = Recorder()
    return OdometryIngest(IngestConfig(startup_hold_s=hold_s), warn=warnings), warnings


def history_arrives_late(ingest: OdometryIngest) -> list[Increment]:
    """3 s of odometry at 0.5 m/s (a distance keyframe every second), then the detector's
    sightings of 0.5-2.3 s all at once as a late match delivers them, then one on time."""
    stamps, poses = straight_line(31, 0.05)
    out: list[Increment] = []
    for stamp, pose in zip(stamps.tolist(), poses, strict=True):
        out += ingest.add_odometry(int(stamp), pose)
    for stamp in (5, 12, 17, 23, 29):
        out += ingest.add_observation_stamp(stamp * STEP_NS)
    return out + ingest.flush()


def test_sightings_delivered_late_at_the_start_get_their_keyframes() -> None:
    ingest, warnings = make(hold_s=5.0)
    out = history_arrives_late(ingest)
    assert warnings.messages == []
    assert {5, 12, 17, 23, 29} <= {s // STEP_NS for s in stamps_to(out)}
    assert ingest.hold_ended == f'at the first timely observation ({29 * STEP_NS} ns)'
    assert_chained(out)


def test_without_the_hold_the_late_sightings_are_older_than_a_keyframe() -> None:
    ingest, warnings = make(hold_s=0.0)
    out = history_arrives_late(ingest)
    late = [m for m in warnings.messages if 'older than the last keyframe' in m]
    assert len(late) == 3  # the distance keyframes at 1 s and 2 s came out before them
    assert not {5, 12, 17} & {s // STEP_NS for s in stamps_to(out)}


def test_the_hold_ends_after_startup_hold_s_of_odometry_without_a_sighting() -> None:
    ingest, _ = make(hold_s=2.0)
    stamps, poses = straight_line(40, 0.05)
    emitted_at = []
    for stamp, pose in zip(stamps.tolist(), poses, strict=True):
        if ingest.add_odometry(int(stamp), pose):
            emitted_at.append(stamp)
    assert emitted_at[0] == 2 * SECOND_NS
    assert ingest.hold_ended == 'after 2.0 s of odometry without a timely observation'


def test_a_flush_ends_the_hold() -> None:
    ingest, _ = make(hold_s=5.0)
    stamps, poses = straight_line(10, 0.05)
    for stamp, pose in zip(stamps.tolist(), poses, strict=True):
        assert ingest.add_odometry(int(stamp), pose) == []
    assert stamps_to(ingest.flush()) == [9 * STEP_NS]
    assert ingest.hold_ended == 'at a flush'


@SETTINGS
@given(
    st.lists(
        st.tuples(st.integers(0, 99), st.integers(0, 4)), min_size=1, max_size=40, unique=True
    ),
    st.floats(0.0, 0.3),
)
def test_with_sightings_on_time_the_hold_changes_no_keyframe(
    sightings: list[tuple[int, int]], speed_step_m: float
) -> None:
    """Sightings reach the ingest 0-0.4 s after their stamp (under observation_delay_s): the
    keyframes with the hold are those without it."""
    stamps, poses = straight_line(100, speed_step_m)
    poses[:, 2] = np.linspace(0.0, 2.0, 100)
    arrivals: dict[int, list[int]] = {}
    for index, delay_steps in sightings:
        arrivals.setdefault(min(index + delay_steps, 99), []).append(index * STEP_NS)
    runs = []
    for hold_s in (0.0, 3.0, 20.0):
        ingest, warnings = make(hold_s)
        out: list[Increment] = []
        for index, (stamp, pose) in enumerate(zip(stamps.tolist(), poses, strict=True)):
            out += ingest.add_odometry(int(stamp), pose)
            for sighting in sorted(arrivals.get(index, [])):
                out += ingest.add_observation_stamp(sighting)
        out += ingest.flush()
        assert_chained(out)
        runs.append(([(i.stamp_from_ns, i.stamp_to_ns) for i in out], warnings.messages))
    assert runs[1] == runs[0]
    assert runs[2] == runs[0]


def test_a_sighting_from_before_the_first_odometry_delivered_late_is_named_as_such() -> None:
    ingest, warnings = make(hold_s=5.0)
    stamps, poses = straight_line(10, 0.05)
    for stamp, pose in zip((stamps + SECOND_NS).tolist(), poses, strict=True):
        ingest.add_odometry(int(stamp), pose)
    assert ingest.add_observation_stamp(SECOND_NS // 2) == []
    assert warnings.messages == [
        f'observation stamp {SECOND_NS // 2} ns came before the first odometry (at '
        f'{SECOND_NS} ns); it gets no keyframe'
    ]
