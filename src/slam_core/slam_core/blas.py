"""One BLAS thread per process.

The suite's filters multiply small matrices (a few hundred rows at most). OpenBLAS starts a
thread per core for them; on a shared 2-core machine those threads spin against each other
and the nodes' own threads, and MonoSLAM ran about 20 times slower (215 ms instead of 9 ms
per frame). Every node (``spin.spin_node``), the in-process graph runner and the evaluation
tools limit OpenBLAS to one thread at start-up.
"""

from __future__ import annotations

import ctypes
from pathlib import Path


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
