"""Length-prefixed pickled messages over a pipe: the wire format between the daemon's processes
(the loop, the I/O process, the planner process; :mod:`motorctl.app.daemon.protocol` names it
beside the socket's). Standard library only, so that a helper process can import it without the
daemon's modules."""

from __future__ import annotations

import os
import pickle
import struct

_HDR = struct.Struct("<I")


class Mailbox:
    """Length-prefixed pickled messages over a pipe; the read side is non-blocking."""

    def __init__(self, rfd: int | None = None, wfd: int | None = None):
        self.rfd, self.wfd = rfd, wfd
        self._buf = b""
        if rfd is not None:
            os.set_blocking(rfd, False)

    def send(self, obj) -> None:
        data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        os.write(self.wfd, _HDR.pack(len(data)) + data)

    def recv(self) -> list | None:
        """Messages available now ([] if none); None when the writer has closed the pipe."""
        eof = False
        while True:
            try:
                chunk = os.read(self.rfd, 65536)
            except BlockingIOError:
                break
            if not chunk:
                eof = True
                break
            self._buf += chunk
        out = []
        while len(self._buf) >= 4:
            (n,) = _HDR.unpack_from(self._buf)
            if len(self._buf) < 4 + n:
                break
            out.append(pickle.loads(self._buf[4:4 + n]))
            self._buf = self._buf[4 + n:]
        if eof and not out:
            return None
        return out
