"""Progress lines: steps of unknown cost are said without a made-up ETA."""

from __future__ import annotations

from slam_core.progress import StepProgress


def test_steps_are_said_with_the_time_each_took_and_no_eta() -> None:
    now = [0.0]
    lines: list[str] = []
    progress = StepProgress(
        ('import', 'solve'), label='job', log=lines.append, clock=lambda: now[0]
    )
    progress.start(0)
    now[0] = 2.0
    progress.start(1)
    now[0] = 302.0
    progress.finish()
    assert lines == [
        'job: step 1/2, import (elapsed 0.0s)',
        'job: step 2/2, solve (elapsed 2.0s; import took 2.0s)',
        'job: done in 5m02s (import 2.0s, solve 5m00s)',
    ]
    assert not any('ETA' in line or '%' in line for line in lines)
