"""Rewrite the hard-coded manylinux Python paths in the ROS 2 wheels' CMake configs.

The msg wheels were built in a manylinux container, so their exported CMake targets name
``/opt/python/cp311-cp311/include/python3.11`` and that interpreter's numpy include directory.
CMake refuses imported targets with missing include directories, which breaks every package
that generates interfaces against them. This rewrites those paths to the running interpreter's
(the venv's) Python and numpy include directories. It is idempotent.
"""

from __future__ import annotations

import argparse
import sys
import sysconfig
from pathlib import Path

MANYLINUX_PREFIX = '/opt/python/cp311-cp311'


def replacements(prefix: Path) -> list[tuple[str, str]]:
    """Return (old, new) path pairs, most specific first."""
    import numpy

    return [
        (f'{MANYLINUX_PREFIX}/include/python3.11', sysconfig.get_paths()['include']),
        (
            f'{MANYLINUX_PREFIX}/lib/python3.11/site-packages/numpy/_core/include',
            numpy.get_include(),
        ),
        (MANYLINUX_PREFIX, str(prefix)),
    ]


def repair(prefix: Path) -> list[Path]:
    """Rewrite the CMake files under ``prefix/share``; return the files changed."""
    changed = []
    pairs = replacements(prefix)
    for path in sorted((prefix / 'share').glob('*/cmake/*.cmake')):
        text = path.read_text(encoding='utf-8')
        if MANYLINUX_PREFIX not in text:
            continue
        for old, new in pairs:
            text = text.replace(old, new)
        tmp = path.with_suffix('.cmake.tmp')
        tmp.write_text(text, encoding='utf-8')
        tmp.replace(path)
        changed.append(path)
    return changed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--prefix', type=Path, default=Path(sys.prefix), help='venv prefix')
    args = parser.parse_args(argv)
    changed = repair(args.prefix)
    if changed:
        print(f'[bootstrap] repaired include paths in {len(changed)} CMake files', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
