"""respawn in GRAPH files: validation, back-off, and slam_run --processes restarting a node."""

from __future__ import annotations

import os
import stat
import sys
import threading
from pathlib import Path

import pytest
import yaml

from slam_bringup import runner
from slam_bringup.graph import load_graph
from slam_bringup.graph_nodes import node_descriptions
from slam_bringup.supervise import (
    MAX_DELAY_S,
    respawn_delay_s,
    restart_description,
    warn_if_respawn_ignored,
)
from slam_core.errors import GraphError


def write(tmp_path: Path, entry: dict[str, object]) -> Path:
    node = {'name': 'crashy', 'package': 'p', 'executable': 'crashy', **entry}
    path = tmp_path / 'graph.yaml'
    path.write_text(yaml.safe_dump({'graph': {'nodes': [node]}}), encoding='utf-8')
    return path


@pytest.mark.parametrize(
    ('entry', 'message'),
    [
        ({'respawn': 'yes'}, r"nodes\[0\]\.respawn: must be true or false, got str 'yes'"),
        ({'respawn': True, 'respawn_delay_s': 0}, r'respawn_delay_s: 0 must be > 0'),
        ({'respawn_delay_s': 2.0}, r'respawn_delay_s: is set but respawn is not true'),
        ({'respawn_parameters': {'a': 1}}, r'respawn_parameters: is set but respawn is not'),
        ({'respawn': True, 'respawn_parameters': [1]}, r'respawn_parameters: must be a mapping'),
    ],
)
def test_bad_respawn_entries_are_named(
    tmp_path: Path, entry: dict[str, object], message: str
) -> None:
    with pytest.raises(GraphError, match=message):
        load_graph(write(tmp_path, entry))


def test_respawn_parameters_are_checked_against_the_node(tmp_path: Path) -> None:
    entry = {
        'name': 'em_sam_mapper',
        'package': 'em_sam_node',
        'executable': 'em_sam_mapper',
        'respawn': True,
        'respawn_parameters': {'resume_form': 'auto'},
    }
    with pytest.raises(GraphError, match=r"respawn_parameters: 'resume_form' is not a"):
        load_graph(write(tmp_path, entry))


def test_restarts_get_the_respawn_parameters_after_the_others(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        {'respawn': True, 'parameters': [{'x': 1}], 'respawn_parameters': {'resume_from': 'a'}},
    )
    (description,) = node_descriptions(load_graph(path))
    assert description.respawn and description.respawn_delay_s == 1.0
    assert restart_description(description).parameters == ({'x': 1}, {'resume_from': 'a'})
    plain = node_descriptions(load_graph(write(tmp_path, {})))[0]
    assert not plain.respawn and restart_description(plain) == plain


def test_the_back_off_doubles_up_to_a_cap() -> None:
    assert [respawn_delay_s(1.0, n) for n in (1, 2, 3, 4)] == [1.0, 2.0, 4.0, 8.0]
    assert respawn_delay_s(1.0, 50) == MAX_DELAY_S


CRASHY = """#!{python}
import os, signal, sys
from pathlib import Path
log = Path({log!r})
runs = log.read_text().count('run') if log.exists() else 0
with log.open('a') as stream:
    files = [sys.argv[i + 1] for i, a in enumerate(sys.argv) if a == '--params-file']
    text = ' '.join(Path(f).read_text().replace(chr(10), ' ') for f in files)
    stream.write('run ' + text + chr(10))
if runs < 2:
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_slam_run_processes_restarts_a_node_that_dies(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    log = tmp_path / 'runs.log'
    script = bin_dir / 'crashy'
    script.write_text(CRASHY.format(python=sys.executable, log=str(log)), encoding='utf-8')
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv('PATH', f'{bin_dir}{os.pathsep}{os.environ["PATH"]}')
    path = write(
        tmp_path,
        {'respawn': True, 'respawn_delay_s': 0.2, 'respawn_parameters': {'resume_from': 'auto'}},
    )
    graph = load_graph(path)
    scratch = tmp_path / 'scratch'
    scratch.mkdir()
    code = runner.run_processes(graph, node_descriptions(graph), scratch, threading.Event())
    runs = log.read_text(encoding='utf-8').splitlines()
    assert len(runs) == 3, runs  # killed twice, restarted twice, then exited 0
    assert 'resume_from' not in runs[0] and all('resume_from: auto' in r for r in runs[1:])
    err = capsys.readouterr().err
    assert 'slam_run: crashy exited with code -9; respawning in 0.2 s (attempt 1)' in err
    assert 'slam_run: crashy exited with code -9; respawning in 0.4 s (attempt 2)' in err
    assert code == 0


def test_a_node_without_respawn_that_dies_still_fails_the_graph(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    script = bin_dir / 'crashy'
    log = tmp_path / 'runs.log'
    script.write_text(CRASHY.format(python=sys.executable, log=str(log)), encoding='utf-8')
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv('PATH', f'{bin_dir}{os.pathsep}{os.environ["PATH"]}')
    graph = load_graph(write(tmp_path, {}))
    scratch = tmp_path / 'scratch'
    scratch.mkdir()
    code = runner.run_processes(graph, node_descriptions(graph), scratch, threading.Event())
    assert code == runner.EXIT_NODE_FAILED
    assert len(log.read_text(encoding='utf-8').splitlines()) == 1


def test_one_process_says_that_respawn_is_ignored(tmp_path: Path) -> None:
    said: list[str] = []
    descriptions = node_descriptions(load_graph(write(tmp_path, {'respawn': True})))
    warn_if_respawn_ignored(descriptions, said.append)
    assert said == [
        'warning: respawn is ignored in one process (graph.nodes[0]): a node cannot be '
        'restarted alone; run with --processes'
    ]
    said.clear()
    warn_if_respawn_ignored(node_descriptions(load_graph(write(tmp_path, {}))), said.append)
    assert said == []
