"""The packages form a tree, every package.xml declares what its code imports, and no file is
longer than 600 lines.

Every Python file of every package under ``src/`` (its modules, tests and launch files) is
parsed, and each ``import`` (also inside functions) is checked:

- an import of another of our packages goes to a package on a lower floor (``FLOORS``), so
  no package imports one above it or beside it and the graph has no cycle;
- it is declared in ``package.xml``: a module or launch file needs a ``depend`` or
  ``exec_depend``; a test may also use a ``test_depend``;
- a third-party import is declared the same way, under its rosdep key (``ROSDEP_KEYS``);
- ``slam_core`` imports nothing of ROS (no rclpy, messages or rosbags).

It also fails on a declared dependency between our packages that runs upward or sideways
(colcon orders builds by every kind of dependency, so such a declaration is a cycle in
waiting) and on a declared package that nothing imports or runs.
"""

from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src'

FLOORS = {
    'slam_interfaces': 0,
    'slam_core': 0,
    'slam_ros': 1,
    'marker_detector': 2,
    'em_sam_node': 2,
    'monoslam_shadow_node': 3,
    'slam_sim': 4,
    'slam_evaluation': 5,
    'slam_bringup': 6,
}
"""Our packages by floor: a package may import only packages on a lower floor."""

ROSDEP_KEYS = {
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'cv2': 'python3-opencv',
    'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib',
    'rosbags': 'python3-rosbags',
    'hypothesis': 'python3-hypothesis',
    'pytest': 'python3-pytest',
    'setuptools': 'python3-setuptools',
    'gtsam': 'python3-gtsam-pip',  # pip's convention; requirements/python.txt installs it
}
"""Third-party Python modules -> the rosdep key a package.xml declares them under."""

ROS_PACKAGES = {
    'rclpy',
    'rcl_interfaces',
    'builtin_interfaces',
    'std_msgs',
    'std_srvs',
    'geometry_msgs',
    'sensor_msgs',
    'nav_msgs',
    'visualization_msgs',
    'tf2_msgs',
    'apriltag_msgs',
    'rosgraph_msgs',
    'diagnostic_msgs',
    'lifecycle_msgs',
    'ament_index_python',
    'launch',
    'launch_ros',
}
"""ROS packages, declared under their own name."""

NOT_DECLARED = {'setuptools'}
"""Imported only by setup.py, which the build tool provides."""


@dataclass(frozen=True)
class Import:
    """One import of a top-level module by a file of a package; ``test`` for test files."""

    package: str
    module: str
    path: Path
    line: int
    test: bool


def python_packages() -> list[Path]:
    """Return the directories of our ament_python packages."""
    return sorted(path.parent for path in SRC.glob('*/setup.py'))


def declared(package_dir: Path) -> dict[str, set[str]]:
    """Return package.xml's dependencies by kind: 'run' (depend, exec_depend) and 'test'."""
    root = ElementTree.parse(package_dir / 'package.xml').getroot()
    kinds: dict[str, set[str]] = {'run': set(), 'test': set()}
    for element in root:
        name = (element.text or '').strip()
        if element.tag in ('depend', 'exec_depend', 'build_depend'):
            kinds['run'].add(name)
        elif element.tag == 'test_depend':
            kinds['test'].add(name)
    return kinds


def imports(package_dir: Path) -> list[Import]:
    """Return every absolute import of every Python file of a package (setup.py aside)."""
    found = []
    for path in sorted(package_dir.rglob('*.py')):
        if path.name == 'setup.py':
            continue
        relative = path.relative_to(package_dir)
        test = relative.parts[0] == 'test'
        siblings = {sibling.stem for sibling in path.parent.glob('*.py')}
        tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top in siblings:
                    continue  # a helper module next to the file, e.g. a test's fixtures
                found.append(Import(package_dir.name, top, relative, node.lineno, test))
    return found


def dependency_key(module: str) -> str | None:
    """Return the package.xml key an imported top-level module needs, or None (stdlib)."""
    if module in FLOORS or module in ROS_PACKAGES:
        return module
    if module in ROSDEP_KEYS:
        return ROSDEP_KEYS[module]
    if module in sys.stdlib_module_names or module == '__future__':
        return None
    return f'<unknown third-party module {module!r}: add it to ROSDEP_KEYS>'


PACKAGES = python_packages()


def test_every_python_package_has_a_floor() -> None:
    assert sorted(p.name for p in PACKAGES) == sorted(set(FLOORS) - {'slam_interfaces'})


