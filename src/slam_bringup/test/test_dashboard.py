"""slam_dashboard's parts without a graph: the WebSocket framing, the state built from real
messages, and the web server answering a real HTTP and WebSocket client on a local port."""

from __future__ import annotations

import base64
import io
import json
import math
import os
import socket
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CompressedImage, Image

from marker_detector.detector.conversions import image_from_message
from slam_bringup.dashboard.server import DashboardServer, serve, stop
from slam_bringup.dashboard.state import DashboardState
from slam_bringup.dashboard.websocket import (
    BINARY,
    CONTINUATION,
    TEXT,
    WebSocketError,
    accept_key,
    encode_frame,
    read_message,
)
from slam_interfaces.msg import (
    FeatureTrack,
    FeatureTrackArray,
    LandmarkEstimate,
    LandmarkMap,
    ShadowTrack,
    ShadowTrackArray,
)


def test_accept_key_is_rfc_6455s_example() -> None:
    assert accept_key('dGhlIHNhbXBsZSBub25jZQ==') == 's3pPLMBiTxaQ9kYGzzhZRbK+xOo='


@pytest.mark.parametrize('size', [0, 1, 125, 126, 65535, 65536, 200_000])
@pytest.mark.parametrize('masked', [False, True])
def test_frames_round_trip(size: int, masked: bool) -> None:
    payload = os.urandom(size)
    frame = encode_frame(payload, BINARY, masked=masked)
    assert read_message(io.BytesIO(frame)) == (BINARY, payload)


def test_fragments_are_joined_and_truncation_is_an_error() -> None:
    first = encode_frame(b'hello ', TEXT)
    first = bytes([first[0] & 0x7F]) + first[1:]  # not final
    rest = encode_frame(b'world', CONTINUATION, masked=True)
    assert read_message(io.BytesIO(first + rest)) == (TEXT, b'hello world')
    with pytest.raises(WebSocketError, match='middle of a frame'):
        read_message(io.BytesIO(encode_frame(b'x' * 300, TEXT)[:-1]))
    with pytest.raises(WebSocketError, match='connection closed'):
        read_message(io.BytesIO(b''))


def landmark_map(*rows: tuple[int, float, float, bool]) -> LandmarkMap:
    message = LandmarkMap()
    message.header.frame_id = 'map'
    for landmark_id, x, y, moveable in rows:
        estimate = LandmarkEstimate(landmark_id=landmark_id, weight=0.5, moveable=moveable)
        estimate.position.x, estimate.position.y = x, y
        estimate.num_observations = 4
        message.landmarks.append(estimate)
    return message


def test_map_section_counts_and_skips_non_finite_positions() -> None:
    state = DashboardState()
    state.on_landmarks(
        landmark_map((7, 1.0, 2.0, False), (3, 0.5, -1.0, True), (9, math.nan, 0, False))
    )
    version, sections = state.snapshot()
    section = sections['map']
    assert (section['count'], section['static'], section['moveable']) == (2, 1, 1)
    assert [item['id'] for item in section['landmarks']] == [3, 7]
    assert state.snapshot(version) == (version, {})  # nothing new since
    path = Path()
    for x in range(5000):
        pose = PoseStamped()
        pose.pose.position.x = float(x)
        path.poses.append(pose)
    state.path_points = 100
    state.on_path(path)
    _, changed = state.snapshot(version)
    assert list(changed) == ['path']
    points = changed['path']['points']
    assert len(points) == 100 and points[0] == [0.0, 0.0] and points[-1] == [4999.0, 0.0]


def test_features_take_the_shadow_filters_class_by_id() -> None:
    state = DashboardState()
    features = FeatureTrackArray(tracks=[FeatureTrack(id=i, u=10.0 * i, v=5.0) for i in range(4)])
    state.on_features(features)
    tracks = ShadowTrackArray(
        tracks=[
            ShadowTrack(id=0, status=1),
            ShadowTrack(id=1, status=2),
            ShadowTrack(id=2, status=0),
        ]
    )
    state.on_shadow_tracks(tracks)
    section = state.snapshot()[1]['features']
    assert [row[3] for row in section['tracks']] == ['static', 'dynamic', 'pending', 'unknown']
    assert section['counts'] == {'pending': 1, 'static': 1, 'dynamic': 1, 'unknown': 1}


