"""slam_dashboard: a live web page of a running graph, at http://<this machine>:8080/.

Topics: subscribes em_sam/landmarks, em_sam/path, em_sam/moveable, monoslam/path, features,
shadow/tracks, camera/image_raw(/compressed), /diagnostics; publishes /diagnostics."""

from __future__ import annotations

import sys
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Path
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from slam_bringup.dashboard.server import DashboardServer, serve, stop
from slam_bringup.dashboard.state import DashboardState
from slam_core.cli import console_main
from slam_core.errors import SlamError
from slam_core.params import Param, ParamTable, Range
from slam_interfaces.msg import (
    FeatureTrackArray,
    LandmarkMap,
    MoveableLandmarkArray,
    ShadowTrackArray,
)
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos, output_qos, sensor_qos
from slam_ros.spin import spin_node

PARAMETERS = ParamTable(
    'slam_dashboard',
    (
        Param(
            'host',
            '0.0.0.0',
            'address to serve the page on: 0.0.0.0 for every network interface (a laptop on '
            'the robot network can open it), 127.0.0.1 for this machine only',
        ),
        Param(
            'port', 8080, 'TCP port of the page (0: any free port, logged)', range=Range(0, 65535)
        ),
        Param('update_hz', 4.0, 'page updates per second, Hz', range=Range(0.2, 30.0)),
        Param(
            'image',
            'auto',
            'camera image shown: auto (whichever of camera/image_raw and '
            'camera/image_raw/compressed comes), raw, compressed or none',
            choices=('auto', 'raw', 'compressed', 'none'),
        ),
        Param(
            'image_hz',
            2.0,
            'images shown per second at most (the others are skipped and counted), Hz',
            range=Range(0.0, 30.0, low_open=True),
        ),
        Param('image_width', 640, 'width of the image on the page, pixels', range=Range(16, 4096)),
        Param(
            'stale_s',
            5.0,
            'a /diagnostics status not updated for this long shows as STALE, s',
            range=Range(0.5),
        ),
        Param(
            'path_points',
            2000,
            'at most this many points of a path on the page (evenly thinned)',
            range=Range(2),
        ),
        Param('map_only', False, 'show the EM-SAM map and diagnostics only (no camera topics)'),
    ),
)


def _decode_image(message: Any) -> Any:
    from marker_detector.detector.conversions import image_from_message

    return image_from_message(message)


class DashboardNode(Node):
    """Subscribes to the graph's outputs and serves them as a web page."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('slam_dashboard', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.state = DashboardState(
            image_width=int(values['image_width']),
            stale_s=float(values['stale_s']),
            decode_image=_decode_image,
            path_points=int(values['path_points']),
        )
        self.image_period_s = 1.0 / float(values['image_hz'])
        self._last_image_s = -float('inf')
        self.images_skipped = 0
        self.diagnostics = Diagnostics(self, self._counts)
        timed = self.diagnostics.timed
        state = self.state
        inputs: list[tuple[Any, str, Any, Any]] = [
            (LandmarkMap, 'em_sam/landmarks', state.on_landmarks, latched_qos()),
            (Path, 'em_sam/path', state.on_path, latched_qos()),
            (MoveableLandmarkArray, 'em_sam/moveable', state.on_moveable, latched_qos()),
            (DiagnosticArray, '/diagnostics', state.on_diagnostics, output_qos(50)),
        ]
        if not values['map_only']:
            inputs += [
                (Path, 'monoslam/path', state.on_monoslam_path, output_qos(1)),
                (FeatureTrackArray, 'features', state.on_features, output_qos()),
                (ShadowTrackArray, 'shadow/tracks', state.on_shadow_tracks, output_qos(100)),
            ]
            if values['image'] in ('auto', 'raw'):
                inputs.append((Image, 'camera/image_raw', self._on_image, sensor_qos()))
            if values['image'] in ('auto', 'compressed'):
                topic = 'camera/image_raw/compressed'
                inputs.append((CompressedImage, topic, self._on_image, sensor_qos()))
        for message_type, topic, callback, qos in inputs:
            self.create_subscription(message_type, topic, timed(callback, topic), qos)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(
            1.0 / float(values['update_hz']), state.refresh_diagnostics, clock=steady
        )
        address = (str(values['host']), int(values['port']))
        try:
            self.server = DashboardServer(address, self.state, float(values['update_hz']))
        except OSError as err:
            raise SlamError(
                f'cannot serve on {address[0]}:{address[1]}: {err.strerror} '
                '(another program on that port? set -p port:=... or port:=0 for any free one)'
            ) from None
        serve(self.server)
        host, port = self.server.server_address[:2]
        host = host.decode() if isinstance(host, bytes) else host
        shown = 'localhost' if host in ('0.0.0.0', '::') else host
        self.get_logger().info(
            f'slam_dashboard: open http://{shown}:{port}/ in a browser'
            + (" (or this machine's address from another one)" if shown == 'localhost' else '')
        )

    def _on_image(self, message: Any) -> None:
        now = time.monotonic()
        if now - self._last_image_s < self.image_period_s:
            self.images_skipped += 1
            return
        self._last_image_s = now
        failed = self.state.images_failed
        self.state.on_image(message)
        if self.state.images_failed > failed:
            self.get_logger().warning(
                f'slam_dashboard: image not shown: {self.state.last_image_error}',
                throttle_duration_sec=10.0,
            )

    def _counts(self) -> dict[str, int]:
        return {
            'images shown': self.state.images_encoded,
            'images skipped (image_hz)': self.images_skipped,
            'dropped': self.state.images_failed,
            'page clients': self.server.clients,
            'page updates sent': self.server.messages_sent,
        }

    def destroy_node(self) -> None:
        stop(self.server)
        super().destroy_node()


@console_main('slam_dashboard')
def main(argv: list[str] | None = None) -> int:
    """Serve the page until Ctrl-C."""
    return spin_node('slam_dashboard', DashboardNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
