"""A real headless Chromium driven over the Chrome DevTools Protocol, for page tests.

``HeadlessChromium`` starts the browser on a free debugging port, connects to its first
page over a WebSocket (the protocol framing of ``slam_bringup.dashboard.websocket``) and
offers ``navigate``, ``evaluate`` (a JavaScript expression's value), ``wait_for`` and
``screenshot`` (PNG). ``find_chromium`` skips the test with the reason when there is no
browser, or fails it when ``SLAM_REQUIRE_BROWSER_TEST=1`` (CI, which installs one).
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest

from slam_bringup.dashboard.websocket import TEXT, encode_frame, read_message

BROWSERS = ('chromium', 'chromium-browser', 'google-chrome', 'google-chrome-stable')
START_TIMEOUT_S = 60.0


def find_chromium() -> str:
    """The browser's path; skip (or fail when it is required) without one."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    reason = (
        'no headless browser (chromium): scripts/test.sh installs it on Debian '
        '(scripts/bootstrap.sh --test); elsewhere install Chromium or Chrome'
    )
    if os.environ.get('SLAM_REQUIRE_BROWSER_TEST') == '1':
        pytest.fail(reason + ' -- SLAM_REQUIRE_BROWSER_TEST=1 requires this test')
    pytest.skip(reason)


class DevToolsError(RuntimeError):
    """The browser answered a DevTools call with an error, or did not answer."""


class HeadlessChromium:
    """One headless browser process with one page (module docstring)."""

    def __init__(self, binary: str, width: int = 1400, height: int = 1000) -> None:
        self.profile = tempfile.mkdtemp(prefix='slam-chromium-')
        self.process = subprocess.Popen(
            [
                binary,
                '--headless=new',
                '--no-sandbox',  # root in CI containers
                '--disable-gpu',
                '--no-first-run',
                '--disable-extensions',
                '--remote-debugging-port=0',
                f'--user-data-dir={self.profile}',
                f'--window-size={width},{height}',
                'about:blank',
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.log: list[str] = []
        self._next_id = 0
        try:
            port = self._debugging_port()
            self.socket = self._connect_page(port)
        except BaseException:
            self.close()
            raise
        self.stream = self.socket.makefile('rb')

    def _debugging_port(self) -> int:
        assert self.process.stderr is not None
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            line = self.process.stderr.readline()
            if not line and self.process.poll() is not None:
                break
            self.log.append(line.rstrip())
            match = re.search(r'DevTools listening on ws://[^:]+:(\d+)/', line)
            if match:
                threading.Thread(target=self._drain, daemon=True).start()
                return int(match.group(1))
        raise DevToolsError('chromium did not start:\n' + '\n'.join(self.log[-20:]))

    def _drain(self) -> None:
        """Keep reading the browser's log so that a full pipe never blocks it."""
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.log.append(line.rstrip())

    def _connect_page(self, port: int) -> socket.socket:
        deadline = time.monotonic() + START_TIMEOUT_S
        targets: list[dict[str, Any]] = []
        while time.monotonic() < deadline:
            with urllib.request.urlopen(f'http://127.0.0.1:{port}/json/list', timeout=10) as r:
                targets = [t for t in json.load(r) if t.get('type') == 'page']
            if targets:
                break
            time.sleep(0.2)
        if not targets:
            raise DevToolsError('chromium shows no page target')
        url = urlparse(targets[0]['webSocketDebuggerUrl'])
        connection = socket.create_connection((url.hostname, url.port), timeout=60)
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f'GET {url.path} HTTP/1.1\r\nHost: {url.netloc}\r\nUpgrade: websocket\r\n'
            f'Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n'
        )
        connection.sendall(request.encode())
        response = b''
        while b'\r\n\r\n' not in response:
            chunk = connection.recv(1)
            if not chunk:
                raise DevToolsError('chromium closed the DevTools connection')
            response += chunk
        if b' 101 ' not in response.split(b'\r\n', 1)[0]:
            raise DevToolsError(f'DevTools refused the WebSocket: {response[:200]!r}')
        return connection

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools call; its result (events in between are ignored)."""
        self._next_id += 1
        request = {'id': self._next_id, 'method': method, 'params': params}
        self.socket.sendall(encode_frame(json.dumps(request).encode(), TEXT, masked=True))
        while True:
            opcode, payload = read_message(self.stream)
            if opcode != TEXT:
                continue
            answer = json.loads(payload)
            if answer.get('id') == self._next_id:
                if 'error' in answer:
                    raise DevToolsError(f'{method}: {answer["error"]}')
                return dict(answer.get('result', {}))

    def navigate(self, url: str) -> None:
        self.call('Page.navigate', url=url)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-serializable)."""
        result = self.call('Runtime.evaluate', expression=expression, returnByValue=True)
        if 'exceptionDetails' in result:
            raise DevToolsError(f'{expression}: {result["exceptionDetails"]}')
        return result['result'].get('value')

    def wait_for(self, expression: str, accept: Callable[[Any], bool], timeout_s: float) -> Any:
        """Evaluate ``expression`` every 0.25 s until ``accept(value)`` (never for None, as
        before the page loaded); the value."""
        deadline = time.monotonic() + timeout_s
        value = None
        while time.monotonic() < deadline:
            try:
                value = self.evaluate(expression)
            except DevToolsError:
                value = None
            if value is not None and accept(value):
                return value
            time.sleep(0.25)
        raise TimeoutError(f'after {timeout_s:g} s, {expression} is {value!r}')

    def screenshot(self, path: Path) -> Path:
        """Save the page as a PNG; its path."""
        data = self.call('Page.captureScreenshot', format='png', captureBeyondViewport=True)
        path.write_bytes(base64.b64decode(data['data']))
        return path

    def close(self) -> None:
        if getattr(self, 'socket', None) is not None:
            self.socket.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)
