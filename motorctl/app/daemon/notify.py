"""systemd's notify protocol (sd_notify(3)) and its watchdog settings."""

from __future__ import annotations

import os
import socket


def sd_notify(message: str) -> bool:
    """Send one datagram to ``$NOTIFY_SOCKET``; False when not under systemd.

    ``message`` is e.g. "READY=1", "STATUS=...", "WATCHDOG=1", "STOPPING=1". An address
    starting with '@' is in the abstract namespace.
    """
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr[0] == "@":
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(message.encode())
        return True
    except OSError:
        return False


def watchdog_ping_interval_s(parent_pid: int) -> float:
    """Half of systemd's ``WATCHDOG_USEC`` [s] (the interval to ping at), 0 when no watchdog
    is set or it is meant for another process (``WATCHDOG_PID`` is not ours or our parent)."""
    wd = int(os.environ.get("WATCHDOG_USEC", "0") or 0)
    wpid = os.environ.get("WATCHDOG_PID")
    if wpid and wpid.isdigit() and int(wpid) != parent_pid:
        wd = 0
    return wd / 2e6 if wd else 0.0
