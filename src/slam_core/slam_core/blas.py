"""One BLAS thread and one OpenCV thread per process (docs/design/ros_and_core.md)."""

from __future__ import annotations

import ctypes
from pathlib import Path

import cv2


def single_threaded_libraries() -> int:
    """Limit OpenCV and OpenBLAS to one thread; return the OpenBLAS libraries limited."""
    cv2.setNumThreads(1)
    return single_threaded_blas()


def single_threaded_blas() -> int:
    """Limit the loaded OpenBLAS libraries to one thread; return how many were limited."""
    try:
        maps = Path('/proc/self/maps').read_text().splitlines()
    except OSError:
        return 0
    paths = {line.split()[-1] for line in maps if 'openblas' in line and '/' in line}
    limited = 0
    for path in sorted(paths):
        try:
            library = ctypes.CDLL(path)
        except OSError:
            continue
        for name in (
            'scipy_openblas_set_num_threads64_',
            'scipy_openblas_set_num_threads',
            'openblas_set_num_threads64_',
            'openblas_set_num_threads',
        ):
            if hasattr(library, name):
                getattr(library, name)(1)
                limited += 1
                break
    return limited
