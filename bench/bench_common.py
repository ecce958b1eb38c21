"""Helpers shared by the benchmarks."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

T = TypeVar('T')

BENCH_DIR = Path(__file__).resolve().parent


def source_revision() -> str:
    """Return the git commit of the measured code, with '+changes' if tracked files differ."""
    try:
        commit = subprocess.run(
            ['git', 'rev-parse', '--short', 'HEAD'],
            cwd=BENCH_DIR,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ['git', 'status', '--porcelain', '--untracked-files=no'],
            cwd=BENCH_DIR,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return 'unknown (no git)'
    return commit + ('+changes' if dirty else '')


def best_of(repeats: int, function: Callable[[], T]) -> tuple[float, T]:
    """Return the shortest wall time (s) of max(repeats, 1) calls and the last result."""
    best = float('inf')
    for _ in range(max(repeats, 1) - 1):
        started = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - started)
    started = time.perf_counter()
    result = function()
    return min(best, time.perf_counter() - started), result


def side_by_side(
    steppers: Sequence[Iterator[object]], count: int
) -> tuple[list[list[float]], list[str | None]]:
    """Advance each of ``steppers`` (one update per ``next``) ``count`` times, the first to
    go alternating from one step to the next so that the machine's load falls on all
    alike. Returns each one's wall time per step (s) and, for one that raised RuntimeError,
    the error's first line (it is not stepped again); one that ends early stops too."""
    latencies: list[list[float]] = [[] for _ in steppers]
    failures: list[str | None] = [None] * len(steppers)
    live = list(range(len(steppers)))
    for step in range(count):
        if not live:
            break
        turn = step % len(live)
        for which in live[turn:] + live[:turn]:
            started = time.perf_counter()
            try:
                next(steppers[which])
            except StopIteration:
                live.remove(which)
                continue
            except RuntimeError as error:  # e.g. GTSAM's IndeterminateLinearSystemException
                failures[which] = (str(error).strip().splitlines() or [repr(error)])[0]
                live.remove(which)
                continue
            latencies[which].append(time.perf_counter() - started)
    return latencies, failures


def pin_to_one_core(cpu: int | None) -> str:
    """Pin this process to one CPU (the last allowed one unless ``cpu``); return its name."""
    cv2.setNumThreads(1)
    if not hasattr(os, 'sched_setaffinity'):
        return 'not pinned (no sched_setaffinity)'
    chosen = sorted(os.sched_getaffinity(0))[-1] if cpu is None else cpu
    os.sched_setaffinity(0, {chosen})
    return f'CPU {chosen}'


def run_meta(pinned: str) -> dict[str, Any]:
    """Return what a report says about the run: date, machine, CPU pinning, Python, numpy,
    OpenCV and the measured commit."""
    return {
        'date': datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC'),
        'platform': platform.platform(),
        'cpus': os.cpu_count(),
        'pinned': pinned,
        'python': platform.python_version(),
        'numpy': np.__version__,
        'opencv': cv2.__version__,
        'commit': source_revision(),
    }
