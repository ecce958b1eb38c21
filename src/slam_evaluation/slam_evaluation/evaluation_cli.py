"""Command-line helpers the evaluators share (ROS-free)."""

from __future__ import annotations

import argparse


def parse_seeds(text: str) -> tuple[int, ...]:
    """Return seeds from '0-9', '1,4' or '0-3,7'; ValueError if malformed or reversed."""
    seeds: list[int] = []
    for part in text.split(','):
        low, _, high = part.strip().partition('-')
        if not low.isdigit() or (high and not high.isdigit()):
            raise ValueError(f'--seeds {text!r}: use e.g. 0-9, 1,4 or 0-3,7')
        if high and int(high) < int(low):
            raise ValueError(f'--seeds {text!r}: the range {part.strip()} is reversed (low-high)')
        seeds += range(int(low), int(high or low) + 1)
    return tuple(dict.fromkeys(seeds))


def add_tracking_noise_arguments(parser: argparse.ArgumentParser) -> None:
    """Add --tracking-offset-px and --tracking-jump-probability (non-white noise)."""
    parser.add_argument(
        '--tracking-offset-px',
        type=float,
        default=0.0,
        help='simulated tracking error that is not white: per-track offsets of this standard '
        'deviation, correlated over about 1 s, on top of the 1 px white noise; the filters are '
        'told of it as a tracker declares its noise (default 0)',
    )
    parser.add_argument(
        '--tracking-jump-probability',
        type=float,
        default=0.0,
        help='per track and frame, the chance that its offset jumps to a new value (default 0)',
    )
