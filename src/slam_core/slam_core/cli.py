"""Console-script plumbing: one-line errors, exit codes, no tracebacks for user errors."""

from __future__ import annotations

import argparse
import functools
import re
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


_DOUBLE_BACKTICKS = re.compile(r'``([^`]+)``')
_ROLE = re.compile(r':(?:mod|func|class|meth|attr|data|ref):`~?([^`]+)`')


def plain_text(text: str) -> str:
    """``text`` (a docstring) with reStructuredText code marks and roles taken off."""
    return _DOUBLE_BACKTICKS.sub(r'\1', _ROLE.sub(r'\1', text))


class PlainDescriptionHelpFormatter(argparse.RawDescriptionHelpFormatter):
    """argparse's RawDescriptionHelpFormatter, its output through ``plain_text``."""

    def format_help(self) -> str:
        return plain_text(super().format_help())


class PlainTextHelpFormatter(argparse.RawTextHelpFormatter):
    """argparse's RawTextHelpFormatter, its output through ``plain_text``."""

    def format_help(self) -> str:
        return plain_text(super().format_help())


HELP_FLAGS = ('-h', '--help')
PRINT_CONFIG = '--print-config'
PRINT_CONFIG_HELP = "print the node's parameter file of defaults, each parameter commented"


def help_requested(argv: list[str]) -> bool:
    """Whether ``argv`` (without the program name) asks for help before any ``--ros-args``."""
    return _flag_before_ros_args(argv, HELP_FLAGS)


def config_requested(argv: list[str]) -> bool:
    """Whether ``argv`` asks for ``--print-config`` before any ``--ros-args``."""
    return _flag_before_ros_args(argv, (PRINT_CONFIG,))


def _flag_before_ros_args(argv: list[str], flags: tuple[str, ...]) -> bool:
    for arg in argv:
        if arg == '--ros-args':
            return False
        if arg in flags:
            return True
    return False


def add_print_config(parser: argparse.ArgumentParser, parameters: ParamTable) -> None:
    """Give an argparse node ``--print-config``: print ``parameters.to_yaml()``, exit 0."""

    class PrintConfig(argparse.Action):
        def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
            print(parameters.to_yaml(), end='')  # noqa: T201
            parser.exit()

    parser.add_argument(PRINT_CONFIG, action=PrintConfig, nargs=0, help=PRINT_CONFIG_HELP)


def node_help(prog: str, doc: str | None, parameters: ParamTable) -> str:
    """A node's --help: usage, module docstring and the declared parameter table."""
    usage = (
        f'usage: {prog} [-h] [{PRINT_CONFIG}] '
        '[--ros-args [-p NAME:=VALUE] [--params-file FILE] [-r FROM:=TO] ...]'
    )
    text = plain_text(without_parameter_section((doc or '').strip()))
    options = f'options:\n  {PRINT_CONFIG}  {PRINT_CONFIG_HELP}'
    return '\n\n'.join(part for part in (usage, text, options, parameters.render()) if part)


_PARAMETER_HEADING = re.compile(r'^Parameters\b[^:]*:')


def without_parameter_section(doc: str) -> str:
    """``doc`` without its 'Parameters...:' sections (docs/design/ros_and_core.md)."""
    lines = doc.splitlines()
    kept: list[str] = []
    skipping = False
    for index, line in enumerate(lines):
        starts_section = not line.startswith((' ', '\t')) and bool(line.strip())
        if starts_section and _PARAMETER_HEADING.match(line):
            skipping = True
            continue
        if skipping and starts_section and index > 0 and not lines[index - 1].strip():
            skipping = False
        if not skipping:
            kept.append(line)
    return '\n'.join(kept).strip()
