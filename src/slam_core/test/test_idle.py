"""IdleWatch: a node's inputs stopped only when two ticks in a row see none for idle_s."""

from __future__ import annotations

import pytest

from slam_core.idle import MIN_TICK_S, IdleWatch


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _ticks(watch: IdleWatch, clock: Clock, count: int) -> list[bool]:
    seen = []
    for _ in range(count):
        clock.now += watch.tick_s
        seen.append(watch.idle())
    return seen


def test_idle_on_the_second_tick_past_idle_s_and_never_while_inputs_come() -> None:
    clock = Clock()
    watch = IdleWatch(0.5, clock)
    assert watch.tick_s == 0.25
    for _ in range(8):  # an input every tick
        clock.now += watch.tick_s
        watch.note_input()
        assert not watch.idle()
    assert _ticks(watch, clock, 4) == [False, False, False, True]  # 0.75 s: armed; 1.0 s: idle
    assert watch.since_input_s == pytest.approx(1.0)
    watch.note_input()
    assert _ticks(watch, clock, 3) == [False, False, False]


def test_a_tick_late_after_a_long_callback_does_not_count() -> None:
    """The timer runs before the inputs that queued while the node was busy: its first tick
    after a 3 s callback sees a stale last input and must not end the wait."""
    clock = Clock()
    watch = IdleWatch(0.5, clock)
    _ticks(watch, clock, 1)
    watch.note_input()
    clock.now += 3.0  # one callback took 3 s
    assert not watch.idle()
    assert _ticks(watch, clock, 1) == [False]  # the next tick on time arms it
    clock.now += 2.0  # an armed watch whose next tick is late is not idle either
    assert not watch.idle()
    assert _ticks(watch, clock, 2) == [False, True]


def test_short_horizons_tick_at_the_floor_and_bad_ones_are_refused() -> None:
    assert IdleWatch(0.02).tick_s == MIN_TICK_S
    clock = Clock()
    watch = IdleWatch(0.02, clock)
    assert _ticks(watch, clock, 2) == [False, True]
    with pytest.raises(ValueError, match='idle_s=0'):
        IdleWatch(0.0)