def raw_image(width: int, height: int) -> Image:
    pixels = (np.arange(width * height) % 251).astype(np.uint8)
    message = Image(width=width, height=height, encoding='mono8', step=width)
    message.data = pixels.tobytes()
    return message


def test_images_are_scaled_to_the_page_and_bad_ones_counted() -> None:
    state = DashboardState(image_width=320, decode_image=image_from_message)
    state.on_image(raw_image(1280, 720))
    image = state.snapshot()[1]['image']
    decoded = cv2.imdecode(np.frombuffer(base64.b64decode(image['jpeg']), np.uint8), 0)
    assert decoded.shape == (180, 320) and image['scale'] == 0.25
    assert (image['width'], image['height']) == (1280, 720)
    state.on_image(CompressedImage(format='jpeg', data=b'not a jpeg'))
    state.on_image(Image(encoding='mono8'))
    assert (state.images_encoded, state.images_failed) == (1, 2)
    assert 'empty image' in state.last_image_error


def test_diagnostics_rows_worst_first_and_stale_with_time() -> None:
    state = DashboardState(stale_s=5.0)
    array = DiagnosticArray(
        status=[
            DiagnosticStatus(name='/a', level=DiagnosticStatus.OK, message='fine'),
            DiagnosticStatus(name='/b', level=DiagnosticStatus.WARN, message='lost 3'),
        ]
    )
    state.on_diagnostics(array)
    rows = state.snapshot()[1]['diagnostics']
    assert [(row['level'], row['name']) for row in rows] == [('WARN', '/b'), ('OK', '/a')]
    received = state._diagnostics.statuses['/a'].received_s
    state.refresh_diagnostics(received + 6.0)
    assert {row['level'] for row in state.snapshot()[1]['diagnostics']} == {'STALE'}


@pytest.fixture
def server() -> DashboardServer:
    state = DashboardState()
    state.on_landmarks(landmark_map((1, 0.0, 0.0, False)))
    instance = DashboardServer(('127.0.0.1', 0), state, update_hz=20.0)
    serve(instance)
    yield instance
    stop(instance)


def url(server: DashboardServer, path: str) -> str:
    return f'http://127.0.0.1:{server.server_address[1]}{path}'


def test_server_serves_the_page_state_and_404(server: DashboardServer) -> None:
    page = urllib.request.urlopen(url(server, '/'), timeout=10).read().decode()
    assert 'id="landmark-count"' in page and 'dashboard.js' in page
    for asset in ('/dashboard.js', '/dashboard.css'):
        assert urllib.request.urlopen(url(server, asset), timeout=10).status == 200
    state = json.load(urllib.request.urlopen(url(server, '/state.json'), timeout=10))
    assert state['map']['count'] == 1
    with pytest.raises(urllib.error.HTTPError) as missing:
        urllib.request.urlopen(url(server, '/nothing'), timeout=10)
    assert missing.value.code == 404


def test_websocket_sends_the_state_then_changes(server: DashboardServer) -> None:
    connection = socket.create_connection(('127.0.0.1', server.server_address[1]), timeout=10)
    key = base64.b64encode(os.urandom(16)).decode()
    connection.sendall(
        (
            f'GET /ws HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n'
            f'Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n'
        ).encode()
    )
    stream = connection.makefile('rb')
    status = stream.readline()
    assert b' 101 ' in status
    headers = b''
    while not headers.endswith(b'\r\n\r\n'):
        headers += stream.readline()
    assert f'Sec-WebSocket-Accept: {accept_key(key)}'.encode() in headers
    opcode, payload = read_message(stream)
    first = json.loads(payload)
    assert opcode == TEXT and first['sections']['map']['count'] == 1
    server.state.on_landmarks(landmark_map((1, 0.0, 0.0, False), (2, 1.0, 0.0, True)))
    _, payload = read_message(stream)
    second = json.loads(payload)
    assert list(second['sections']) == ['map'] and second['sections']['map']['count'] == 2
    assert second['version'] > first['version']
    connection.sendall(encode_frame(b'\x03\xe8', 0x8, masked=True))  # close
    assert read_message(stream)[0] == 0x8
    connection.close()
