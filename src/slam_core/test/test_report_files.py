"""slam_core.files: atomic writes leave no temporary file and honour the umask; JSON is
strict (NaN becomes null)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from slam_core.files import keep_previous_run, write_atomically, write_json


def test_atomic_write_replaces_the_file_and_leaves_nothing_else(tmp_path: Path) -> None:
    target = tmp_path / 'sub' / 'report.md'
    write_atomically(target, 'first')
    write_atomically(target, b'second')
    assert target.read_text() == 'second'
    assert [p.name for p in target.parent.iterdir()] == ['report.md']
    assert target.stat().st_mode & 0o777 == 0o666 & ~_umask()


def test_a_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    target = tmp_path / 'report.json'
    write_json(target, {'a': 1})
    with pytest.raises(TypeError):
        write_json(target, {'a': object()})
    assert json.loads(target.read_text()) == {'a': 1}
    assert [p.name for p in tmp_path.iterdir()] == ['report.json']


def test_json_is_strict(tmp_path: Path) -> None:
    target = write_json(tmp_path / 'r.json', {'x': np.float64('nan'), 'y': (np.int64(3),)})
    assert json.loads(target.read_text()) == {'x': None, 'y': [3]}


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_a_previous_run_is_moved_aside_not_overwritten(tmp_path: Path) -> None:
    run = tmp_path / 'em_sam_live'
    assert keep_previous_run(run, 'em_sam_') is None  # nothing there
    run.mkdir()
    assert keep_previous_run(run, 'em_sam_') is None  # empty
    for _ in range(2):  # two runs finished in the same second
        run.mkdir(exist_ok=True)
        (run / 'em_sam_report.json').write_text('{}')
        (run / 'em_sam_map.png').write_bytes(b'png')
        for path in run.iterdir():
            os.utime(path, (1.7e9, 1.7e9))
        moved = keep_previous_run(run, 'em_sam_')
        assert moved is not None and (moved / 'em_sam_report.json').read_text() == '{}'
        assert not run.exists()
    assert sorted(p.name[len('em_sam_live.') :] for p in tmp_path.iterdir()) == [
        time.strftime('%Y%m%d-%H%M%S', time.localtime(1.7e9)) + suffix for suffix in ('', '-2')
    ]
    shared = tmp_path / 'shared'
    shared.mkdir()
    (shared / 'em_sam_report.json').write_text('{}')
    (shared / 'notes.txt').write_text('mine')
    assert keep_previous_run(shared, 'em_sam_') is None and shared.exists()  # not ours alone
