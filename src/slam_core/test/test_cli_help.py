"""--help text for a terminal: no reStructuredText marks, each parameter once."""

from __future__ import annotations

import argparse

import pytest

from slam_core.cli import (
    PlainDescriptionHelpFormatter,
    node_help,
    plain_text,
    positive_float,
    without_parameter_section,
)
from slam_core.params import Param, ParamTable

DOC = """node_x: does a thing with ``topic_a``.

Topics:
  subscribes  topic_a (see :func:`slam_core.cli.plain_text`)

Parameters (core): the fields of ``Config``.
  rate_hz (10.0)   how often.

Parameters (node):
  depth (5)        queue depth.

Frames: the ``map`` frame.
"""


def test_plain_text_removes_code_marks_and_roles() -> None:
    assert (
        plain_text('the ``online`` flag, :mod:`x.y`, :func:`~a.b`') == 'the online flag, x.y, a.b'
    )


def test_the_parameter_sections_of_a_docstring_are_left_out() -> None:
    text = without_parameter_section(DOC)
    assert 'rate_hz' not in text and 'depth (5)' not in text
    assert text.startswith('node_x: does a thing') and text.endswith('Frames: the ``map`` frame.')
    assert 'Topics:' in text


def test_node_help_prints_each_parameter_once() -> None:
    table = ParamTable('node_x', (Param('depth', 5, 'queue depth'),))
    text = node_help('node_x', DOC, table)
    assert text.count('depth (') == 1 and '``' not in text and ':func:' not in text


def test_the_plain_formatter_strips_marks() -> None:
    parser = argparse.ArgumentParser(
        prog='p', description='uses ``this``', formatter_class=PlainDescriptionHelpFormatter
    )
    assert 'uses this' in parser.format_help() and '``' not in parser.format_help()


@pytest.mark.parametrize('text', ['0', '-1', 'inf', 'nan', 'abc'])
def test_positive_float_refuses(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        positive_float(text)
