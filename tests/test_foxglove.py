"""The scope's channels over Foxglove's WebSocket protocol: a client written from the protocol's
specification (``foxglove.websocket.v1``, named ``foxglove.sdk.v1`` by foxglove-sdk 0.30, which
speaks only that name: serverInfo and advertise as JSON text, subscribe,
then binary message data: opcode 0x01, subscription id u32, log time u64, payload) subscribes
to every channel the daemon advertises and decodes at least one message of each."""

from __future__ import annotations

import asyncio
import json
import struct
import time

from harness import free_port
from test_daemon_helpers import ctl, running_daemon, wait_for


def _listening(port: int) -> bool:
    import socket
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


async def _one_message_per_channel(url: str, timeout_s: float) -> tuple[dict, dict]:
    import aiohttp

    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(url, protocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            assert ws.protocol in ("foxglove.sdk.v1", "foxglove.websocket.v1")
            channels, got = {}, {}
            deadline = asyncio.get_running_loop().time() + timeout_s
            while asyncio.get_running_loop().time() < deadline:
                msg = await ws.receive(timeout=timeout_s)
                if msg.type == aiohttp.WSMsgType.TEXT:
                    op = json.loads(msg.data)
                    if op["op"] == "advertise":
                        new = {c["id"]: c for c in op["channels"]}
                        channels.update(new)
                        await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": cid, "channelId": cid} for cid in new]}))
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    data = msg.data
                    if data[0] != 0x01:
                        continue
                    sub, _log_time = struct.unpack_from("<IQ", data, 1)
                    topic = channels[sub]["topic"]
                    got.setdefault(topic, json.loads(data[13:].decode()))
                    if channels and set(got) == {c["topic"] for c in channels.values()}:
                        return channels, got
                else:
                    break
            return channels, got


def test_foxglove_client_decodes_every_channel(tmp_path):
    port = free_port()
    with running_daemon(tmp_path, extra_daemon={"foxglove": {"listen": f"127.0.0.1:{port}"}}) as d:
        for _ in range(5):                  # bounded: a refusal that asks for a retry gets one
            r = ctl(d.sock, "start", "Y")
            if r.returncode == 0 or "retry" not in r.stdout + r.stderr:
                break
            time.sleep(0.2)
        assert r.returncode == 0, r.stdout + r.stderr
        wait_for(lambda: _listening(port), 30, "the view process to serve Foxglove")
        channels, got = asyncio.run(_one_message_per_channel(f"ws://127.0.0.1:{port}/", 20.0))
    topics = {c["topic"] for c in channels.values()}
    assert topics == {"/motorctl/X", "/motorctl/Y", "/motorctl/loop", "/motorctl/status"}
    assert set(got) == topics, set(got)
    for c in channels.values():
        assert c["encoding"] == "json" and json.loads(c["schema"])["type"] == "object"
    assert {"t", "e", "u", "theta_hat1", "e_min", "e_max"} <= set(got["/motorctl/Y"])
    assert "turnaround_us" in got["/motorctl/loop"]
    assert got["/motorctl/status"]["axes"]["Y"]["state"] in ("enabled", "disabled")
