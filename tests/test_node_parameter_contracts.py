"""Every node's parameter contract, one table for all: its --help lists every declared
parameter with type and default, its docstring stays a screen long and agrees with the
declaration, its config YAML is the one ``--print-config`` writes from the declaration, a
parameter file's errors name the file and the key, and a parameter that sets a core config
field takes its default from that config (``slam_core.params.config_param``), not from a
second literal."""

from __future__ import annotations

import ast
import importlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import pytest
import yaml

from slam_core.errors import ParameterError
from slam_ros.testing.node_contract import (
    NODE_DOCSTRING_MAX_LINES,
    config_mismatches,
    declared,
    docstring_lines,
    docstring_mismatches,
    help_without_parameters,
)

SRC = Path(__file__).resolve().parents[1] / 'src'


@dataclass(frozen=True)
class NodeCase:
    """One node: its executable, its module and its config YAML (package-relative), if any."""

    executable: str
    module: str
    config: str = ''

    @property
    def node_module(self) -> ModuleType:
        return importlib.import_module(self.module)

    @property
    def config_path(self) -> Path:
        return SRC / self.module.partition('.')[0] / 'config' / self.config


NODES = [
    NodeCase('odometry_ingest', 'em_sam_node.odometry_ingest.node', 'odometry_ingest.yaml'),
    NodeCase('em_sam_mapper', 'em_sam_node.mapper.node', 'em_sam_mapper.yaml'),
    NodeCase('marker_detector', 'marker_detector.detector.node', 'marker_detector.yaml'),
    NodeCase('apriltag_bridge', 'marker_detector.apriltag_bridge.node', 'apriltag_bridge.yaml'),
    NodeCase(
        'feature_tracker', 'monoslam_shadow_node.feature_tracker.node', 'feature_tracker.yaml'
    ),
    NodeCase('monoslam', 'monoslam_shadow_node.monoslam.node', 'monoslam.yaml'),
    NodeCase('shadow_filter', 'monoslam_shadow_node.shadow_filter.node', 'shadow_filter.yaml'),
    NodeCase('bag_player', 'slam_bringup.bag_player', 'bag_player.yaml'),
    NodeCase('bag_recorder', 'slam_bringup.bag_recorder', 'bag_recorder.yaml'),
    NodeCase('slam_dashboard', 'slam_bringup.dashboard.node'),
    NodeCase('camera_mount', 'slam_bringup.camera_mount'),
    NodeCase('peoplebot_sim', 'slam_sim.peoplebot_sim_node'),
    NodeCase('route_driver', 'slam_sim.route_driver_node'),
    NodeCase('dynamic_scene_sim', 'slam_sim.dynamic_scene_sim_node'),
    NodeCase('label_gate', 'slam_sim.label_gate_node'),
]
WITH_CONFIG = [case for case in NODES if case.config]


def _ids(cases: list[NodeCase]) -> list[str]:
    return [case.executable for case in cases]


@pytest.mark.parametrize('case', NODES, ids=_ids(NODES))
def test_help_lists_every_parameter_and_the_docstring_stays_short(case: NodeCase) -> None:
    assert help_without_parameters(case.node_module, case.executable) == []
    assert docstring_lines(case.node_module) <= NODE_DOCSTRING_MAX_LINES


@pytest.mark.parametrize('case', NODES, ids=_ids(NODES))
def test_docstring_types_and_defaults_match_the_declaration(case: NodeCase) -> None:
    assert docstring_mismatches(case.node_module) == []


@pytest.mark.parametrize('case', WITH_CONFIG, ids=_ids(WITH_CONFIG))
def test_config_yaml_matches_declared_parameters(case: NodeCase) -> None:
    assert case.config_path.is_file(), case.config_path
    assert config_mismatches(case.node_module, case.config_path) == []


