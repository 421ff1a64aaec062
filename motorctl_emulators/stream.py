"""The device end of a byte stream, for the emulated serial and Modbus devices."""

from __future__ import annotations

import os
import select
import socket
import tty


class StreamEndpoint:
    """Where a serial or Modbus driver's link ends on the device side.

    ``url``: ``socket://HOST:PORT`` or ``tcp://HOST:PORT`` (listen on HOST:PORT, one client at a
    time; a new client replaces the old one), or a filesystem path (make a pty pair, raw mode,
    and symlink PATH to its slave device, the way socat's ``link=`` does).

    Raises:
        OSError: the port is taken, or the pty or the link cannot be made.
    """

    def __init__(self, url: str):
        self.url = url
        self.client = None
        self.listener = None
        self.master = None
        self._link = None
        if url.startswith(("socket://", "tcp://")):
            hostport = url.split("://", 1)[1]
            host, _, port = hostport.rpartition(":")
            self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.listener.bind((host or "127.0.0.1", int(port)))
            self.listener.listen(1)
        else:
            self.master, self._slave = os.openpty()
            tty.setraw(self._slave)
            tty.setraw(self.master)
            name = os.ttyname(self._slave)
            if os.path.lexists(url):
                os.unlink(url)
            os.symlink(name, url)
            self._link = url

    def wait(self, timeout_s: float) -> bytes | None:
        """Wait up to ``timeout_s`` [s] for bytes; accept a new client on the way. None: nothing."""
        fds = [f for f in (self.listener, self.client, self.master) if f is not None]
        r, _, _ = select.select(fds, [], [], max(timeout_s, 0.0))
        if not r:
            return None
        if self.listener is not None and self.listener in r:
            conn, _ = self.listener.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.client is not None:
                self.client.close()
            self.client = conn
            return None
        if self.master is not None:
            try:
                return os.read(self.master, 4096)
            except OSError:
                return None
        try:
            data = self.client.recv(4096)
        except OSError:
            data = b""
        if not data:
            self.client.close()
            self.client = None
            return None
        return data

    def send(self, data: bytes) -> None:
        """Send ``data`` to the driver (dropped when no client is connected)."""
        if self.master is not None:
            os.write(self.master, data)
        elif self.client is not None:
            try:
                self.client.sendall(data)
            except OSError:
                self.client.close()
                self.client = None

    def disconnect(self) -> None:
        """Drop the link: close the client connection (a pty cannot be unplugged: no-op)."""
        if self.client is not None:
            self.client.close()
            self.client = None

    def close(self) -> None:
        """Close everything and remove the pty link."""
        for s in (self.client, self.listener):
            if s is not None:
                s.close()
        self.client = self.listener = None
        if self.master is not None:
            os.close(self.master)
            os.close(self._slave)
            self.master = None
        if self._link and os.path.islink(self._link):
            os.unlink(self._link)
