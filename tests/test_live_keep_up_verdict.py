"""bench/live_keep_up.py's verdict: a graph whose nodes never reported, or that took fewer of
a bag's images than the player published, is not keeping up."""

from __future__ import annotations

import importlib.util
import sys
from functools import cache
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


@cache
def _live_keep_up() -> ModuleType:
    """bench/live_keep_up.py as a module (bench/ on the path for its bench_common), once."""
    sys.path.insert(0, str(ROOT / 'bench'))
    spec = importlib.util.spec_from_file_location(
        'live_keep_up', ROOT / 'bench' / 'live_keep_up.py'
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _snapshot(taken: int, published: int = 928) -> dict[str, dict[str, str]]:
    return {
        '/bag_player': {'published /camera/image_raw/compressed': str(published), 'skipped': '0'},
        '/feature_tracker': {'received image': str(taken), 'lost image': '0', 'dropped': '0'},
        '/monoslam': {'received features': str(taken), 'lost': '0', 'dropped': '0'},
    }


def test_a_graph_that_took_every_image_passes_and_one_that_reported_nothing_fails() -> None:
    live = _live_keep_up()
    _, clean = live.rows('processes', {}, _snapshot(928), 31.0)
    assert clean
    lines, clean = live.rows('processes', {}, {'/bag_player': _snapshot(0)['/bag_player']}, 31.0)
    assert not clean and any('nothing measured' in line for line in lines)
    _, clean = live.rows('processes', {}, {}, 31.0)
    assert not clean


def test_images_of_a_bag_not_taken_fail_the_run() -> None:
    live = _live_keep_up()
    _, clean = live.rows('processes', {}, _snapshot(927), 31.0)
    assert not clean
    _, clean = live.rows('processes', {}, _snapshot(0), 31.0)
    assert not clean


def test_a_bag_played_beside_a_simulator_graph_that_ignores_it_fails() -> None:
    """The simulator's frames were all taken, but no node took the bag's images."""
    live = _live_keep_up()
    snapshot = {
        '/bag_player': {'published /camera/image_raw/compressed': '928'},
        '/peoplebot_sim': {'frames published': '310', 'frames late': '0'},
        '/marker_detector': {'processed': '310', 'dropped': '0'},
    }
    lines, clean = live.rows('processes', {}, snapshot, 31.0)
    assert not clean and any("took the bag's images" in line for line in lines)
    del snapshot['/bag_player']
    assert live.rows('processes', {}, snapshot, 31.0)[1]  # the simulator alone passes
