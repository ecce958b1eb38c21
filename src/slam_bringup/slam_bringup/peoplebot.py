"""peoplebot_graph: the live GRAPH of a Peoplebot, from a robot, a camera and a pipeline.

Example: peoplebot_graph --robot rosaria --camera usb_cam -o g.yaml; slam_run g.yaml --processes"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

from slam_bringup.graph import load_graph, read_yaml
from slam_bringup.graph_types import Graph
from slam_core.cli import PlainDescriptionHelpFormatter, console_main
from slam_core.errors import GraphError
from slam_core.files import write_atomically

ROBOTS = ('sim', 'p2os', 'rosaria')
CAMERAS = ('sim', 'usb_cam', 'v4l2_camera')
PIPELINES = ('em_sam', 'monoslam', 'both')
PARTS = ('all', 'drivers', 'pipeline')  # drivers: base, camera and mount (the robot's side)
PRESETS_NAME = 'peoplebot.yaml'


def presets_path() -> Path:
    """Return config/peoplebot.yaml: the installed one, else the source tree's."""
    try:
        share = Path(get_package_share_directory('slam_bringup'))
    except PackageNotFoundError:
        share = Path(__file__).resolve().parents[1]
    return share / 'config' / PRESETS_NAME


def compose(
    robot: str,
    camera: str,
    pipeline: str,
    presets: dict[str, Any] | None = None,
    *,
    part: str = 'all',
) -> dict[str, Any]:
    """Return the GRAPH mapping of the choices, or of one ``part``; ValueError: a wrong choice."""
    for label, value, choices in (
        ('robot', robot, ROBOTS),
        ('camera', camera, CAMERAS),
        ('pipeline', pipeline, PIPELINES),
        ('part', part, PARTS),
    ):
        if value not in choices:
            raise ValueError(f'{label} {value!r}: choose one of {", ".join(choices)}')
    if camera == 'sim' and robot != 'sim':
        raise ValueError(
            "camera 'sim' is the simulated robot's own camera: use it with robot 'sim', or "
            'choose a camera driver (usb_cam, v4l2_camera)'
        )
    parts = presets if presets is not None else read_yaml(presets_path(), str(presets_path()))
    pipelines = ('em_sam', 'monoslam') if pipeline == 'both' else (pipeline,)
    drivers = [*parts['robot'][robot], *parts['camera'][camera], *parts['mount']]
    mapping = [entry for name in pipelines for entry in parts['pipeline'][name]]
    nodes = {'all': drivers + mapping, 'drivers': drivers, 'pipeline': mapping}[part]
    what = '' if part == 'all' else f', {part} only'
    return {
        'graph': {
            'description': (
                f'{pipeline} live on a Peoplebot (robot {robot}, camera {camera}{what})'
            ),
            'nodes': nodes,
        }
    }


def write_graph(path: Path, robot: str, camera: str, pipeline: str, *, part: str = 'all') -> Graph:
    """Write the composed GRAPH to ``path`` (atomically) and return it validated."""
    text = (
        f'# peoplebot_graph --robot {robot} --camera {camera} --pipeline {pipeline} '
        f'--part {part}\n'
        + yaml.safe_dump(compose(robot, camera, pipeline, part=part), sort_keys=False)
    )
    write_atomically(path, text)
    return load_graph(path)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='peoplebot_graph',
        description=__doc__,
        formatter_class=PlainDescriptionHelpFormatter,
    )
    parser.add_argument('--robot', choices=ROBOTS, default='sim', help='base driver')
    parser.add_argument('--camera', choices=CAMERAS, default='sim', help='camera driver')
    parser.add_argument('--pipeline', choices=PIPELINES, default='em_sam', help='SLAM pipeline')
    parser.add_argument(
        '--part',
        choices=PARTS,
        default='all',
        help='all nodes, or the drivers (the robot) or the pipeline (a laptop) only',
    )
    parser.add_argument(
        '-o', '--output', type=Path, required=True, help='GRAPH file to write (for slam_run)'
    )
    return parser


@console_main('peoplebot_graph')
def main(argv: list[str] | None = None) -> int:
    """Write and validate the GRAPH; say what it runs."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        graph = write_graph(args.output, args.robot, args.camera, args.pipeline, part=args.part)
    except ValueError as err:
        parser.error(str(err))
    except GraphError as err:
        raise SystemExit(f'peoplebot_graph: {err}') from None
    names = ', '.join(node.name for node in graph.nodes)
    print(  # noqa: T201
        f'peoplebot_graph: wrote {args.output} ({names}); run: slam_run {args.output} --processes'
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
