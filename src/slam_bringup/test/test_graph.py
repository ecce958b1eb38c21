"""GRAPH files: validation messages, node descriptions, --ros-args, the shipped graphs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml

from slam_bringup import graph as graph_module
from slam_bringup import graph_nodes
from slam_bringup.graph import load_graph
from slam_bringup.graph_nodes import (
    PLAYER_PLUGIN,
    RECORDER_PLUGIN,
    node_descriptions,
    ros_arguments,
    with_overrides,
)
from slam_core.errors import GraphError

PACKAGE_DIR = Path(__file__).resolve().parents[1]

VALID = """\
graph:
  description: two nodes, a player and a recorder
  use_sim_time: true
  nodes:
    - name: ingest
      package: em_sam_node
      executable: odometry_ingest
      plugin: graph_example.ingest:IngestNode
      namespace: robot1
      parameters: [config/ingest.yaml, {max_gap_s: 0.5, frames: {odom: odom}}]
      remappings: {odom: /wheel/odom}
    - name: mapper
      package: em_sam_node
      executable: em_sam_mapper
      remappings: ['landmark_observations:=/markers']
  player:
    bag: bags/sample
    rate: 2.0
    topics: [/odom]
    remap: ['/odom:=/wheel/odom']
  recorder:
    output: out/run
    topics: [/wheel/odom, /em_sam/path]
