"""The dashboard's web server: the page's files, ``/state.json`` and the ``/ws`` WebSocket."""

from __future__ import annotations

import json
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from slam_bringup.dashboard.state import DashboardState
from slam_bringup.dashboard.websocket import (
    CLOSE,
    PING,
    PONG,
    TEXT,
    WebSocketError,
    accept_key,
    encode_frame,
    read_message,
)

ASSETS = {
    '/': ('index.html', 'text/html; charset=utf-8'),
    '/index.html': ('index.html', 'text/html; charset=utf-8'),
    '/dashboard.js': ('dashboard.js', 'text/javascript; charset=utf-8'),
    '/dashboard.css': ('dashboard.css', 'text/css; charset=utf-8'),
}


def asset(name: str) -> bytes:
    """The bytes of one of the page's files."""
    return resources.files('slam_bringup.dashboard').joinpath('web', name).read_bytes()


class DashboardServer(ThreadingHTTPServer):
    """Serves one DashboardState; counts connections and messages sent."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(
        self,
        address: tuple[str, int],
        state: DashboardState,
        update_hz: float,
    ) -> None:
        super().__init__(address, DashboardHandler)
        self.state, self.update_hz = state, update_hz
        self.lock = threading.Lock()
        self.clients = 0
        self.connections = 0
        self.messages_sent = 0
        self.requests = 0
        self.stopping = threading.Event()

    def count(self, name: str, delta: int = 1) -> None:
        with self.lock:
            setattr(self, name, getattr(self, name) + delta)


class DashboardHandler(BaseHTTPRequestHandler):
    """GET of a page file, ``/state.json``, or the ``/ws`` upgrade."""

    server: DashboardServer
    protocol_version = 'HTTP/1.1'

    def log_message(self, format: str, *args: Any) -> None:
        """Quiet: the node counts requests on /diagnostics instead of logging each."""

    def do_GET(self) -> None:
        self.server.count('requests')
        path = self.path.split('?', 1)[0]
        if path == '/ws':
            self._websocket()
        elif path == '/state.json':
            _, sections = self.server.state.snapshot(0)
            self._send(json.dumps(sections).encode(), 'application/json')
        elif path in ASSETS:
            name, content_type = ASSETS[path]
            self._send(asset(name), content_type)
        else:
            self.send_error(HTTPStatus.NOT_FOUND, f'no {path} here; the page is at /')

    def _send(self, body: bytes, content_type: str) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header('Content-Type', content_type)
        self.send_header('Content-Length', str(len(body)))
        self.send_header('Cache-Control', 'no-store')
        self.end_headers()
        self.wfile.write(body)

    def _websocket(self) -> None:
        key = self.headers.get('Sec-WebSocket-Key')
        if 'websocket' not in self.headers.get('Upgrade', '').lower() or not key:
            self.send_error(HTTPStatus.BAD_REQUEST, '/ws takes a WebSocket upgrade')
            return
        self.send_response(HTTPStatus.SWITCHING_PROTOCOLS)
        self.send_header('Upgrade', 'websocket')
        self.send_header('Connection', 'Upgrade')
        self.send_header('Sec-WebSocket-Accept', accept_key(key))
        self.end_headers()
        self.close_connection = True
        server = self.server
        server.count('connections')
        server.count('clients')
        closed = threading.Event()
        send_lock = threading.Lock()

        def send(payload: bytes, opcode: int) -> None:
            with send_lock:
                self.wfile.write(encode_frame(payload, opcode))
                self.wfile.flush()

        def receive() -> None:
            try:
                while not closed.is_set():
                    opcode, payload = read_message(self.rfile)
                    if opcode == CLOSE:
                        send(payload[:2], CLOSE)
                        break
                    if opcode == PING:
                        send(payload, PONG)
            except (OSError, WebSocketError):
                pass
            closed.set()

        threading.Thread(target=receive, name='dashboard-ws-receive', daemon=True).start()
        version = 0
        try:
            while not closed.is_set() and not server.stopping.is_set():
                version, sections = server.state.snapshot(version)
                if sections:
                    message = {'version': version, 'sections': sections}
                    send(json.dumps(message).encode(), TEXT)
                    server.count('messages_sent')
                closed.wait(1.0 / server.update_hz)
            if not closed.is_set():
                send(b'\x03\xe9', CLOSE)  # 1001: going away
        except OSError:
            pass
        finally:
            closed.set()
            server.count('clients', -1)


def serve(server: DashboardServer) -> threading.Thread:
    """Run ``server`` in a daemon thread; stop it with ``stop(server)``."""
    thread = threading.Thread(target=server.serve_forever, name='dashboard-http', daemon=True)
    thread.start()
    return thread


def stop(server: DashboardServer, timeout_s: float = 2.0) -> None:
    """Close every WebSocket (1001) and the listening socket."""
    server.stopping.set()
    server.shutdown()
    server.server_close()
    deadline = time.monotonic() + timeout_s
    while server.clients > 0 and time.monotonic() < deadline:
        time.sleep(0.05)