@pytest.mark.parametrize('case', WITH_CONFIG, ids=_ids(WITH_CONFIG))
def test_config_yaml_is_written_from_the_declaration(case: NodeCase) -> None:
    """Its comments are the parameters' descriptions: `<node> --print-config` rewrites it."""
    written = declared(case.node_module).to_yaml()
    assert case.config_path.read_text(encoding='utf-8') == written, (
        f'{case.config_path} is not what `{case.executable} --print-config` writes; '
        f'regenerate it with `{case.executable} --print-config > {case.config_path}`'
    )


@pytest.mark.parametrize('case', NODES, ids=_ids(NODES))
def test_parameter_file_errors_name_the_file_and_key(case: NodeCase, tmp_path: Path) -> None:
    table = declared(case.node_module)
    first = next(iter(table))
    value = first.default_value()
    stray = tmp_path / 'stray.yaml'
    stray.write_text(
        yaml.safe_dump({'/**': {'ros__parameters': {first.name: value, 'no_such_key': 2.0}}})
    )
    with pytest.raises(
        ParameterError,
        match=rf"stray\.yaml.*'no_such_key' is not a parameter of node {table.node}",
    ):
        table.read_yaml(stray)
    empty = tmp_path / 'empty.yaml'
    empty.write_text(f'{table.node}: {{}}\n')
    with pytest.raises(ParameterError, match='no "/\\*\\*: ros__parameters:"'):
        table.read_yaml(empty)
    named = tmp_path / 'named.yaml'
    named.write_text(yaml.safe_dump({table.node: {'ros__parameters': {first.name: value}}}))
    assert table.read_yaml(named)[first.name] == value


NODE_OVERRIDES = {
    'monoslam_shadow_node/monoslam_shadow_node/monoslam/settings.py': {'initialize'},
}
"""Deliberate node defaults that differ from the core's: the monoslam node runs the paper's
system (features enter on the Shadow filter's handover), the core defaults to classic
MonoSLAM ('all')."""


def _literal(node: ast.expr) -> bool:
    try:
        ast.literal_eval(node)
    except ValueError:
        return False
    return True


def _second_sources(path: Path, root: Path = SRC) -> list[str]:
    """``Param(...)`` calls in ``path`` that set a core field (``field=``) with a literal
    default of their own instead of the core's (no ``to_field`` conversion in between)."""
    tree = ast.parse(path.read_text(encoding='utf-8'))
    allowed = NODE_OVERRIDES.get(str(path.relative_to(root)), set())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            keywords = {k.arg for k in node.keywords}
            if (
                node.func.id == 'Param'
                and 'field' in keywords
                and 'to_field' not in keywords
                and len(node.args) >= 2
                and _literal(node.args[1])
                and ast.literal_eval(node.args[0]) not in allowed
            ):
                found.append(f'{path.relative_to(root)}:{node.lineno}')
    return found


def test_core_fields_take_their_default_from_the_core() -> None:
    """A parameter that sets a core config field reads its default from the config
    (config_param): the value is written once, in the core."""
    files = [
        path
        for path in SRC.glob('*/*/**/*.py')
        if '/test/' not in str(path) and path.parts[-2] != 'launch'
    ]
    assert len(files) > 100  # the tree was found
    assert [hit for path in files for hit in _second_sources(path)] == []


def test_the_second_source_check_can_fail(tmp_path: Path) -> None:
    """The check above sees a literal default beside a field, and accepts a converted one."""
    module = tmp_path / 'pkg' / 'pkg' / 'settings.py'
    module.parent.mkdir(parents=True)
    module.write_text(
        "A = Param('alpha', 0.05, 'level', field='classifier.alpha')\n"
        "B = Param('angle_deg', 3.0, 'deg', field='c.angle', to_field=math.radians)\n"
        "C = config_param(DEFAULTS, 'classifier.beta', 'level')\n"
        "D = Param('gamma', CORE.gamma, 'level', field='classifier.gamma')\n"
    )
    assert _second_sources(module, tmp_path) == ['pkg/pkg/settings.py:1']
