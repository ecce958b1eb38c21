"""Console-script plumbing: one-line errors, exit codes, no tracebacks for user errors."""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable

from slam_core.errors import SlamError
from slam_core.params import ParamTable

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130


def console_main(prog: str) -> Callable[[Callable[[list[str] | None], int]], Callable[..., int]]:
    """Wrap a ``main(argv) -> int`` so user errors print ``prog: error: ...`` and exit 2."""

    def decorate(main: Callable[[list[str] | None], int]) -> Callable[..., int]:
        @functools.wraps(main)
        def wrapper(argv: list[str] | None = None) -> int:
            try:
                return main(argv)
            except SlamError as err:
                print(f'{prog}: error: {err}', file=sys.stderr)  # noqa: T201
                return EXIT_USER_ERROR
            except KeyboardInterrupt:
                return EXIT_INTERRUPTED

        return wrapper

    return decorate


def positive_float(text: str) -> float:
    """argparse ``type``: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not value > 0 or value == float('inf'):
        raise argparse.ArgumentTypeError(f'{text!r} must be a finite number > 0')
    return value


HELP_FLAGS = ('-h', '--help')


def help_requested(argv: list[str]) -> bool:
    """Whether ``argv`` (without the program name) asks for help before any ``--ros-args``."""
    for arg in argv:
        if arg == '--ros-args':
            return False
        if arg in HELP_FLAGS:
            return True
    return False


def node_help(prog: str, doc: str | None, parameters: ParamTable) -> str:
    """Return a node executable's --help: usage, the module docstring (what the node does,
    its topics, QoS and frames) and the parameter table from the declaration."""
    usage = (
        f'usage: {prog} [-h] [--ros-args [-p NAME:=VALUE] [--params-file FILE] [-r FROM:=TO] ...]'
    )
    return '\n\n'.join(part for part in (usage, (doc or '').strip(), parameters.render()) if part)
