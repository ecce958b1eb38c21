"""peoplebot_sim: a live, wall-clock simulated Peoplebot in the EM-SAM paper's office.

Stands in for a robot's base and camera drivers (same topics, frames and QoS; the camera
mount is camera_mount's), with the paper's marker moves and ground truth on its own topics;
route_driver drives it.
Topics:
  subscribes  cmd_vel (geometry_msgs/Twist, reliable, 10)
  publishes   odom (nav_msgs/Odometry), /tf (odom -> base_link, with publish_tf);
              camera/image_raw (mono8), camera/image_raw/compressed, camera/camera_info:
              best effort; ground_truth/pose, ground_truth/landmarks (transient local);
              /diagnostics. In full: docs/design/simulation_nodes.md."""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from tf2_msgs.msg import TFMessage

from slam_core.cli import console_main
from slam_core.geometry.se2 import wrap_angle
from slam_core.params import NON_NEGATIVE, POSITIVE, Param, ParamTable, Range
from slam_interfaces.msg import LandmarkEstimate, LandmarkMap
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos, output_qos, sensor_qos
from slam_ros.spin import spin_node
from slam_sim.core.camera_effects import CameraEffects, encode_jpeg
from slam_sim.core.live_base import LiveBase
from slam_sim.core.office import OfficeConfig, Variant, office_route, simulate_office
from slam_sim.core.office_render import Renderer
from slam_sim.core.office_view import office_camera
from slam_sim.live_messages import camera_info_message, odometry_message, set_stamp
from slam_sim.office_bag import ODOM_POSE_COVARIANCE_DIAGONAL, odom_twist_covariance_diagonal
from slam_sim.office_camera_bag import (
    IMAGE_FORMAT,
    OPTICAL_FRAME,
    CameraRig,
    camera_pose,
    office_markers,
)

PARAMETERS = ParamTable(
    'peoplebot_sim',
    (
        Param(
            'seed',
            0,
            'world, moves, odometry noise and image noise of the run',
            range=NON_NEGATIVE,
        ),
        Param(
            'variant',
            Variant.STANDARD.value,
            'what the moveable markers do (office_sim variants)',
            choices=tuple(v.value for v in Variant),
        ),
        Param(
            'odom_rate_hz',
            20.0,
            'odometry and odom -> base_link rate, Hz',
            range=Range(1.0, 200.0),
        ),
        Param('camera_rate_hz', 10.0, 'camera frame rate, Hz', range=Range(1.0, 30.0)),
        Param(
            'width',
            640,
            'image width, px (70 deg horizontal field of view)',
            range=Range(16, 8192),
        ),
        Param('height', 480, 'image height, px', range=Range(16, 8192)),
        Param(
            'jpeg_quality', 65, 'JPEG quality of the compressed image, 1-100', range=Range(1, 100)
        ),
        Param('publish_compressed', True, 'also publish camera/image_raw/compressed'),
        Param('publish_tf', True, 'publish odom -> base_link on /tf, as a base driver does'),
        Param(
            'cmd_vel_timeout_s',
            0.5,
            'stop when no cmd_vel came for this long, s (the drivers watchdog)',
            range=POSITIVE,
        ),
        Param('odom_frame', 'odom', 'odometry frame id'),
        Param('base_frame', 'base_link', 'robot base frame id'),
        Param('camera_frame', OPTICAL_FRAME, 'camera optical frame id of the images'),
    ),
)


