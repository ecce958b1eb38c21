"""dynamic_scene_sim: the dynamic scene's hand-held camera as a live camera driver.

dynamic_camera_sim's scene (same seed, duration_s): all frames are rendered at the start
(about 0.1 s each), then published live at rate_hz; loops > 1 replays it.
Topics:
  publishes   camera/image_raw (sensor_msgs/Image mono8, camera_optical_frame, best effort)
              camera/camera_info (sensor_msgs/CameraInfo, best effort)
              ground_truth/camera_pose (geometry_msgs/PoseStamped, map: the optical frame)
              /diagnostics: frames published, frames skipped
Details: docs/design/simulation.md."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from slam_core.cli import console_main
from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.params import NON_NEGATIVE, Param, ParamTable, Range
from slam_core.progress import ProgressReporter
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import output_qos, sensor_qos
from slam_ros.spin import spin_node
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_render import DynamicRenderer
from slam_sim.live_messages import camera_info_message, set_stamp

OPTICAL_FRAME, MAP_FRAME = 'camera_optical_frame', 'map'
# The frames are held in memory (640 x 480 mono8: 307 KB each, 9.2 MB per second at 30 Hz):
# 240 s at 30 Hz is 2.2 GB, and leaves a 2-minute live window after any warm-up.
MAX_DURATION_S = 240.0

PARAMETERS = ParamTable(
    'dynamic_scene_sim',
    (
        Param('seed', 0, 'the scene, its camera path and its objects', range=NON_NEGATIVE),
        Param(
            'duration_s',
            10.0,
            'length of the run, s (held in memory: 9.2 MB per second at 30 Hz)',
            range=Range(1.0, MAX_DURATION_S),
        ),
        Param('rate_hz', 30.0, 'camera frame rate, Hz', range=Range(1.0, 60.0)),
        Param('loops', 1, 'times the run is played', range=Range(1, 1000)),
        Param(
            'start_delay_s',
            2.0,
            'wait this long after rendering (discovery), s',
            range=NON_NEGATIVE,
        ),
    ),
)


class DynamicSceneSimNode(Node):
    """The live camera of the dynamic scene."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('dynamic_scene_sim', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        config = DynamicSceneConfig(
            duration_s=float(values['duration_s']), rate_hz=float(values['rate_hz'])
        )
        renderer = DynamicRenderer(config, int(values['seed']))
        self.period_ns = round(1e9 / config.rate_hz)
        self.loops = int(values['loops'])
        self.frames: list[tuple[bytes, np.ndarray, np.ndarray]] = []
        progress = ProgressReporter(
            config.frame_count,
            label='dynamic_scene_sim rendering',
            unit='frames',
            log=self.get_logger().info,
        )
        for index, frame in enumerate(renderer.render_all(range(config.frame_count))):
            pixels = np.ascontiguousarray(frame.image, dtype=np.uint8)
            self.frames.append((pixels.tobytes(), frame.rotation.copy(), frame.position_m.copy()))
            progress.update(index + 1)
        progress.finish()
        self.height, self.width = renderer.camera.height, renderer.camera.width
        self.camera_info = camera_info_message(renderer.camera)
        sensor = sensor_qos()
        self.image_publisher = self.create_publisher(Image, 'camera/image_raw', sensor)
        self.info_publisher = self.create_publisher(CameraInfo, 'camera/camera_info', sensor)
        self.pose_publisher = self.create_publisher(
            PoseStamped, 'ground_truth/camera_pose', output_qos(depth=100)
        )
        self.published = self.skipped = self.next_index = 0
        self.diagnostics = Diagnostics(self, self._counts)
        self.start_ns = self._now_ns() + round(float(values['start_delay_s']) * 1e9)
        self.timer = self.create_timer(
            1.0 / (4.0 * config.rate_hz), self.diagnostics.timed(self._tick)
        )
        self.get_logger().info(
            f'dynamic_scene_sim: seed {values["seed"]}, {len(self.frames)} frames '
            f'{self.width}x{self.height} at {config.rate_hz:g} Hz, {self.loops} time(s)'
        )

    def _now_ns(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    def _counts(self) -> dict[str, int]:
        return {'frames published': self.published, 'frames skipped': self.skipped}

    def _tick(self) -> None:
        """Publish the frame that is due; skip and count frames whose time passed."""
        total = len(self.frames) * self.loops
        if self.next_index >= total:
            if not self.timer.is_canceled():
                self.timer.cancel()
                self.get_logger().info(
                    f'dynamic_scene_sim: all {total} frames done: {self.published} published, '
                    f'{self.skipped} skipped'
                )
            return
        due = (self._now_ns() - self.start_ns) // self.period_ns
        if due < self.next_index:
            return
        index = int(min(due, total - 1))
        self.skipped += index - self.next_index
        self.next_index = index + 1
        data, rotation, position = self.frames[index % len(self.frames)]
        stamp_ns = self.start_ns + index * self.period_ns
        image = Image(
            height=self.height,
            width=self.width,
            encoding='mono8',
            is_bigendian=0,
            step=self.width,
            data=data,
        )
        set_stamp(image.header, stamp_ns, OPTICAL_FRAME)
        self.camera_info.header = image.header
        self.info_publisher.publish(self.camera_info)
        self.image_publisher.publish(image)
        pose = PoseStamped()
        set_stamp(pose.header, stamp_ns, MAP_FRAME)
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = (
            float(v) for v in position
        )
        w, x, y, z = quaternion_from_rotation(rotation).tolist()
        orientation = pose.pose.orientation
        orientation.x, orientation.y, orientation.z, orientation.w = x, y, z, w
        self.pose_publisher.publish(pose)
        self.published += 1


@console_main('dynamic_scene_sim')
def main(argv: list[str] | None = None) -> int:
    """Render the run, then publish it live until done or Ctrl-C."""
    return spin_node(
        'dynamic_scene_sim', DynamicSceneSimNode, argv, parameters=PARAMETERS, doc=__doc__
    )


if __name__ == '__main__':
    sys.exit(main())
