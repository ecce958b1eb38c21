"""route_driver: drive the EM-SAM paper's office route by publishing cmd_vel.

Pure pursuit along the route from poses in its frame (with peoplebot_sim: remap pose to
/ground_truth/pose); a stop without a pose for pose_timeout_s and once the route is done.
Topics:
  subscribes  pose (nav_msgs/Odometry: the pose, and the twist to know the robot is at rest)
  publishes   cmd_vel (geometry_msgs/Twist, reliable); /diagnostics: poses, commands,
              pose timeouts, route percent. Details: docs/design/simulation.md."""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import numpy as np
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from slam_core.cli import console_main
from slam_core.geometry.quaternion import yaw_from_quaternion
from slam_core.params import POSITIVE, Param, ParamTable
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import output_qos
from slam_ros.spin import spin_node
from slam_sim.core.office import OfficeConfig, office_route
from slam_sim.core.trajectory import RouteFollower

AT_REST_MPS = 1e-3  # a piece is done when the robot is slower than this (and the turn rate)
AT_REST_RADPS = 1e-3
PROGRESS_PERIOD_S = 10.0

PARAMETERS = ParamTable(
    'route_driver',
    (
        Param(
            'pose_timeout_s',
            0.5,
            'command a stop when no pose came for this long, s',
            range=POSITIVE,
        ),
    ),
)


class RouteDriverNode(Node):
    """Publishes cmd_vel along the office route."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('route_driver', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.pose_timeout_s = float(values['pose_timeout_s'])
        config = OfficeConfig()
        _, path, _ = office_route(config)
        self.follower = RouteFollower(path, config.motion)
        self.commands = self.timeouts = self.rejected = 0
        self.started_s: float | None = None
        self._last_pose_s = time.monotonic()
        self._stopped_for_timeout = False
        self._announced_done = False
        self.publisher = self.create_publisher(Twist, 'cmd_vel', output_qos(depth=10))
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        self.create_subscription(Odometry, 'pose', timed(self._on_pose, 'pose'), 10)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(self.pose_timeout_s / 2.0, timed(self._watch_poses), clock=steady)
        self.create_timer(PROGRESS_PERIOD_S, self._log_progress, clock=steady)
        self.get_logger().info(
            f'route_driver: the office route, {self.follower.length_m:.1f} m in '
            f'{len(self.follower.pieces)} pieces; waiting for poses on '
            f'{self.resolve_topic_name("pose")}'
        )

    def _counts(self) -> dict[str, int]:
        return {
            'commands': self.commands,
            'poses rejected': self.rejected,
            'pose timeouts': self.timeouts,
            'route percent': round(100.0 * self.follower.progress),
            'done': int(self.follower.done),
        }

    def _command(self, speed: float, turn: float) -> None:
        twist = Twist()
        twist.linear.x, twist.angular.z = float(speed), float(turn)
        self.publisher.publish(twist)
        self.commands += 1

    def _on_pose(self, message: Odometry) -> None:
        pose = message.pose.pose
        q, twist = pose.orientation, message.twist.twist
        values = (pose.position.x, pose.position.y, q.x, q.y, q.z, q.w)
        if not all(math.isfinite(v) for v in values):
            self.rejected += 1
            self.get_logger().warning(
                f'pose refused: not finite; {self.rejected} refused so far',
                throttle_duration_sec=2.0,
            )
            return
        self._last_pose_s = time.monotonic()
        self._stopped_for_timeout = False
        if self.started_s is None:
            self.started_s = self._last_pose_s
        at_rest = abs(twist.linear.x) < AT_REST_MPS and abs(twist.angular.z) < AT_REST_RADPS
        state = np.array(
            [pose.position.x, pose.position.y, yaw_from_quaternion(q.x, q.y, q.z, q.w)]
        )
        self._command(*self.follower.command(state, at_rest=at_rest))
        if self.follower.done and not self._announced_done:
            self._announced_done = True
            self.get_logger().info(
                f'route done in {self._last_pose_s - self.started_s:.0f} s; commanding a stop'
            )

    def _watch_poses(self) -> None:
        if self._stopped_for_timeout or time.monotonic() - self._last_pose_s < self.pose_timeout_s:
            return
        self._stopped_for_timeout = True
        self.timeouts += 1
        self._command(0.0, 0.0)
        if self.started_s is not None:
            self.get_logger().warning(
                f'no pose for {self.pose_timeout_s:g} s: commanding a stop '
                f'({self.timeouts} times so far)'
            )

    def _log_progress(self) -> None:
        if self.started_s is None or self.follower.done:
            return
        elapsed = time.monotonic() - self.started_s
        share = self.follower.progress
        eta = f', ETA {elapsed * (1.0 - share) / share:.0f} s' if share > 0.01 else ''
        self.get_logger().info(
            f'route {100.0 * share:.0f} % ({share * self.follower.length_m:.1f} of '
            f'{self.follower.length_m:.1f} m) after {elapsed:.0f} s{eta}'
        )


@console_main('route_driver')
def main(argv: list[str] | None = None) -> int:
    """Drive the route until Ctrl-C."""
    return spin_node('route_driver', RouteDriverNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
