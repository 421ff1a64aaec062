"""The scope's channels over Foxglove's WebSocket protocol (``foxglove.websocket.v1``; the
subprotocol foxglove-sdk 0.30 negotiates is ``foxglove.sdk.v1``), with the ``foxglove-sdk`` library, from the daemon's view process
(:mod:`motorctl.app.daemon.views`): the Foxglove app connects live (a client that asks only for
``foxglove.websocket.v1`` is refused by the SDK with HTTP 400).

Topics (JSON encoding, each with a JSON schema): ``/motorctl/<AXIS>`` per axis (t [s] and, per
channel of :data:`motorctl.app.daemon.scope.AXIS_CHANNELS`, the mid-range of its envelope over
:data:`STEP_S`, with e's and u's min and max), ``/motorctl/loop`` (turnaround and lateness [µs])
and ``/motorctl/status`` (each axis's state, phase, controller and latched fault, at every
status refresh). The SDK keeps at most :data:`BACKLOG` messages per client: a slow client
drops its oldest messages; the drainer never waits (it runs in another process).
"""

from __future__ import annotations

import math

from motorctl.app.daemon.scope import AXIS_CHANNELS, CYCLE_CHANNELS
from motorctl.config import parse_listen
from motorctl.loop.records import AXIS_FIELDS

STEP_S = 0.01        #: one message per axis per this much loop time [s] (100 per second)
BACKLOG = 2048       #: messages buffered per client


def _schema(title: str, props: dict) -> dict:
    return {"title": title, "type": "object", "properties": props}


class FoxglovePublisher:
    """Publish the frames of a :class:`motorctl.app.daemon.scope.Scope` (a listener of it).

    Args:
        listen: "host:port". scope: the frame source (its ``bucket_s`` sets the stride).
    Raises (from :meth:`start`): OSError when the address cannot be bound; ImportError when
        foxglove-sdk is missing (the ``foxglove`` extra).
    """

    def __init__(self, listen: str, scope):
        self.host, self.port = parse_listen(listen)
        self.scope = scope
        self.stride = max(1, int(round(STEP_S / (scope.bucket * scope.period_s))))
        self.server = None
        self.channels: dict = {}
        self.error = ""
        self.published = 0

    def start(self) -> None:
        import foxglove

        self.server = foxglove.start_server(name="motorctl", host=self.host, port=self.port,
                                            message_backlog_size=BACKLOG)
        num = {"type": "number"}
        for name in self.scope.names:
            props = {"t": num}
            for f in AXIS_CHANNELS:
                props[f] = {"type": ["number", "null"], "description": AXIS_FIELDS[f]}
            for f in ("e", "u"):
                props[f + "_min"] = props[f + "_max"] = {"type": ["number", "null"]}
            self.channels[name] = foxglove.Channel(f"/motorctl/{name}", schema=_schema(f"motorctl axis {name}", props))
        self.channels["loop"] = foxglove.Channel(
            "/motorctl/loop", schema=_schema("motorctl loop", {"t": num, **{lab: {"type": ["number", "null"]}
                                                                            for lab, _ in CYCLE_CHANNELS.values()}}))
        self.channels["status"] = foxglove.Channel("/motorctl/status", schema=_schema(
            "motorctl status", {"axes": {"type": "object"}}))

    def on_frame(self, frame: dict) -> None:
        """Listener of the scope (I/O thread): every ``stride``-th bucket as one message per
        topic. Never raises."""
        try:
            self._publish(frame)
        except Exception as exc:       # noqa: BLE001 - the live view is best effort
            self.error = f"{type(exc).__name__}: {exc}"

    def _publish(self, frame: dict) -> None:
        lo, hi, t = frame["min"], frame["max"], frame["t"]
        for j in range(0, len(t), self.stride):
            ns = int(round(t[j] * 1e9))
            for name in self.scope.names:
                msg = {"t": t[j]}
                for f in AXIS_CHANNELS:
                    a, b = lo[f"{name}.{f}"][j], hi[f"{name}.{f}"][j]
                    msg[f] = None if a is None or b is None else 0.5 * (a + b)
                for f in ("e", "u"):
                    msg[f + "_min"], msg[f + "_max"] = lo[f"{name}.{f}"][j], hi[f"{name}.{f}"][j]
                self.channels[name].log(msg, log_time=ns)
            self.channels["loop"].log({"t": t[j], **{lab: hi[lab][j] for lab, _ in CYCLE_CHANNELS.values()}},
                                      log_time=ns)
            self.published += 1

    def publish_status(self, status: dict, t_s: float) -> None:
        try:
            self.channels["status"].log(status, log_time=int(round(t_s * 1e9)) if math.isfinite(t_s) else None)
        except Exception as exc:       # noqa: BLE001
            self.error = f"{type(exc).__name__}: {exc}"

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None
