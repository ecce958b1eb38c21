"""Report files written atomically; strict JSON (docs/design/ros_and_core.md)."""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np


def write_atomically(
    path: Path, data: bytes | str | Callable[[BinaryIO], None], *, durable: bool = False
) -> Path:
    """Write ``data`` (text, bytes or a writer) to ``path`` atomically; fsync if ``durable``."""
    if isinstance(data, str):
        data = data.encode('utf-8')
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
    try:
        os.fchmod(handle, 0o666 & ~_umask())
        with os.fdopen(handle, 'wb') as stream:
            if callable(data):
                data(stream)
            else:
                stream.write(data)
            if durable:
                stream.flush()
                os.fsync(stream.fileno())
        Path(temporary).replace(path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    if durable:
        directory = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
    return path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def jsonable(value: Any) -> Any:
    """``value`` as JSON types; non-finite floats become None."""
    if isinstance(value, Mapping):
        return {str(key): jsonable(item) for key, item in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [jsonable(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def write_json(path: Path, content: Mapping[str, Any]) -> Path:
    """Write ``content`` as indented strict JSON, atomically."""
    text = json.dumps(jsonable(content), indent=2, allow_nan=False)
    return write_atomically(path, text + '\n')


def keep_previous_run(directory: Path, prefix: str) -> Path | None:
    """Rename a previous run's ``directory`` to ``<directory>.<stamp>``; return it or None."""
    files = [path for path in directory.rglob('*') if path.is_file()] if directory.is_dir() else []
    if not files or not all(path.name.startswith(prefix) for path in files):
        return None
    newest = max(path.stat().st_mtime for path in files)
    stamp = time.strftime('%Y%m%d-%H%M%S', time.localtime(newest))
    target = directory.with_name(f'{directory.name}.{stamp}')
    suffix = 2
    while target.exists():
        target = directory.with_name(f'{directory.name}.{stamp}-{suffix}')
        suffix += 1
    directory.rename(target)
    return target
