"""builtin_interfaces/Time <-> int ns, and the stamps that are not a time."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from slam_core.stamps import ns_to_stamp, stamp_problem, stamp_to_ns


def test_a_stamp_round_trips_through_nanoseconds() -> None:
    stamp = SimpleNamespace(sec=12, nanosec=999_999_999)
    assert stamp_to_ns(stamp) == 12_999_999_999
    back = ns_to_stamp(12_999_999_999, SimpleNamespace(sec=0, nanosec=0))
    assert (back.sec, back.nanosec) == (12, 999_999_999)
    assert stamp_problem(stamp) is None


@pytest.mark.parametrize('nanosec', [1_000_000_000, 4_294_967_295, -1])
def test_nanoseconds_outside_a_second_are_not_a_time(nanosec: int) -> None:
    problem = stamp_problem(SimpleNamespace(sec=2_147_483_647, nanosec=nanosec))
    assert problem == f'nanosec={nanosec} is outside [0, 1e9)'
