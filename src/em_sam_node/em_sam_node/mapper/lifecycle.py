"""em_sam_mapper_lifecycle: em_sam_mapper as a lifecycle (managed) node.

The same node (name em_sam_mapper), topics, services and parameters as ``em_sam_mapper``
(``em_sam_mapper --help``), started unconfigured, as Nav2-style bringups expect:

- configure: the parameters are validated, the map of localization is read, the
  publishers and services are made (a failure is logged and the node stays unconfigured);
- activate: odometry_increments and landmark_observations are taken, the solve, checkpoint
  and TF timers run;
- deactivate: inputs pause; what is held stays and the services still answer;
- cleanup: the report and checkpoint are written and everything is dropped;
- shutdown or Ctrl-C: the report and checkpoint are written.

Transitions come from ``<node>/change_state`` (lifecycle_msgs/srv/ChangeState): a launch
file (``em_sam_lifecycle.launch.py`` in slam_bringup), a lifecycle manager, or
``slam_call em_sam_mapper/change_state '{transition: {id: 1}}'`` (1 configure, 3 activate,
4 deactivate, 2 cleanup).
"""

from __future__ import annotations

import sys

from em_sam_node.mapper.node import MapperBehaviour
from em_sam_node.mapper.settings import PARAMETERS
from slam_core.cli import console_main
from slam_ros.lifecycle import managed
from slam_ros.spin import spin_node

EmSamMapperLifecycleNode = managed(MapperBehaviour, 'em_sam_mapper', PARAMETERS)


@console_main('em_sam_mapper_lifecycle')
def main(argv: list[str] | None = None) -> int:
    """Run the lifecycle node until Ctrl-C."""
    return spin_node(
        'em_sam_mapper_lifecycle',
        EmSamMapperLifecycleNode,
        argv,
        parameters=PARAMETERS,
        doc=__doc__,
    )


if __name__ == '__main__':
    sys.exit(main())
