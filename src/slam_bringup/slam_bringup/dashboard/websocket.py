"""The WebSocket protocol (RFC 6455) on a plain socket: the handshake key and frames."""

from __future__ import annotations

import base64
import hashlib
import os
import struct
from typing import Protocol

GUID = '258EAFA5-E914-47DA-95CA-C5AB0DC85B11'
TEXT, BINARY, CLOSE, PING, PONG, CONTINUATION = 0x1, 0x2, 0x8, 0x9, 0xA, 0x0
MAX_MESSAGE_BYTES = 64 * 1024 * 1024


class Readable(Protocol):
    """A byte stream: a socket's ``makefile('rb')``, ``io.BytesIO``."""

    def read(self, size: int, /) -> bytes | None: ...


class WebSocketError(ConnectionError):
    """The peer broke the protocol or closed the connection."""


def accept_key(key: str) -> str:
    """The Sec-WebSocket-Accept value for a client's Sec-WebSocket-Key."""
    digest = hashlib.sha1((key.strip() + GUID).encode('ascii')).digest()
    return base64.b64encode(digest).decode('ascii')


def encode_frame(payload: bytes, opcode: int = TEXT, *, masked: bool = False) -> bytes:
    """One final frame with ``payload``; a client's frames are ``masked``."""
    first = 0x80 | opcode
    mask_bit = 0x80 if masked else 0
    size = len(payload)
    if size < 126:
        header = struct.pack('!BB', first, mask_bit | size)
    elif size < 1 << 16:
        header = struct.pack('!BBH', first, mask_bit | 126, size)
    else:
        header = struct.pack('!BBQ', first, mask_bit | 127, size)
    if not masked:
        return header + payload
    mask = os.urandom(4)
    return header + mask + _unmask(payload, mask)


def _unmask(payload: bytes, mask: bytes) -> bytes:
    if not payload:
        return payload
    repeated = (mask * (len(payload) // 4 + 1))[: len(payload)]
    value = int.from_bytes(payload, 'big') ^ int.from_bytes(repeated, 'big')
    return value.to_bytes(len(payload), 'big')


def _read_exactly(stream: Readable, size: int) -> bytes:
    data = stream.read(size)
    if data is None or len(data) < size:
        raise WebSocketError('connection closed in the middle of a frame')
    return data


def read_frame(stream: Readable) -> tuple[bool, int, bytes]:
    """Read one frame: (final, opcode, unmasked payload)."""
    head = stream.read(2)
    if not head:
        raise WebSocketError('connection closed')
    if len(head) < 2:
        raise WebSocketError('connection closed in the middle of a frame')
    first, second = head[0], head[1]
    size = second & 0x7F
    if size == 126:
        size = struct.unpack('!H', _read_exactly(stream, 2))[0]
    elif size == 127:
        size = struct.unpack('!Q', _read_exactly(stream, 8))[0]
    if size > MAX_MESSAGE_BYTES:
        raise WebSocketError(f'frame of {size} bytes, more than {MAX_MESSAGE_BYTES}')
    mask = _read_exactly(stream, 4) if second & 0x80 else b''
    payload = _read_exactly(stream, size) if size else b''
    return bool(first & 0x80), first & 0x0F, _unmask(payload, mask) if mask else payload


def read_message(stream: Readable) -> tuple[int, bytes]:
    """Read one message, frames joined: (opcode, payload). Control frames come alone."""
    final, opcode, payload = read_frame(stream)
    if opcode >= CLOSE or final:
        return opcode, payload
    parts = [payload]
    total = len(payload)
    while not final:
        final, next_opcode, part = read_frame(stream)
        if next_opcode != CONTINUATION:
            raise WebSocketError(f'expected a continuation frame, got opcode {next_opcode}')
        total += len(part)
        if total > MAX_MESSAGE_BYTES:
            raise WebSocketError(f'message of more than {MAX_MESSAGE_BYTES} bytes')
        parts.append(part)
    return opcode, b''.join(parts)
