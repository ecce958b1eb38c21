"""Run a one-node launch file against recording stand-ins (docs/design/ros_and_core.md)."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

STAND_INS = {
    'launch': ['LaunchDescription'],
    'launch.actions': ['DeclareLaunchArgument'],
    'launch.substitutions': ['LaunchConfiguration', 'PathJoinSubstitution'],
    'launch_ros': [],
    'launch_ros.actions': ['Node'],
    'launch_ros.parameter_descriptions': ['ParameterValue'],
    'launch_ros.substitutions': ['FindPackageShare'],
}


class Recorded:
    """A stand-in for a launch class: keeps what it was constructed with."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs


@dataclass(frozen=True)
class LaunchedNode:
    """A launch file's declared arguments (name -> keyword arguments) and its Node."""

    arguments: dict[str, dict[str, Any]]
    node: Recorded

    @property
    def remapped(self) -> set[str]:
        """The topics the Node remaps."""
        return {source for source, _ in self.node.kwargs['remappings']}


def launched_node(path: Path, monkeypatch: pytest.MonkeyPatch) -> LaunchedNode:
    """Run the launch file at ``path`` against recording stand-ins (one Node)."""
    for name, classes in STAND_INS.items():
        module = ModuleType(name)
        for class_name in classes:
            setattr(module, class_name, type(class_name, (Recorded,), {}))
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location(path.name.split('.')[0] + '_launch', path)
    assert spec is not None and spec.loader is not None
    launch_file = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch_file)
    (entities,) = launch_file.generate_launch_description().args
    arguments = {
        e.args[0]: e.kwargs for e in entities if type(e).__name__ == 'DeclareLaunchArgument'
    }
    (node,) = [e for e in entities if type(e).__name__ == 'Node']
    return LaunchedNode(arguments, node)


def check_launched_node(
    launched: LaunchedNode, *, package_dir: Path, entry_point: str, config: Path
) -> None:
    """Assert what every node's launch file promises (arguments, executable, config)."""
    package = package_dir.name
    assert all(kwargs.get('description') for kwargs in launched.arguments.values())
    executable = launched.node.kwargs['executable']
    assert f"'{executable} = {entry_point}'" in (package_dir / 'setup.py').read_text()
    assert launched.node.kwargs['package'] == package
    share, *parts = launched.arguments['params_file']['default_value'].args[0]
    assert share.args == (package,)
    assert package_dir.joinpath(*parts) == config
