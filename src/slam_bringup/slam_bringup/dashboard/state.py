"""What the dashboard shows, from ROS messages into versioned JSON-ready sections."""

from __future__ import annotations

import base64
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import numpy as np

from slam_bringup.diag_monitor import SEVERITY, DiagnosticsTable

PATH_POINTS = 2000
CLASSES = {0: 'pending', 1: 'static', 2: 'dynamic'}
MAX_CLASSIFIED = 100_000
"""Feature ids whose class is remembered; the oldest are forgotten beyond this."""


def _thin(points: Sequence[Sequence[float]], limit: int = PATH_POINTS) -> list[list[float]]:
    """At most ``limit`` points, evenly spaced, the last one kept; rounded to mm."""
    if len(points) > limit:
        step = len(points) / (limit - 1)
        picked = [points[int(i * step)] for i in range(limit - 1)] + [points[-1]]
    else:
        picked = list(points)
    return [[round(float(v), 3) for v in point] for point in picked]


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _stamp_s(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


class DashboardState:
    """The dashboard's sections, versioned; thread-safe (sections: docs/design/bringup.md)."""

    def __init__(
        self,
        *,
        image_width: int = 640,
        jpeg_quality: int = 70,
        stale_s: float = 5.0,
        path_points: int = PATH_POINTS,
        decode_image: Callable[[Any], np.ndarray] | None = None,
    ) -> None:
        self.image_width, self.jpeg_quality = image_width, jpeg_quality
        self.decode_image = decode_image
        self.path_points = path_points
        self._lock = threading.Lock()
        self._version = 0
        self._sections: dict[str, tuple[int, Any]] = {}
        self._classes: dict[int, str] = {}
        self._features: list[tuple[int, float, float]] = []
        self._diagnostics = DiagnosticsTable(stale_s)
        self.images_encoded = 0
        self.images_failed = 0
        self.last_image_error = ''

    # --- writers (ROS callbacks) -------------------------------------------------------
    def _set(self, name: str, value: Any) -> None:
        with self._lock:
            self._version += 1
            self._sections[name] = (self._version, value)

    def on_landmarks(self, message: Any) -> None:
        landmarks = []
        for landmark in message.landmarks:
            x, y = float(landmark.position.x), float(landmark.position.y)
            if not _finite(x, y):
                continue
            landmarks.append(
                {
                    'id': int(landmark.landmark_id),
                    'x': round(x, 3),
                    'y': round(y, 3),
                    'weight': round(float(landmark.weight), 3),
                    'moveable': bool(landmark.moveable),
                    'sightings': int(landmark.num_observations),
                }
            )
        landmarks.sort(key=lambda item: item['id'])
        moveable = sum(item['moveable'] for item in landmarks)
        self._set(
            'map',
            {
                'frame': str(message.header.frame_id),
                'stamp': _stamp_s(message.header),
                'landmarks': landmarks,
                'count': len(landmarks),
                'static': len(landmarks) - moveable,
                'moveable': moveable,
            },
        )

    def _path(self, message: Any, second: str) -> dict[str, Any]:
        """A nav_msgs/Path as its frame and [[x, ``second``], ...] points, thinned."""
        points = [
            (p.pose.position.x, getattr(p.pose.position, second))
            for p in message.poses
            if _finite(p.pose.position.x, getattr(p.pose.position, second))
        ]
        return {'frame': str(message.header.frame_id), 'points': _thin(points, self.path_points)}

    def on_path(self, message: Any) -> None:
        self._set('path', self._path(message, 'y'))

    def on_moveable(self, message: Any) -> None:
        items = []
        for landmark in message.landmarks:
            seen = [
                (s.position.x, s.position.y)
                for s in landmark.sightings
                if _finite(s.position.x, s.position.y)
            ]
            items.append(
                {
                    'id': int(landmark.landmark_id),
                    'weight': round(float(landmark.weight), 3),
                    'seen': _thin(seen, 500),
                }
            )
        self._set('moveable', sorted(items, key=lambda item: item['id']))

    def on_monoslam_path(self, message: Any) -> None:
        self._set('monoslam', self._path(message, 'z'))  # seen from above: x right, z forward

    def on_shadow_tracks(self, message: Any) -> None:
        with self._lock:
            for track in message.tracks:
                status = track.status
                status = int.from_bytes(status, 'little') if isinstance(status, bytes) else status
                self._classes[int(track.id)] = CLASSES.get(int(status), 'unknown')
            while len(self._classes) > MAX_CLASSIFIED:
                del self._classes[next(iter(self._classes))]
        self._publish_features()

    def on_features(self, message: Any) -> None:
        self._features = [
            (int(t.id), float(t.u), float(t.v)) for t in message.tracks if _finite(t.u, t.v)
        ]
        self._publish_features()

    def _publish_features(self) -> None:
        with self._lock:
            rows = [
                [i, round(u, 1), round(v, 1), self._classes.get(i, 'unknown')]
                for i, u, v in self._features
            ]
        counts = {name: 0 for name in ('pending', 'static', 'dynamic', 'unknown')}
        for row in rows:
            counts[str(row[3])] += 1
        self._set('features', {'tracks': rows, 'counts': counts})

    def on_image(self, message: Any) -> None:
        """Encode the image for the page; a message that cannot be decoded is counted."""
        try:
            if self.decode_image is None:
                raise ValueError('no image decoder')
            gray = self.decode_image(message)
            height, width = gray.shape[:2]
            scale = min(1.0, self.image_width / max(1, width))
            if scale < 1.0:
                size = (max(1, round(width * scale)), max(1, round(height * scale)))
                gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
            ok, jpeg = cv2.imencode('.jpg', gray, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if not ok:
                raise ValueError('OpenCV could not encode the image as JPEG')
        except ValueError as error:
            self.images_failed += 1
            self.last_image_error = str(error)
            return
        self.images_encoded += 1
        self._set(
            'image',
            {
                'jpeg': base64.b64encode(jpeg.tobytes()).decode('ascii'),
                'width': int(width),
                'height': int(height),
                'scale': scale,
                'stamp': _stamp_s(message.header),
            },
        )

    def on_diagnostics(self, message: Any) -> None:
        with self._lock:
            self._diagnostics(message)
        self.refresh_diagnostics()

    def refresh_diagnostics(self, now_s: float | None = None) -> None:
        """Recompute the table's levels and ages (STALE comes with time, not messages)."""
        now = time.monotonic() if now_s is None else now_s
        table = self._diagnostics
        with self._lock:
            rows = [
                {
                    'level': table.level_of(status, now),
                    'name': status.name,
                    'message': status.message,
                    'age': round(now - status.received_s, 1),
                }
                for status in table.statuses.values()
            ]
        rows.sort(key=lambda row: (-SEVERITY.get(str(row['level']), 3), str(row['name'])))
        self._set('diagnostics', rows)

    # --- reader (web server) -----------------------------------------------------------
    @property
    def version(self) -> int:
        with self._lock:
            return self._version

    def snapshot(self, since: int = 0) -> tuple[int, dict[str, Any]]:
        """(version, the sections changed after version ``since``)."""
        with self._lock:
            changed = {
                name: value for name, (version, value) in self._sections.items() if version > since
            }
            return self._version, changed
