"""bench_common.side_by_side: the solvers a bench compares advance together, the first to go
alternating, and one that fails stops there with its error while the others go on."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))

from bench_common import side_by_side  # noqa: E402


def _stepper(name: str, log: list[str], fail_at: int | None = None) -> Iterator[int]:
    step = 0
    while True:
        if step == fail_at:
            raise RuntimeError(f'Indeterminate system at step {step}\nmore detail')
        log.append(name)
        yield step
        step += 1


def test_the_first_to_go_alternates_and_every_step_is_timed() -> None:
    log: list[str] = []
    latencies, failures = side_by_side([_stepper('a', log), _stepper('b', log)], 4)
    assert log == ['a', 'b', 'b', 'a', 'a', 'b', 'b', 'a']
    assert [len(times) for times in latencies] == [4, 4]
    assert all(t >= 0.0 for times in latencies for t in times)
    assert failures == [None, None]


def test_a_failing_stepper_stops_with_its_first_error_line_and_the_other_goes_on() -> None:
    log: list[str] = []
    latencies, failures = side_by_side([_stepper('a', log, fail_at=2), _stepper('b', log)], 5)
    assert failures == ['Indeterminate system at step 2', None]
    assert [len(times) for times in latencies] == [2, 5]
    assert log.count('b') == 5


def test_a_stepper_that_ends_early_stops_without_a_failure() -> None:
    log: list[str] = []
    short = (step for step in range(2))
    latencies, failures = side_by_side([short, _stepper('b', log)], 4)
    assert [len(times) for times in latencies] == [2, 4]
    assert failures == [None, None]
