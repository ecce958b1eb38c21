"""One BLAS thread and one OpenCV thread per process.

The suite's filters multiply small matrices (a few hundred rows at most). OpenBLAS starts a
thread per core for them; on a shared 2-core machine those threads spin against each other
and the nodes' own threads, and MonoSLAM ran about 20 times slower (215 ms instead of 9 ms
per frame). OpenCV likewise splits an optical-flow pass or a corner search of one 640x480
image over a thread per core: the feature tracker took 80 % of a core at 30 Hz with its
default threads and 66 % with one (the live dynamic scene, the tracker alone with the
camera). With a process per node, the processes are the parallelism: every node process
(``spin.spin_node``) calls ``single_threaded_libraries`` at start-up. A graph in one process
(the runner's default) and the evaluation tools keep OpenCV's threads, the one way their
work reaches the second core, and call ``single_threaded_blas``.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import cv2


def single_threaded_libraries() -> int:
    """Run OpenCV on the calling thread only and limit OpenBLAS to one thread; return how
    many OpenBLAS libraries were limited (module doc)."""
    cv2.setNumThreads(1)
    return single_threaded_blas()


def single_threaded_blas() -> int:
    """Limit the loaded OpenBLAS libraries to one thread; return how many were limited.

    The filters' matrices are small (a few hundred rows): on a shared 2-core machine two
    OpenBLAS threads spin against each other and a run takes ~10 times longer."""
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
