"""marker_detector_lifecycle: marker_detector as a lifecycle (managed) node.

The same node (name marker_detector), topics and parameters as ``marker_detector``
(``marker_detector --help``), started unconfigured: configure builds the detector and the
publishers, activate takes images, camera_info and /tf_static, deactivate pauses them
(camera_info and the mount already taken stay), cleanup drops everything. Transitions:
``slam_call marker_detector/change_state '{transition: {id: 1}}'`` (1 configure,
3 activate, 4 deactivate, 2 cleanup).
"""

from __future__ import annotations

import sys

from marker_detector.detector.node import DetectorBehaviour
from marker_detector.detector.settings import PARAMETERS
from slam_core.cli import console_main
from slam_ros.lifecycle import managed
from slam_ros.spin import spin_node

MarkerDetectorLifecycleNode = managed(DetectorBehaviour, 'marker_detector', PARAMETERS)


@console_main('marker_detector_lifecycle')
def main(argv: list[str] | None = None) -> int:
    """Run the lifecycle node until Ctrl-C."""
    return spin_node(
        'marker_detector_lifecycle',
        MarkerDetectorLifecycleNode,
        argv,
        parameters=PARAMETERS,
        doc=__doc__,
    )


if __name__ == '__main__':
    sys.exit(main())
