"""Mapper checkpoints: numpy arrays and JSON meta in one .npz (docs/design/ros_and_core.md)."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

import numpy as np

from slam_core.errors import SlamError
from slam_core.files import write_atomically

T = TypeVar('T')


class CheckpointError(SlamError):
    """A checkpoint file that cannot be used; the message names the file and the problem."""


def save_arrays(path: Path, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> None:
    """Write ``arrays`` and ``meta`` (with 'format', 'version') as one .npz, durably."""
    if 'meta' in arrays:
        raise ValueError("'meta' is the name of the meta array; name the array otherwise")
    content = {**arrays, 'meta': np.array(json.dumps(dict(meta)))}

    def write(stream: BinaryIO) -> None:
        np.savez(stream, **content)  # type: ignore[arg-type]

    write_atomically(path, write, durable=True)


def shaped(
    arrays: Mapping[str, np.ndarray], name: str, shape: tuple[int | None, ...]
) -> np.ndarray:
    """Array ``name`` after checking its shape (None: any length) and finite floats."""
    if name not in arrays:
        raise ValueError(f'array {name!r} is missing')
    array = arrays[name]
    if array.ndim != len(shape) or any(
        want is not None and have != want for have, want in zip(array.shape, shape, strict=True)
    ):
        wanted = tuple('N' if s is None else s for s in shape)
        raise ValueError(f'array {name!r} has shape {array.shape}, expected {wanted}')
    if array.dtype.kind == 'f' and not np.all(np.isfinite(array)):
        raise ValueError(f'array {name!r} has non-finite values')
    return array


def _meta(arrays: Mapping[str, np.ndarray], format_name: str, version: int, reader: str) -> Any:
    meta = json.loads(str(shaped(arrays, 'meta', ())))
    if not isinstance(meta, dict):
        raise ValueError("array 'meta' is not a JSON object")
    if meta.get('format') != format_name:
        raise ValueError(f'format {meta.get("format")!r}, not {format_name!r}')
    if meta.get('version') != version:
        raise ValueError(f'version {meta.get("version")!r}; this {reader} reads version {version}')
    return meta


def load_checkpoint_arrays(
    path: Path,
    format_name: str,
    version: int,
    reader: str,
    restore: Callable[[dict[str, np.ndarray], dict[str, Any]], T],
) -> T:
    """Return ``restore(arrays, meta)`` of a checked .npz; CheckpointError if bad."""
    try:
        with np.load(path, allow_pickle=False) as loaded:
            arrays = {name: loaded[name] for name in loaded.files}
    except FileNotFoundError:
        raise CheckpointError(f'checkpoint {str(path)!r}: no such file') from None
    except Exception as err:
        raise CheckpointError(
            f'checkpoint {str(path)!r}: not a readable .npz file ({err})'
        ) from err
    try:
        return restore(arrays, _meta(arrays, format_name, version, reader))
    except (ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f'checkpoint {str(path)!r}: {err}') from err
