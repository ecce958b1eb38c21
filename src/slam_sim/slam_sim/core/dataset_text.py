"""Whitespace-separated dataset text files, read with errors that name ``file:line``."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from enum import Enum
from pathlib import Path

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.errors import DatasetError


def line_error(path: Path, line_no: int, message: str) -> DatasetError:
    """Return a DatasetError ``<path>:<line_no>: <message>``."""
    return DatasetError(f'{path}:{line_no}: {message}')


def read_lines(path: Path) -> list[str]:
    """Return the lines of a UTF-8 text file; DatasetError if missing, unreadable or not text."""
    if not path.is_file():
        raise DatasetError(f'{path}: no such file; check the dataset directory')
    try:
        return path.read_text(encoding='utf-8').splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f'{path}: cannot be read as text: {err}') from None


def data_lines(lines: Sequence[str], *, comment: str | None) -> Iterator[tuple[int, list[str]]]:
    """Yield (1-based line number, tokens) of every line that is neither blank nor a comment."""
    for index, line in enumerate(lines):
        tokens = line.split()
        if tokens and not (comment is not None and tokens[0].startswith(comment)):
            yield index + 1, tokens


def parse_float(token: str, name: str) -> float:
    """Return ``token`` as a finite float; ValueError naming ``name`` otherwise."""
    try:
        value = float(token)
    except ValueError:
        raise ValueError(f'{name} {token!r} is not a number') from None
    if not math.isfinite(value):
        raise ValueError(f'{name} {token!r} is not finite')
    return value


def parse_int(token: str, name: str) -> int:
    """Return ``token`` as an int (decimal digits, optional sign); ValueError otherwise."""
    try:
        return int(token, 10)
    except ValueError:
        raise ValueError(f'{name} {token!r} is not an integer') from None


def parse_stamp_ns(token: str, name: str) -> int:
    """Return decimal seconds ``token`` as int nanoseconds, rounded half-even to 1 ns."""
    try:
        seconds = Decimal(token)
    except InvalidOperation:
        raise ValueError(f'{name} {token!r} is not a number') from None
    if not seconds.is_finite():
        raise ValueError(f'{name} {token!r} is not finite')
    return int((seconds * 1_000_000_000).to_integral_value())


class Kind(Enum):
    """How one column of a table is parsed."""

    STAMP = 'stamp'  # decimal seconds -> int ns
    INT = 'int'
    FLOAT = 'float'


_PARSERS = {Kind.STAMP: parse_stamp_ns, Kind.INT: parse_int, Kind.FLOAT: parse_float}


@dataclass(frozen=True)
class Table:
    """Columns of a numeric text table, each (R,) int64 or float64; 1-based ``line_numbers``."""

    path: Path
    line_numbers: IntArray
    columns: dict[str, IntArray | FloatArray]

    def __len__(self) -> int:
        """Return the number of rows."""
        return len(self.line_numbers)

    def ints(self, name: str) -> IntArray:
        """Return an integer column (STAMP or INT), shape (R,)."""
        column = self.columns[name]
        if column.dtype != np.int64:
            raise TypeError(f'column {name!r} is not an integer column')
        return column.astype(np.int64)

    def floats(self, name: str) -> FloatArray:
        """Return a column as float64, shape (R,)."""
        return self.columns[name].astype(np.float64)

    def error(self, row: int, message: str) -> DatasetError:
        """Return a DatasetError naming the line of ``row``."""
        return line_error(self.path, int(self.line_numbers[row]), message)


def read_table(path: Path, columns: Sequence[tuple[str, Kind]], *, comment: str = '#') -> Table:
    """Return ``path``'s data lines as ``columns``; DatasetError names a bad file:line."""
    names = [name for name, _ in columns]
    parsers = [_PARSERS[kind] for _, kind in columns]
    values: list[list[int | float]] = [[] for _ in columns]
    line_numbers: list[int] = []
    for line_no, tokens in data_lines(read_lines(path), comment=comment):
        if len(tokens) != len(columns):
            raise line_error(
                path,
                line_no,
                f'expected {len(columns)} columns ({", ".join(names)}), got {len(tokens)}',
            )
        try:
            for column, parse, name, token in zip(values, parsers, names, tokens, strict=True):
                column.append(parse(token, name))
        except ValueError as err:
            raise line_error(path, line_no, str(err)) from None
        line_numbers.append(line_no)
    arrays: dict[str, IntArray | FloatArray] = {}
    for (name, kind), column in zip(columns, values, strict=True):
        if kind is Kind.FLOAT:
            arrays[name] = np.array(column, dtype=np.float64)
        else:
            arrays[name] = np.array(column, dtype=np.int64)
    return Table(path, np.array(line_numbers, dtype=np.int64), arrays)
