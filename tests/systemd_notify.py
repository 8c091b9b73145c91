"""systemd's end of NOTIFY_SOCKET for tests of the daemon's sd_notify messages."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path


class NotifySocket:
    """systemd's end of NOTIFY_SOCKET: every datagram, split into its KEY=VALUE lines and
    stamped with the time it was read, collected by a reader thread (a real service
    manager always reads; an unread socket fills after ~10 datagrams)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.settimeout(0.05)
        self.messages: list[tuple[float, list[str]]] = []
        self._changed = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._closing:
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            with self._changed:
                self.messages.append((time.monotonic(), data.decode().split("\n")))
                self._changed.notify_all()

    def wait_for(self, field: str, timeout: float, after: int = 0) -> int:
        """Index of the first message from `after` on that carries `field`."""
        end = time.monotonic() + timeout
        with self._changed:
            while True:
                for i, (_, fields) in enumerate(self.messages[after:], start=after):
                    if field in fields:
                        return i
                left = end - time.monotonic()
                assert left > 0, f"no {field} within {timeout} s: {self.messages}"
                self._changed.wait(left)

    def snapshot(self) -> list[tuple[float, list[str]]]:
        with self._changed:
            return list(self.messages)

    def close(self) -> None:
        self._closing = True
        self._thread.join(5)
        self._sock.close()
