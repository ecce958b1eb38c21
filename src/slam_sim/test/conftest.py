"""Shared fixtures of the slam_sim tests: simulated office runs, cached per session."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import pytest

from slam_sim.core.office import OfficeRun, simulate_office


@cache
def _office_run(seed: int, variant: str) -> OfficeRun:
    return simulate_office(seed, variant)


@pytest.fixture(scope='session')
def office_run() -> Callable[[int, str], OfficeRun]:
    """Return ``simulate_office(seed, variant)`` with the default config, cached."""
    return _office_run