"""

PARAMETER_FILE = '/**:\n  ros__parameters:\n    max_gap_s: 1.0\n'


def write_graph(directory: Path, text: str, name: str = 'graph.yaml') -> Path:
    """Write a GRAPH file with its parameter file and bag directory next to it."""
    (directory / 'config').mkdir(exist_ok=True)
    (directory / 'config' / 'ingest.yaml').write_text(PARAMETER_FILE)
    (directory / 'bags' / 'sample').mkdir(parents=True, exist_ok=True)
    path = directory / name
    path.write_text(text)
    return path


def node_entry(**changes: object) -> dict[str, object]:
    """A valid node entry of a GRAPH, with changes."""
    entry: dict[str, object] = {'name': 'a', 'package': 'p', 'executable': 'e'}
    entry.update(changes)
    return {key: value for key, value in entry.items() if value is not None}


def graph_text(**graph: object) -> str:
    return yaml.safe_dump({'graph': graph})


# -- validation ---------------------------------------------------------------------------
BAD_GRAPHS = {
    'yaml syntax': ('graph:\n  nodes: [\n', 'line 3', 'YAML syntax error'),
    'duplicate yaml key': (
        'graph:\n  nodes: []\n  nodes: []\n',
        'line 3',
        "duplicate key 'nodes'",
    ),
    'empty file': ('', 'graph.yaml', 'is empty'),
    'no graph key': ('nodes: []\n', 'nodes:', 'unknown key'),
    'graph not a mapping': ('graph: [1]\n', 'graph:', 'must be a mapping'),
    'unknown graph key': (graph_text(nodez=[]), 'graph.nodez:', "did you mean 'nodes'"),
    'unknown node key': (
        graph_text(nodes=[node_entry(paramters=[])]),
        'graph.nodes[0].paramters:',
        "did you mean 'parameters'",
    ),
    'missing required key': (
        graph_text(nodes=[node_entry(package=None)]),
        'graph.nodes[0].package:',
        'missing required key',
    ),
    'name of wrong type': (
        graph_text(nodes=[node_entry(), node_entry(name=5)]),
        'graph.nodes[1].name:',
        'must be a string, got int 5',
    ),
    'invalid node name': (
        graph_text(nodes=[node_entry(name='my-node')]),
        'graph.nodes[0].name:',
        'not a valid name',
    ),
    'nodes not a list': (graph_text(nodes={'a': 1}), 'graph.nodes:', 'must be a list'),
    'rate of wrong type': (graph_text(player={'rate': 'fast'}), 'graph.player.rate:', 'number'),
    'rate not positive': (graph_text(player={'rate': 0}), 'graph.player.rate:', '> 0'),
    'bool of wrong type': (
        graph_text(exit_when_player_done='yes'),
        'graph.exit_when_player_done:',
        'true or false',
    ),
    'recorder topics of wrong type': (
        graph_text(recorder={'topics': '/odom'}),
        'graph.recorder.topics:',
        'list of strings',
    ),
    'duplicate node name': (
        graph_text(nodes=[node_entry(), node_entry(executable='f')]),
        'graph.nodes[1].name:',
        "node '/a' is also graph.nodes[0]",
    ),
    'node named like the player': (
        graph_text(nodes=[node_entry(name='bag_player')], player={}),
        'graph.nodes[0].name:',
        'is also graph.player',
    ),
    'missing parameter file': (
        graph_text(nodes=[node_entry(), node_entry(name='b', parameters=[{}, 'nope.yaml'])]),
        'graph.nodes[1].parameters[1]:',
        "file 'nope.yaml' does not exist",
    ),
    'parameter file without ros__parameters': (
        graph_text(nodes=[node_entry(parameters=['graph.yaml'])]),
        'graph.nodes[0].parameters[0]:',
        "no 'ros__parameters' key",
    ),
    'parameters not a list': (
        graph_text(nodes=[node_entry(parameters={'a': 1})]),
        'graph.nodes[0].parameters:',
        'must be a list',
    ),
    'mixed-type parameter list': (
        graph_text(nodes=[node_entry(parameters=[{'gains': [1, 2.5]}])]),
        'graph.nodes[0].parameters[0].gains:',
        'one type',
    ),
    'empty parameter list': (
        graph_text(nodes=[node_entry(parameters=[{'topics': []}])]),
        'graph.nodes[0].parameters[0].topics:',
        'empty list',
    ),
    'remap without :=': (
        graph_text(nodes=[node_entry(remappings=['odom:=/a', 'odom=/b'])]),
        'graph.nodes[0].remappings[1]:',
        "not of the form 'from:=to'",
    ),
    'remap to an invalid name': (
        graph_text(nodes=[node_entry(remappings={'odom': 'wheel odom'})]),
        'graph.nodes[0].remappings.odom:',
        'not a valid topic',
    ),
    'remap twice': (
        graph_text(nodes=[node_entry(remappings=['odom:=/a', 'odom:=/b'])]),
        'graph.nodes[0].remappings[1]:',
        'remapped twice',
    ),
    'remap of the node name': (
        graph_text(nodes=[node_entry(remappings=['__node:=b'])]),
        'graph.nodes[0].remappings[0]:',
        'name and namespace keys',
    ),
    'player remap syntax': (
        graph_text(player={'remap': ['/a->/b']}),
        'graph.player.remap[0]:',
        'from:=to',
    ),
    'invalid namespace': (
        graph_text(nodes=[node_entry(namespace='robot 1')]),
        'graph.nodes[0].namespace:',
        'not a valid namespace',
    ),
    'invalid plugin': (
        graph_text(nodes=[node_entry(plugin='package.module.Class')]),
        'graph.nodes[0].plugin:',
        'not a valid name',
    ),
}


@pytest.mark.parametrize('case', BAD_GRAPHS, ids=list(BAD_GRAPHS))
def test_invalid_graph_names_file_and_key(tmp_path: Path, case: str) -> None:
    text, key, reason = BAD_GRAPHS[case]
    path = write_graph(tmp_path, text)
    with pytest.raises(GraphError) as raised:
        load_graph(path)
    message = str(raised.value)
    assert message.startswith(f'graph {str(path)!r}')
    assert key in message
    assert reason in message
    assert '\n' not in message


def test_missing_graph_file(tmp_path: Path) -> None:
    path = tmp_path / 'absent.yaml'
    with pytest.raises(GraphError, match=r"graph '.*absent\.yaml' does not exist"):
        load_graph(path)


@pytest.mark.parametrize(
    ('graph', 'key', 'reason'),
    [
        ({'player': {}}, 'graph.player.bag:', 'give --bag'),
        ({'player': {'bag': 'absent'}}, 'graph.player.bag:', 'does not exist'),
        ({'exit_when_player_done': True}, 'graph.exit_when_player_done:', 'no player'),
        ({'recorder': {'output': '.'}}, 'graph.recorder.output:', 'exists already'),
    ],
)
def test_graphs_that_cannot_run(
    tmp_path: Path, graph: dict[str, object], key: str, reason: str
) -> None:
    loaded = load_graph(write_graph(tmp_path, yaml.safe_dump({'graph': graph})))
    with pytest.raises(GraphError) as raised:
        node_descriptions(loaded)
    assert key in str(raised.value)
    assert reason in str(raised.value)


# -- loading and describing ----------------------------------------------------------------
def test_valid_graph_resolves_paths_and_normalizes(tmp_path: Path) -> None:
    loaded = load_graph(write_graph(tmp_path, VALID))
    ingest, mapper = loaded.nodes
    assert ingest.parameters[0] == tmp_path / 'config' / 'ingest.yaml'
    assert ingest.parameters[1] == {'max_gap_s': 0.5, 'frames': {'odom': 'odom'}}
    assert ingest.namespace == '/robot1'
    assert ingest.remappings == (('odom', '/wheel/odom'),)
    assert mapper.remappings == (('landmark_observations', '/markers'),)
    assert mapper.plugin is None
    assert loaded.player is not None and loaded.player.bag == tmp_path / 'bags' / 'sample'
    assert loaded.recorder is not None and loaded.recorder.output == Path('out/run')
    assert loaded.use_sim_time is True
    assert loaded.exit_when_player_done is False


def test_node_descriptions_in_start_order(tmp_path: Path) -> None:
    descriptions = node_descriptions(load_graph(write_graph(tmp_path, VALID)))
    assert [(d.role, d.name) for d in descriptions] == [
        ('node', 'ingest'),
        ('node', 'mapper'),
        ('player', 'bag_player'),
        ('recorder', 'bag_recorder'),
    ]
    ingest, _, player, recorder = descriptions
    assert ingest.fully_qualified_name == '/robot1/ingest'
    assert ingest.parameters[-1] == {'use_sim_time': True}
    assert (player.package, player.executable, player.plugin) == (
        'slam_bringup',
        'bag_player',
        PLAYER_PLUGIN,
    )
    assert player.parameters[0] == {
        'bag_path': str(tmp_path / 'bags' / 'sample'),
        'rate': 2.0,
        'topics': ['/odom'],
        'remap': ['/odom:=/wheel/odom'],
    }
    assert recorder.plugin == RECORDER_PLUGIN
    assert recorder.parameters[0] == {
        'output': 'out/run',
        'topics': ['/wheel/odom', '/em_sam/path'],
    }
    assert recorder.arguments == ('/wheel/odom', '/em_sam/path')


def test_overrides_replace_and_add_player_and_recorder(tmp_path: Path) -> None:
    bag = tmp_path / 'other_bag'
    bag.mkdir()
    loaded = load_graph(write_graph(tmp_path, graph_text(nodes=[node_entry()])))
    with pytest.raises(GraphError, match='has no player'):
        with_overrides(loaded, rate=2.0)
    changed = with_overrides(
        loaded, bag=bag, rate=3.0, record=Path('rec'), exit_when_player_done=True
    )
    roles = {d.role: d for d in node_descriptions(changed)}
    assert roles['player'].parameters[0] == {'bag_path': str(bag), 'rate': 3.0}
    assert roles['recorder'].parameters[0] == {'output': 'rec'}
    assert roles['recorder'].arguments == ('--all',)
    assert changed.exit_when_player_done


def test_ros_arguments_keep_parameter_order(tmp_path: Path) -> None:
    description = node_descriptions(load_graph(write_graph(tmp_path, VALID)))[0]
    scratch = tmp_path / 'scratch'
    scratch.mkdir()
    arguments = ros_arguments(description, scratch)
    files = [arguments[i + 1] for i, a in enumerate(arguments) if a == '--params-file']
    assert files[0] == str(tmp_path / 'config' / 'ingest.yaml')
    assert yaml.safe_load(Path(files[1]).read_text()) == {
        '/**': {'ros__parameters': {'max_gap_s': 0.5, 'frames': {'odom': 'odom'}}}
    }
    assert yaml.safe_load(Path(files[2]).read_text()) == {
        '/**': {'ros__parameters': {'use_sim_time': True}}
    }
    assert arguments[:5] == ['--ros-args', '-r', '__node:=ingest', '-r', '__ns:=/robot1']
    assert arguments[-2:] == ['-r', 'odom:=/wheel/odom']


def test_ros_arguments_are_accepted_by_rcl(tmp_path: Path) -> None:
    """Name, namespace, parameters (later wins) and remaps reach a real rclpy node."""
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.utilities import try_shutdown

    description = node_descriptions(load_graph(write_graph(tmp_path, VALID)))[0]
    context = Context()
    context.init(['test'])
    try:
        node = Node(
            'renamed_by_the_arguments',
            context=context,
            cli_args=ros_arguments(description, tmp_path),
            use_global_arguments=False,
            automatically_declare_parameters_from_overrides=True,
        )
        assert node.get_fully_qualified_name() == '/robot1/ingest'
        assert node.get_parameter('max_gap_s').value == 0.5
        assert node.get_parameter('frames.odom').value == 'odom'
        assert node.get_parameter('use_sim_time').value is True
        assert node.resolve_topic_name('odom') == '/wheel/odom'
        node.destroy_node()
    finally:
        try_shutdown(context=context)


# -- shipped files ------------------------------------------------------------------------
def test_shipped_graphs_are_valid(tmp_path: Path) -> None:
    graphs = sorted((PACKAGE_DIR / 'graphs').glob('*.yaml'))
    assert graphs, 'slam_bringup/graphs/ holds no GRAPH file'
    for path in graphs:
        loaded = with_overrides(load_graph(path), bag=tmp_path, record=tmp_path / 'out')
        assert node_descriptions(loaded)


def test_bag_replay_plays_and_records(tmp_path: Path) -> None:
    loaded = load_graph(PACKAGE_DIR / 'graphs' / 'bag_replay.yaml')
    roles = [d.role for d in node_descriptions(with_overrides(loaded, bag=tmp_path))]
    assert roles == ['player', 'recorder']
    assert loaded.recorder is not None and loaded.recorder.topics
    assert loaded.exit_when_player_done


def test_launch_file_uses_only_existing_graph_functions() -> None:
    """The launch file cannot be imported here (no launch); check what it takes from us."""
    tree = ast.parse((PACKAGE_DIR / 'launch' / 'graph.launch.py').read_text())
    modules = {'slam_bringup.graph': graph_module, 'slam_bringup.graph_nodes': graph_nodes}
    imported = [
        (node.module, alias.name)
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module in modules
        for alias in node.names
    ]
    assert {'load_graph', 'node_descriptions'} <= {name for _, name in imported}
    assert all(hasattr(modules[module], name) for module, name in imported)
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert 'generate_launch_description' in functions


# -- parameters checked against the nodes' declarations -----------------------------------
INGEST_ENTRY = """graph:
  nodes:
    - name: odometry_ingest
      package: em_sam_node
      executable: odometry_ingest
{plugin}      parameters: [{parameters}]
"""
PLUGIN = '      plugin: em_sam_node.odometry_ingest.node:OdometryIngestNode\n'


@pytest.mark.parametrize('plugin', [PLUGIN, ''], ids=['plugin', 'executable'])
def test_misspelled_parameter_in_a_parameter_file_is_named(tmp_path: Path, plugin: str) -> None:
    (tmp_path / 'ingest.yaml').write_text(
        '/**:\n  ros__parameters:\n    keyframe_distanse_m: 0.3\n', encoding='utf-8'
    )
    path = write_graph(tmp_path, INGEST_ENTRY.format(plugin=plugin, parameters='ingest.yaml'))
    with pytest.raises(GraphError) as caught:
        load_graph(path)
    message = str(caught.value)
    assert message.startswith(f"graph '{path}': graph.nodes[0].parameters[0]: parameter file ")
    assert str(tmp_path / 'ingest.yaml') in message
    assert "'keyframe_distanse_m' is not a parameter of node odometry_ingest" in message
    assert "did you mean 'keyframe_distance_m'?" in message


def test_misspelled_inline_parameter_and_bad_value_are_named(tmp_path: Path) -> None:
    path = write_graph(
        tmp_path, INGEST_ENTRY.format(plugin='', parameters='{keyframe_distanse_m: 0.3}')
    )
    with pytest.raises(GraphError, match=r"parameters\[0\]: 'keyframe_distanse_m' is not a "):
        load_graph(path)
    path = write_graph(
        tmp_path, INGEST_ENTRY.format(plugin='', parameters='{keyframe_distance_m: -1.0}')
    )
    with pytest.raises(GraphError, match=r'odometry_ingest\.keyframe_distance_m=-1\.0: must be'):
        load_graph(path)
    path = write_graph(tmp_path, INGEST_ENTRY.format(plugin='', parameters='{idle_flush_s: 2}'))
    with pytest.raises(GraphError, match=r'idle_flush_s=2: must be a double for a ROS node'):
        load_graph(path)


def test_sections_for_other_nodes_and_ros_parameters_are_accepted(tmp_path: Path) -> None:
    (tmp_path / 'all.yaml').write_text(
        'em_sam_mapper:\n  ros__parameters:\n    em_mode: paper\n'
        'odometry_ingest:\n  ros__parameters:\n    keyframe_distance_m: 0.3\n'
        '    use_sim_time: true\n',
        encoding='utf-8',
    )
    path = write_graph(tmp_path, INGEST_ENTRY.format(plugin=PLUGIN, parameters='all.yaml'))
    assert load_graph(path).nodes[0].name == 'odometry_ingest'


def test_player_and_recorder_keys_are_the_bag_tools_parameters() -> None:
    """graph.player and graph.recorder take exactly the parameters the bag tools declare
    (the player's bag_path is spelled bag)."""
    from slam_bringup import bag_player, bag_recorder

    player = {'bag_path' if key == 'bag' else key for key in graph_module._PLAYER_KEYS}
    assert player == set(bag_player.PARAMETERS.names)
    assert set(graph_module._RECORDER_KEYS) == set(bag_recorder.PARAMETERS.names)


def test_a_misspelled_bundled_graph_gets_the_closest_names() -> None:
    from slam_bringup.graph_nodes import bundled_graphs, bundled_graphs_help, find_graph

    assert find_graph('em_sam_office').name == 'em_sam_office.yaml'
    with pytest.raises(GraphError, match=r"did you mean 'em_sam_office\.yaml'"):
        find_graph('em_sam_ofice')
    graphs = bundled_graphs()
    assert 'em_sam_office.yaml' in graphs and all(graphs.values())  # each described
    assert all(name in bundled_graphs_help() for name in graphs)