@pytest.mark.parametrize('package_dir', PACKAGES, ids=lambda path: path.name)
def test_imports_go_down_and_are_declared(package_dir: Path) -> None:
    name = package_dir.name
    kinds = declared(package_dir)
    problems = []
    for item in imports(package_dir):
        if item.module == name:
            continue
        where = f'{name}/{item.path}:{item.line} imports {item.module}'
        if item.module in FLOORS and FLOORS[item.module] >= FLOORS[name]:
            problems.append(f'{where}, which is not on a lower floor than {name}')
        key = dependency_key(item.module)
        if key is None or item.module in NOT_DECLARED:
            continue
        allowed = kinds['run'] | (kinds['test'] if item.test else set())
        if key not in allowed:
            kind = 'test_depend' if item.test else 'exec_depend'
            problems.append(f'{where}: package.xml lacks <{kind}>{key}</{kind}>')
    assert not problems, '\n'.join(problems)


@pytest.mark.parametrize('package_dir', PACKAGES, ids=lambda path: path.name)
def test_declared_dependencies_go_down_and_are_used(package_dir: Path) -> None:
    name = package_dir.name
    kinds = declared(package_dir)
    used = {dependency_key(item.module) for item in imports(package_dir)}
    used |= _run_only(package_dir)
    problems = []
    for kind, keys in kinds.items():
        for key in sorted(keys):
            if key in FLOORS and FLOORS[key] >= FLOORS[name]:
                problems.append(f'{name}/package.xml: {kind} dependency {key} is not lower')
            if key not in used:
                problems.append(f'{name}/package.xml: {kind} dependency {key} is never imported')
    assert not problems, '\n'.join(problems)


def _run_only(package_dir: Path) -> set[str]:
    """Dependencies a package names without importing them: message packages whose types it
    publishes or replays by name (``sensor_msgs/msg/Image``), and packages whose executables
    its GRAPH and launch files start (``package: em_sam_node``)."""
    text = ' '.join(
        path.read_text(encoding='utf-8')
        for path in package_dir.rglob('*')
        if path.suffix in ('.py', '.yaml') and path.is_file()
    )
    return {key for key in ROS_PACKAGES | set(FLOORS) if re.search(rf'\b{key}\b', text)}


def test_slam_core_imports_nothing_of_ros() -> None:
    ros = ROS_PACKAGES | {'rosbags', 'slam_interfaces', 'slam_ros'}
    found = [
        f'slam_core/{item.path}:{item.line} imports {item.module}'
        for item in imports(SRC / 'slam_core')
        if item.module in ros or item.module.endswith('_msgs')
    ]
    assert not found, '\n'.join(found)


MAX_FILE_LINES = 600
"""No file of a package is longer than this (STYLE.md: look for the second idea past ~400)."""


def test_no_package_file_is_longer_than_the_limit() -> None:
    long_files = []
    for path in sorted(SRC.rglob('*')):
        if not path.is_file() or path.suffix not in ('.py', '.yaml', '.xml', '.msg', '.txt'):
            continue
        lines = len(path.read_text(encoding='utf-8').splitlines())
        if lines > MAX_FILE_LINES:
            long_files.append(f'{path.relative_to(SRC)}: {lines} lines')
    assert not long_files, '\n'.join(long_files)


NODE_PACKAGES = ('em_sam_node', 'marker_detector', 'monoslam_shadow_node')
ROOM_FILES = ('processor.py', 'settings.py', 'conversions.py', 'node.py')
"""Every node of a node package lives in a room of these files (and may have more)."""


def node_rooms() -> list[Path]:
    """The rooms of the node packages: the subpackages with a node.py."""
    return sorted(
        path.parent
        for package in NODE_PACKAGES
        for path in (SRC / package / package).glob('*/node.py')
    )


def test_every_node_has_the_same_room() -> None:
    """core/ beside the rooms (ROS-free), and in each room a processor, its settings, its
    conversions and the rclpy node; the rooms' core types are imported from a core/."""
    rooms = node_rooms()
    assert {room.name for room in rooms} == {
        'mapper', 'odometry_ingest', 'detector', 'apriltag_bridge',
        'feature_tracker', 'monoslam', 'shadow_filter',
    }  # fmt: skip
    missing = [f'{room.relative_to(SRC)}/{name}' for room in rooms for name in ROOM_FILES
               if not (room / name).is_file()]  # fmt: skip
    assert missing == []
    for package in NODE_PACKAGES:
        assert (SRC / package / package / 'core' / '__init__.py').is_file() or all(
            (room / 'core' / '__init__.py').is_file()
            for room in rooms
            if room.parent.name == package
        ), package
    stray = [
        str(path.relative_to(SRC))
        for package in NODE_PACKAGES
        for path in (SRC / package / package).glob('*.py')
        if path.name.endswith('_node.py') or path.name in ('processor.py', 'settings.py')
    ]
    assert stray == [], 'node-level modules outside a room'
