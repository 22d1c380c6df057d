"""Screenshots of a web page in headless Chromium, through the DevTools protocol (standard library only).

WebGL runs on SwiftShader (the CPU), so pages that draw with it render without a GPU."""
from __future__ import annotations

import base64
import contextlib
import json
import os
import socket
import struct
import subprocess
import tempfile
import time
import urllib.request

FLAGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--mute-audio",
         "--window-size=1280,800"]


class _WebSocket:
    """A client text websocket (RFC 6455), enough for the DevTools protocol."""

    def __init__(self, url: str):
        address, path = url.removeprefix("ws://").split("/", 1)
        host, port = address.split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=60)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(f"GET /{path} HTTP/1.1\r\nHost: {address}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                          f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
        self.buffer = b""
        while b"\r\n\r\n" not in self.buffer:
            self.buffer += self._recv()
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        if b" 101 " not in head.split(b"\r\n")[0]:
            raise ConnectionError(f"websocket handshake refused: {head[:200]!r}")

    def _recv(self) -> bytes:
        chunk = self.sock.recv(1 << 20)
        if not chunk:
            raise ConnectionError("the browser closed the connection")
        return chunk

    def _read(self, n: int) -> bytes:
        while len(self.buffer) < n:
            self.buffer += self._recv()
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def send(self, text: str) -> None:
        data, mask = text.encode(), os.urandom(4)
        n = len(data)
        length = bytes([0x80 | n]) if n < 126 else (bytes([0xFE]) + struct.pack(">H", n) if n < 1 << 16
                                                    else bytes([0xFF]) + struct.pack(">Q", n))
        self.sock.sendall(bytes([0x81]) + length + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def receive(self) -> str:
        message = b""
        while True:
            first, second = self._read(2)
            n = second & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            message += self._read(n)
            if first & 0x80:  # the final fragment
                return message.decode()


class Page:
    """One browser tab: :meth:`open` a URL, :meth:`screenshot` it (PNG bytes)."""

    def __init__(self, websocket_url: str):
        self.ws = _WebSocket(websocket_url)
        self._id = 0

    def call(self, method: str, until: str | None = None, **params) -> dict:
        """The answer to ``method``, after the event ``until`` too when given (other events are passed over)."""
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        result, waiting = None, until
        while result is None or waiting:
            message = json.loads(self.ws.receive())
            if message.get("id") == self._id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                result = message["result"]
            elif message.get("method") == waiting:
                waiting = None
        return result

    def open(self, url: str) -> None:
        """Navigate to ``url`` and wait for its load event."""
        self.call("Page.enable")
        self.call("Page.navigate", until="Page.loadEventFired", url=url)

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])


@contextlib.contextmanager
def headless_page(executable: str, port: int, start_timeout: float = 30.0):
    """A :class:`Page` of a headless ``executable`` (chromium) debugged on ``port``; the browser ends after."""
    with tempfile.TemporaryDirectory() as profile:
        browser = subprocess.Popen([executable, *FLAGS, f"--remote-debugging-port={port}",
                                    f"--user-data-dir={profile}", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            end = time.monotonic() + start_timeout
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json") as answer:
                        targets = json.load(answer)
                    break
                except OSError:
                    if time.monotonic() > end or browser.poll() is not None:
                        raise RuntimeError(f"{executable} did not open its debugging port {port}") from None
                    time.sleep(0.2)
            yield Page(next(t for t in targets if t["type"] == "page")["webSocketDebuggerUrl"])
        finally:
            browser.terminate()
            browser.wait(timeout=30)
