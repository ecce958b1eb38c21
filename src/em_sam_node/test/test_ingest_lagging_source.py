"""OdometryIngest with an observation source that lags behind the odometry: while it keeps
publishing (empty arrays for images without sightings) its keyframes are waited for; once it
is silent for observation_silence_s they are not."""

from __future__ import annotations

import numpy as np

from em_sam_node.core.inputs import Increment
from em_sam_node.odometry_ingest.processor import IngestConfig, OdometryIngest

STEP_NS = 100_000_000  # odometry and images at 10 Hz
LAG_STEPS = 15  # the source's messages reach the ingest 1.5 s after their stamps
SPEED_M = 0.1  # per step: a 0.5 m motion keyframe every 0.5 s


def seen_at(step: int) -> bool:
    """Sightings in images 0-19 and 40-59 only; images 20-39 show nothing for 2 s, in which
    the robot travels 2 m (four motion keyframes' worth)."""
    return step < 20 or 40 <= step < 60


def pose(step: int) -> np.ndarray:
    return np.array([SPEED_M * step, 0.0, 0.0])


def run(
    lag_steps: int, *, empty_arrays: bool, steps: int = 80, **config: float
) -> tuple[list[int], OdometryIngest]:
    """Feed odometry and the source's messages, ``lag_steps`` behind, as they would arrive;
    return the keyframe stamps (with the flush) and the ingest. The default startup hold
    keeps the first keyframes until the source has spoken."""
    ingest = OdometryIngest(IngestConfig(**config))  # type: ignore[arg-type]
    out: list[Increment] = []
    for step in range(steps + lag_steps):
        if step < steps:
            out += ingest.add_odometry(step * STEP_NS, pose(step))
        image = step - lag_steps
        if 0 <= image < steps and (empty_arrays or seen_at(image)):
            out += ingest.add_observation_stamp(image * STEP_NS, seen=seen_at(image))
    out += ingest.flush()
    return [out[0].stamp_from_ns, *(i.stamp_to_ns for i in out)], ingest


def test_a_lagging_source_that_says_its_empty_images_gets_every_keyframe_in_order() -> None:
    timely, _ = run(0, empty_arrays=True)
    lagging, ingest = run(LAG_STEPS, empty_arrays=True)
    wanted = {step * STEP_NS for step in range(80) if seen_at(step)}
    assert wanted <= set(lagging)
    assert ingest.refused_stamps == 0
    # the same keyframes as a source without lag: the motion keyframes of the gap included
    assert lagging == timely
    assert any(20 * STEP_NS < stamp < 40 * STEP_NS for stamp in lagging)


def test_a_lagging_source_that_publishes_only_sightings_is_waited_for_through_a_short_gap() -> (
    None
):
    """The 2 s without sightings are shorter than observation_silence_s: the source counts as
    running, and its sightings after the gap keep their keyframes."""
    timely, _ = run(0, empty_arrays=False)
    lagging, ingest = run(LAG_STEPS, empty_arrays=False)
    assert lagging == timely and ingest.refused_stamps == 0


def test_sightings_after_a_silence_longer_than_observation_silence_s_are_refused() -> None:
    """With observation_silence_s 1 s the 2 s gap is a stopped source: the gap's keyframes go
    out observation_delay_s behind the odometry, ahead of the sightings that come 1.5 s late,
    which are refused and counted."""
    lagging, ingest = run(LAG_STEPS, empty_arrays=False, observation_silence_s=1.0)
    wanted = {step * STEP_NS for step in range(80) if seen_at(step)}
    # 40-48 come after the gap's last motion keyframe (at 49) went out; 44 is one of the gap's
    # motion keyframes, so the mapper still has a keyframe at that stamp
    assert ingest.refused_stamps == 9
    assert sorted(wanted - set(lagging)) == [s * STEP_NS for s in (40, 41, 42, 43, 45, 46, 47, 48)]


def test_keyframes_do_not_wait_for_a_silent_source() -> None:
    """The source stops: observation_silence_s later, motion keyframes follow the odometry
    observation_delay_s behind."""
    config = IngestConfig(startup_hold_s=0.0)
    ingest = OdometryIngest(config)
    out: list[Increment] = []
    for step in range(100):
        out += ingest.add_odometry(step * STEP_NS, pose(step))
        if step < 10:
            out += ingest.add_observation_stamp(step * STEP_NS, seen=False)
        if step == 9 + round(config.observation_silence_s * 1e9) // STEP_NS - 1:
            assert out[-1].stamp_to_ns <= 9 * STEP_NS  # still waiting for the source
    delay_ns = round(config.observation_delay_s * 1e9)
    assert out[-1].stamp_to_ns >= 99 * STEP_NS - delay_ns - round(0.5 / SPEED_M) * STEP_NS


def test_a_lagging_source_is_waited_for_at_most_max_buffer_s() -> None:
    config = IngestConfig(startup_hold_s=0.0, max_buffer_s=3.0)
    ingest = OdometryIngest(config)
    out: list[Increment] = []
    for step in range(100):
        out += ingest.add_odometry(step * STEP_NS, pose(step))
        out += ingest.add_observation_stamp(0, seen=False)  # stuck at its first image
    assert out, 'keyframes must go out once the source is max_buffer_s behind'
    assert out[-1].stamp_to_ns >= 99 * STEP_NS - round(3.0e9) - 5 * STEP_NS
