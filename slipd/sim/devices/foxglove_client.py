"""A minimal Foxglove WebSocket client (the ``foxglove.sdk.v1`` subprotocol) for tests and benchmarks of the live
view: it connects, reads the server's channel advertisements, subscribes to every channel, and then reads the
messages, or (``stall``) never reads again, as a stuck viewer on a slow link would.

Only what that takes: the opening handshake, masked text frames out, unmasked frames in (text: JSON ops; binary
op 1: message data = op, subscription id u32, log time u64, payload).
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
from typing import Any

SUBPROTOCOL = "foxglove.sdk.v1"


class FoxgloveClient:
    """One connection to a Foxglove WebSocket server on ``host``:``port``."""

    def __init__(self, host: str, port: int, timeout: float = 5.0, recv_buffer: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if recv_buffer is not None:  # small: a client that stops reading fills it (and the server's side) at once
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, recv_buffer)
        self.sock.settimeout(timeout)
        self.sock.connect((host, port))
        self._buf = b""
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n").encode())
        while b"\r\n\r\n" not in self._buf:
            self._fill()
        head, self._buf = self._buf.split(b"\r\n\r\n", 1)
        if not head.startswith(b"HTTP/1.1 101"):
            raise ConnectionError(f"not a WebSocket upgrade: {head[:80]!r}")
        self.channels: dict[str, int] = {}
        """Topic -> channel id, from the server's advertisements."""
        self.subscriptions: dict[int, str] = {}

    def _fill(self) -> None:
        data = self.sock.recv(65536)
        if not data:
            raise ConnectionError("the server closed the connection")
        self._buf += data

    def _take(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._fill()
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def frame(self) -> tuple[int, bytes]:
        """The next frame from the server: (opcode, payload)."""
        b0, b1 = self._take(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._take(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._take(8))[0]
        mask = self._take(4) if b1 & 0x80 else b""
        data = self._take(n)
        if mask:
            data = bytes(c ^ mask[i % 4] for i, c in enumerate(data))
        return b0 & 0x0F, data

    def send_json(self, obj: Any) -> None:
        """One masked text frame (clients must mask)."""
        data = json.dumps(obj).encode()
        n = len(data)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n))
        mask = os.urandom(4)
        self.sock.sendall(head + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(data)))

    def wait_for_channels(self, topics: set[str], timeout: float = 5.0) -> None:
        """Read until the server has advertised every topic of ``topics``."""
        deadline = time.monotonic() + timeout
        while not topics <= set(self.channels):
            if time.monotonic() > deadline:
                raise TimeoutError(f"advertised {sorted(self.channels)}, not {sorted(topics)}")
            op, data = self.frame()
            if op == 1:
                msg = json.loads(data)
                if msg.get("op") == "advertise":
                    self.channels.update({c["topic"]: int(c["id"]) for c in msg["channels"]})

    def subscribe_all(self) -> None:
        """Subscribe to every advertised channel."""
        subs = []
        for k, (topic, cid) in enumerate(sorted(self.channels.items()), start=1):
            subs.append({"id": k, "channelId": cid})
            self.subscriptions[k] = topic
        self.send_json({"op": "subscribe", "subscriptions": subs})

    def messages(self, count: int, timeout: float = 10.0) -> list[tuple[str, int, bytes]]:
        """Read ``count`` messages: (topic, log time ns, payload)."""
        out: list[tuple[str, int, bytes]] = []
        deadline = time.monotonic() + timeout
        while len(out) < count and time.monotonic() < deadline:
            op, data = self.frame()
            if op == 2 and data and data[0] == 1:
                sub, t_ns = struct.unpack_from("<IQ", data, 1)
                out.append((self.subscriptions.get(sub, "?"), t_ns, data[13:]))
        return out

    def close(self) -> None:
        self.sock.close()