class PeoplebotSimNode(Node):
    """The live simulated robot."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('peoplebot_sim', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.odom_frame, self.base_frame = str(values['odom_frame']), str(values['base_frame'])
        self.camera_frame = str(values['camera_frame'])
        config = OfficeConfig(odom_rate_hz=float(values['odom_rate_hz']))
        self.run = simulate_office(int(values['seed']), str(values['variant']), config=config)
        _, _, start = office_route(config)
        seeds = np.random.SeedSequence(int(values['seed'])).spawn(6)
        self.base = LiveBase(
            start,
            self._now_ns(),
            config.motion,
            config.odometry_noise,
            command_timeout_s=float(values['cmd_vel_timeout_s']),
            seed=int(seeds[5].generate_state(1)[0]),
        )
        self.rig = CameraRig(
            camera=office_camera(int(values['width']), int(values['height'])),
            rate_hz=float(values['camera_rate_hz']),
            jpeg_quality=int(values['jpeg_quality']),
        )
        self.renderer = Renderer(self.rig.camera, self.run.world.walls_m, self.rig.style)
        self.effects = CameraEffects(self.rig.effects, self.rig.camera, seeds[4])
        self.camera_info = camera_info_message(self.rig.camera)
        self.covariances = (
            np.diag(ODOM_POSE_COVARIANCE_DIAGONAL).reshape(36),
            np.diag(odom_twist_covariance_diagonal(config)).reshape(36),
        )
        self.corridor_middle_x = float(self.run.world.corridor.center_m[0])
        self.moved_at_ns: int | None = None
        self.frames = self.frames_late = self.odometry = self.rejected = 0
        self._last_odom = (self.base.time_ns, self.base.odom_pose.copy())
        self._last_frame_wall: float | None = None

        sensor = sensor_qos()
        self.odom_publisher = self.create_publisher(Odometry, 'odom', output_qos(depth=100))
        self.tf_publisher = (
            self.create_publisher(TFMessage, '/tf', output_qos(depth=100))
            if values['publish_tf']
            else None
        )
        self.image_publisher = self.create_publisher(Image, 'camera/image_raw', sensor)
        self.compressed_publisher = (
            self.create_publisher(CompressedImage, 'camera/image_raw/compressed', sensor)
            if values['publish_compressed']
            else None
        )
        self.info_publisher = self.create_publisher(CameraInfo, 'camera/camera_info', sensor)
        self.truth_publisher = self.create_publisher(
            Odometry, 'ground_truth/pose', output_qos(depth=100)
        )
        self.landmarks_publisher = self.create_publisher(
            LandmarkMap, 'ground_truth/landmarks', latched_qos()
        )
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        self.create_subscription(Twist, 'cmd_vel', timed(self._on_cmd_vel, 'cmd_vel'), 10)
        self.create_timer(1.0 / config.odom_rate_hz, timed(self._publish_odometry))
        self.create_timer(1.0 / self.rig.rate_hz, timed(self._publish_frame))
        self._publish_landmarks()
        self.get_logger().info(
            f'peoplebot_sim: office seed {values["seed"]} variant {self.run.variant.value}, '
            f'{self.rig.camera.width}x{self.rig.camera.height} at {self.rig.rate_hz:g} Hz, '
            f'odometry at {config.odom_rate_hz:g} Hz; the moveable markers move when the '
            f'robot first crosses x = {self.corridor_middle_x:.2f} m'
        )

    def _now_ns(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    def _counts(self) -> dict[str, int]:
        return {
            'commands rejected': self.rejected,
            'watchdog stops': self.base.timeouts,
            'odometry published': self.odometry,
            'frames published': self.frames,
            'frames late': self.frames_late,
            'seconds skipped': round(self.base.skipped_s),
        }

    def _on_cmd_vel(self, message: Twist) -> None:
        try:
            self.base.command(message.linear.x, message.angular.z, self._now_ns())
        except ValueError as err:
            self.rejected += 1
            self.get_logger().warning(
                f'cmd_vel refused: {err}; {self.rejected} refused so far',
                throttle_duration_sec=2.0,
            )

    def _advance(self) -> None:
        skipped = self.base.skipped_s
        self.base.advance(self._now_ns())
        if self.base.skipped_s > skipped:
            self.get_logger().warning(
                f'the process stalled: {self.base.skipped_s - skipped:.1f} s not simulated '
                f'({self.base.skipped_s:.1f} s so far)'
            )
        if (
            self.moved_at_ns is None
            and self.run.landmarks.move_time_ns is not None
            and self.base.pose[0] >= self.corridor_middle_x
        ):
            self.moved_at_ns = self.base.time_ns
            self.get_logger().info(
                f'the moveable markers moved ({self.run.variant.value}) at {self.moved_at_ns} ns'
            )
            self._publish_landmarks()

    def _publish_odometry(self) -> None:
        self._advance()
        base, stamp_ns = self.base, self.base.time_ns
        last_ns, last_pose = self._last_odom
        if stamp_ns <= last_ns and self.odometry:
            return  # the timer fired again within one 5 ms step (catching up): no new sample
        period_s = max((stamp_ns - last_ns) / 1e9, 1e-9)
        delta = base.odom_pose - last_pose
        heading = last_pose[2]
        forward = float(np.cos(heading) * delta[0] + np.sin(heading) * delta[1]) / period_s
        turn = wrap_angle(float(delta[2])) / period_s
        self._last_odom = (stamp_ns, base.odom_pose.copy())
        odom = odometry_message(
            stamp_ns,
            (self.odom_frame, self.base_frame),
            base.odom_pose,
            (forward, turn),
            self.covariances,
        )
        self.odom_publisher.publish(odom)
        if self.tf_publisher is not None:
            transform = TransformStamped()
            transform.header = odom.header
            transform.child_frame_id = self.base_frame
            position, orientation = odom.pose.pose.position, odom.pose.pose.orientation
            transform.transform.translation.x = position.x
            transform.transform.translation.y = position.y
            transform.transform.rotation = orientation
            self.tf_publisher.publish(TFMessage(transforms=[transform]))
        zeros = np.zeros(36)
        self.truth_publisher.publish(
            odometry_message(
                stamp_ns,
                ('map', self.base_frame),
                base.pose,
                (base.speed, base.turn),
                (zeros, zeros),
            )
        )
        self.odometry += 1

    def _publish_frame(self) -> None:
        wall = time.monotonic()
        if (
            self._last_frame_wall is not None
            and wall - self._last_frame_wall > 1.5 / self.rig.rate_hz
        ):
            self.frames_late += 1
        self._last_frame_wall = wall
        self._advance()
        stamp_ns = self.base.time_ns
        markers = office_markers(self.run, self._marker_time_ns())
        rendered, _ = self.renderer.render(camera_pose(self.base.pose), markers)
        pixels = self.effects.apply(
            rendered,
            frame_index=self.frames,
            time_s=(stamp_ns - self.base.start_ns) / 1e9,
            yaw_rate_radps=self.base.turn,
        )
        image = Image(
            height=int(pixels.shape[0]),
            width=int(pixels.shape[1]),
            encoding='mono8',
            is_bigendian=0,
            step=int(pixels.shape[1]),
            data=pixels.tobytes(),
        )
        set_stamp(image.header, stamp_ns, self.camera_frame)
        self.camera_info.header = image.header
        self.info_publisher.publish(self.camera_info)
        self.image_publisher.publish(image)
        if self.compressed_publisher is not None:
            compressed = CompressedImage(
                format=IMAGE_FORMAT, data=encode_jpeg(pixels, self.rig.jpeg_quality)
            )
            compressed.header = image.header
            self.compressed_publisher.publish(compressed)
        self.frames += 1

    def _marker_time_ns(self) -> int:
        """A run time at which ``office_markers`` draws the markers where they are now."""
        move_ns = self.run.landmarks.move_time_ns
        return 0 if self.moved_at_ns is None or move_ns is None else move_ns

    def _publish_landmarks(self) -> None:
        truth = self.run.landmarks
        after = self.moved_at_ns is not None
        positions = truth.positions_after_m if after else truth.positions_before_m
        message = LandmarkMap()
        set_stamp(message.header, self.base.time_ns, 'map')
        for k, landmark_id in enumerate(truth.ids.tolist()):
            estimate = LandmarkEstimate(
                landmark_id=int(landmark_id), weight=1.0, moveable=bool(truth.moveable[k])
            )
            estimate.position.x, estimate.position.y = (float(v) for v in positions[k])
            message.landmarks.append(estimate)
        self.landmarks_publisher.publish(message)


@console_main('peoplebot_sim')
def main(argv: list[str] | None = None) -> int:
    """Run the simulated robot until Ctrl-C."""
    return spin_node('peoplebot_sim', PeoplebotSimNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
