"""The client library's waits (motorctl.client.Client) where no daemon answers: bounded, and a
daemon process that has ended ends the wait at once."""

from __future__ import annotations

import time

import pytest

from motorctl.client import Client, DaemonUnreachable


def test_wait_started_ends_when_the_daemons_process_has_ended(tmp_path):
    c = Client(str(tmp_path / "none.sock"), timeout_s=0.5)
    t0 = time.monotonic()
    with pytest.raises(DaemonUnreachable, match="ended before it started"):
        c.wait_started(60, alive=lambda: False)
    assert time.monotonic() - t0 < 30          # not the 60 s bound: the first try's refusal


def test_wait_started_is_bounded_without_a_daemon(tmp_path):
    c = Client(str(tmp_path / "none.sock"), timeout_s=0.5)
    with pytest.raises(DaemonUnreachable, match="did not start within 0.3 s"):
        c.wait_started(0.3, poll_s=0.05)
