"""label_gate: pass on the tracked features labelled static (paper 001's variant (a)).

An evaluation oracle, not part of the SLAM pipeline: labels from an imported sequence's
label_masks.npz (slam_sim.core.label_gate; docs/design/simulation.md).
Topics:
  subscribes  features (slam_interfaces/FeatureTrackArray, reliable, depth 100)
  publishes   features/labelled (same type and QoS): the tracks labelled static so far;
              /diagnostics: frames, frames with masks, features in and passed, moving"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from slam_core import lazy_stats
from slam_core.cli import console_main
from slam_core.params import NON_NEGATIVE, Param, ParamTable
from slam_interfaces.msg import FeatureTrackArray
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import output_qos
from slam_ros.spin import spin_node
from slam_sim.core.label_gate import LabelGate, read_label_masks

DEPTH = 100
STATUS_PERIOD_S = 10.0

PARAMETERS = ParamTable(
    'label_gate',
    (
        Param(
            'label_masks_file',
            '',
            "a sequence's label_masks.npz (tum_rgbd_sequence with the mask rule); required",
        ),
        Param(
            'stamp_tolerance_s',
            0.001,
            'largest features-to-mask stamp difference, s',
            range=NON_NEGATIVE,
        ),
    ),
)


class LabelGateNode(Node):
    """Passes the features labelled static."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('label_gate', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        path = str(values['label_masks_file'])
        if not path:
            raise ValueError('label_gate: parameter label_masks_file is required (a .npz)')
        lazy_stats.load()
        masks = read_label_masks(Path(path))
        self.gate = LabelGate(
            masks,
            tolerance_ns=round(float(values['stamp_tolerance_s']) * 1e9),
        )
        self.publisher = self.create_publisher(
            FeatureTrackArray, 'features/labelled', output_qos(depth=DEPTH)
        )
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        self.create_subscription(
            FeatureTrackArray, 'features', timed(self._on_features, 'features'),
            output_qos(depth=DEPTH),
        )  # fmt: skip
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(STATUS_PERIOD_S, self._log_status, clock=steady)
        self.started = time.monotonic()
        self.get_logger().info(
            f'label_gate: {len(masks.stamps_ns)} images with masks from {path}; passing '
            f'{self.resolve_topic_name("features")} to '
            f'{self.resolve_topic_name("features/labelled")} with only the tracks labelled '
            'static (an oracle for evaluation)'
        )

    def _counts(self) -> dict[str, int]:
        gate = self.gate
        return {
            'frames': gate.frames,
            'frames with masks': gate.frames_with_masks,
            'features': gate.features,
            'features passed': gate.passed,
            'tracks labelled moving': gate.tracks_moving(),
        }

    def _on_features(self, message: Any) -> None:
        tracks = list(message.tracks)
        ids = np.array([t.id for t in tracks], dtype=np.int64)
        pixels = np.array([(t.u, t.v) for t in tracks], dtype=np.float64).reshape(-1, 2)
        stamp_ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        keep = self.gate.admit(stamp_ns, ids, pixels)
        out = FeatureTrackArray()
        out.header = message.header
        out.tracks = [track for track, kept in zip(tracks, keep.tolist(), strict=True) if kept]
        self.publisher.publish(out)

    def _log_status(self) -> None:
        counts = self._counts()
        self.get_logger().info(
            f'{counts["frames"]} frames ({counts["frames with masks"]} with masks): passed '
            f'{counts["features passed"]} of {counts["features"]} features; '
            f'{counts["tracks labelled moving"]} tracks labelled moving'
        )

    def destroy_node(self) -> None:
        """Log the final counts, then destroy the node."""
        self._log_status()
        super().destroy_node()


@console_main('label_gate')
def main(argv: list[str] | None = None) -> int:
    """Run the gate until Ctrl-C."""
    return spin_node('label_gate', LabelGateNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
