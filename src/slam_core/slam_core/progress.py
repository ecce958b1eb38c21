"""Progress for long work: a terminal bar, or periodic log lines (docs/design/ros_and_core.md)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

BAR_WIDTH = 28


def format_seconds(seconds: float) -> str:
    """Return ``seconds`` as ``1h02m``, ``3m05s`` or ``12.3s``."""
    if seconds != seconds or seconds == float('inf'):  # NaN or inf
        return '--'
    if seconds >= 3600:
        return f'{int(seconds // 3600)}h{int(seconds % 3600 // 60):02d}m'
    if seconds >= 60:
        return f'{int(seconds // 60)}m{int(seconds % 60):02d}s'
    return f'{seconds:.1f}s'


class ProgressReporter:
    """Report progress of ``total`` units of work (e.g. bag seconds or iterations)."""

    def __init__(
        self,
        total: float,
        *,
        label: str,
        unit: str = '',
        stream: TextIO | None = None,
        log: Callable[[str], None] | None = None,
        period_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total = max(float(total), 0.0)
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.is_tty = self.stream.isatty() if log is None or stream is not None else False
        self.log = log
        self.period_s = period_s if not self.is_tty else 0.1
        self.clock = clock
        self.started = clock()
        self.last_report = float('-inf')
        self.done = 0.0
        self._last_done: float | None = None
        self.items = 0

    def update(self, done: float, *, items: int | None = None, force: bool = False) -> None:
        """Set the amount done (same unit as total); report if the period has passed."""
        self.done = done
        if items is not None:
            self.items = items
        now = self.clock()
        if force or now - self.last_report >= self.period_s:
            self.last_report = now
            self._last_done = done
            self._emit(self.line(now))

    def finish(self) -> None:
        """Emit the final state (unless just reported) and end the terminal line."""
        if self.is_tty or self.done != self._last_done:
            self._emit(self.line(self.clock()))
        if self.is_tty:
            self.stream.write('\n')
            self.stream.flush()

    def line(self, now: float) -> str:
        """Return the progress text at time ``now``."""
        elapsed = max(now - self.started, 1e-9)
        fraction = min(self.done / self.total, 1.0) if self.total > 0 else 1.0
        rate = self.done / elapsed
        eta = (self.total - self.done) / rate if rate > 0 else float('inf')
        item_rate = f' {self.items} msgs ({self.items / elapsed:.1f}/s)' if self.items else ''
        bar = ''
        if self.is_tty:
            filled = round(fraction * BAR_WIDTH)
            bar = '[' + '#' * filled + '-' * (BAR_WIDTH - filled) + '] '
        return (
            f'{self.label} {bar}{100 * fraction:5.1f}% {self.done:.1f}/{self.total:.1f}'
            f'{self.unit}{item_rate} rate {rate:.2f}{self.unit}/s '
            f'elapsed {format_seconds(elapsed)} ETA {format_seconds(eta)}'
        )

    def _emit(self, text: str) -> None:
        if self.is_tty:
            self.stream.write('\r' + text)
            self.stream.flush()
        elif self.log is not None:
            self.log(text)
        else:
            self.stream.write(text + '\n')
            self.stream.flush()


class StepProgress:
    """Progress through named steps of unknown, unequal cost: said as each starts."""

    def __init__(
        self,
        steps: tuple[str, ...],
        *,
        label: str,
        log: Callable[[str], None] | None = None,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.steps = steps
        self.label = label
        self.log = log
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.started = clock()
        self.took: list[float] = []
        self._step_started: float | None = None

    def start(self, index: int) -> None:
        """Say that step ``index`` (0-based) starts; the one before, if any, ended."""
        now = self.clock()
        previous = ''
        if self._step_started is not None:
            self.took.append(now - self._step_started)
            previous = f'; {self.steps[len(self.took) - 1]} took {format_seconds(self.took[-1])}'
        self._step_started = now
        self._emit(
            f'{self.label}: step {index + 1}/{len(self.steps)}, {self.steps[index]} '
            f'(elapsed {format_seconds(now - self.started)}{previous})'
        )

    def finish(self) -> None:
        """Say that the last step ended, with every step's time."""
        now = self.clock()
        if self._step_started is not None:
            self.took.append(now - self._step_started)
            self._step_started = None
        times = ', '.join(
            f'{name} {format_seconds(spent)}'
            for name, spent in zip(self.steps, self.took, strict=False)
        )
        self._emit(f'{self.label}: done in {format_seconds(now - self.started)} ({times})')

    def _emit(self, text: str) -> None:
        if self.log is not None:
            self.log(text)
        else:
            self.stream.write(text + '\n')
            self.stream.flush()
