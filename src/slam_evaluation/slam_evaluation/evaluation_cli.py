"""Command-line helpers the evaluators share (ROS-free)."""

from __future__ import annotations


def parse_seeds(text: str) -> tuple[int, ...]:
    """Return seeds from '0-9', '1,4' or '0-3,7'; ValueError if malformed or a range is
    reversed ('5-2' would give no seeds)."""
    seeds: list[int] = []
    for part in text.split(','):
        low, _, high = part.strip().partition('-')
        if not low.isdigit() or (high and not high.isdigit()):
            raise ValueError(f'--seeds {text!r}: use e.g. 0-9, 1,4 or 0-3,7')
        if high and int(high) < int(low):
            raise ValueError(f'--seeds {text!r}: the range {part.strip()} is reversed (low-high)')
        seeds += range(int(low), int(high or low) + 1)
    return tuple(dict.fromkeys(seeds))
