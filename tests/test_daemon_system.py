"""The daemon as a system service: systemd unit files, the sd_notify protocol (READY, STATUS,
WATCHDOG only while the loop's heartbeat advances, STOPPING), socket permissions, and
``realtime: required`` refusing to start."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import time

import pytest
from conftest import MOTORCTL, console_script
from test_daemon_helpers import REPO, Daemon, ctl, make_config, status, wait_for

SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
SETPRIV = shutil.which("setpriv")


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed")
@pytest.mark.parametrize("unit,instance", [("motorctl.service", "motorctl.service"),
                                           ("motorctl@.service", "motorctl@xy.service")])
def test_unit_files_verify_clean(tmp_path, unit, instance):
    exe = str(console_script())   # the script beside this interpreter, never PATH
    text = (REPO / "systemd" / unit).read_text()
    for key in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "CPUSchedulingPolicy=fifo",
                "LimitRTPRIO=", "LimitMEMLOCK=infinity", "RuntimeDirectory=", "NotifyAccess=all",
                "KillMode=mixed"):
        assert key in text, key
    assert "Restart=always" not in text
    # ExecStart rewritten to the console script under test (verify checks that it exists)
    text, n = re.subn(r"^(ExecStart(?:Pre)?)=\S+", rf"\1={exe}", text, flags=re.M)
    assert n == 2, "one ExecStart line, one ExecStartPre (motorctl warmup)"
    (tmp_path / unit).write_text(text)
    if instance != unit:
        (tmp_path / instance).write_text(text)
    r = subprocess.run([SYSTEMD_ANALYZE, "verify", str(tmp_path / instance)],
                       capture_output=True, text=True, timeout=60)
    ours = [ln for ln in (r.stdout + r.stderr).splitlines() if str(tmp_path) in ln]
    assert r.returncode == 0 and not ours, r.stdout + r.stderr


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed")
@pytest.mark.parametrize("unit,instance", [("motorctl.service", "motorctl.service"),
                                           ("motorctl@.service", "motorctl@xy.service")])
def test_units_are_sandboxed(tmp_path, unit, instance):
    """systemd's own exposure scale: 3.0 or lower, with what the loop needs kept open."""
    exe = str(console_script())
    text = re.sub(r"^(ExecStart(?:Pre)?)=\S+", rf"\1={exe}", (REPO / "systemd" / unit).read_text(),
                  flags=re.M)
    for key in ("RestrictRealtime=no", "LimitMEMLOCK=infinity", "AF_UNIX", "AF_CAN", "AF_INET",
                "LimitNOFILE=", "NoNewPrivileges=yes", "ProtectSystem=strict",
                "MOTORCTL_CACHE_DIR=", "CacheDirectory="):
        assert key in text, key
    (tmp_path / instance).write_text(text)
    r = subprocess.run([SYSTEMD_ANALYZE, "security", "--offline=true", str(tmp_path / instance)],
                       capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", r.stdout + r.stderr)
    assert m, r.stdout + r.stderr
    assert float(m.group(1)) <= 3.0, r.stdout


class _NotifySocket:
    def __init__(self, path):
        self.path = str(path)
        self.s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.s.bind(self.path)
        self.s.setblocking(False)
        self.msgs: list[tuple[float, str]] = []

    def drain(self):
        while True:
            try:
                self.msgs.append((time.monotonic(), self.s.recv(4096).decode()))
            except BlockingIOError:
                return self.msgs

    def has(self, text, since=0.0):
        return self.count(text, since) > 0

    def count(self, text, since=0.0):
        """How many messages holding ``text`` were drained at or after ``since`` (this
        process's receive, not the daemon's send)."""
        return sum(text in m for t, m in self.drain() if t >= since)


def test_sd_notify_ready_status_watchdog_only_while_the_loop_runs_and_stopping(tmp_path):
    ns = _NotifySocket(tmp_path / "notify.sock")
    env = dict(os.environ, NOTIFY_SOCKET=ns.path, WATCHDOG_USEC="200000")
    cfg = make_config(tmp_path)
    d = Daemon(cfg, tmp_path / "motorctl.sock", env=env)
    try:
        d.wait_ready()
        wait_for(lambda: ns.has("READY=1"), 10, "READY=1")
        wait_for(lambda: ns.has("WATCHDOG=1"), 10, "WATCHDOG=1")
        wait_for(lambda: ns.has("STATUS=X disabled; Y disabled"), 10, "STATUS=")
        # stall the loop process (the heartbeat stops): the pings must stop. Counted, no sleep
        # as a fence: what was sent before the stop is drained at once (a datagram is in the
        # socket when sent); after that at most 2 can come, one decided from the heartbeat's last
        # advance, one more if the stop took hold after the drain; a loop still beating gives 13
        # in the 1.3 s (one each 0.1 s), a starved I/O process fewer, never more
        os.kill(d.proc.pid, signal.SIGSTOP)
        try:
            ns.drain()
            t_stall = time.monotonic()
            time.sleep(1.3)                      # 13 watchdog half-periods
            n = ns.count("WATCHDOG=1", since=t_stall)
            assert n <= 2, f"{n} pings while the loop was stalled"
        finally:
            os.kill(d.proc.pid, signal.SIGCONT)
        t_cont = time.monotonic()
        wait_for(lambda: ns.has("WATCHDOG=1", since=t_cont), 10, "WATCHDOG=1 after resume")
        code, _, err = d.terminate()
        assert code == 0, err
        assert ns.has("STOPPING=1")
    finally:
        d.kill()


def _drop(*caps):
    """setpriv prefix: run as root without these capabilities (root keeps its uid)."""
    spec = ",".join(f"-{c}" for c in caps)
    return [SETPRIV, "--bounding-set", spec, "--inh-caps", spec, "--"]


@pytest.mark.skipif(SETPRIV is None, reason="setpriv not installed")
def test_realtime_required_refuses_to_start_when_fifo_is_refused(tmp_path):
    cfg = make_config(tmp_path, policy="required")
    r = subprocess.run(_drop("sys_nice", "ipc_lock") + [*MOTORCTL, "daemon", str(cfg)], capture_output=True, text=True, timeout=60, cwd=str(REPO))
    assert r.returncode == 1, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "realtime: required" in lines[0] and "sched_fifo" in lines[0]
    assert not (tmp_path / "motorctl.sock").exists()


@pytest.mark.skipif(SETPRIV is None, reason="setpriv not installed")
def test_socket_permissions(tmp_path):
    main = list(MOTORCTL)
    # the daemon cannot create its socket in a directory it may not write to
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    cfg = make_config(tmp_path)
    r = subprocess.run(_drop("dac_override", "dac_read_search") + main + [
        "daemon", str(cfg), "--socket", str(locked / "m.sock")],
        capture_output=True, text=True, timeout=60, cwd=str(REPO))
    assert r.returncode == 1 and r.stderr.count("\n") == 1, r.stderr
    assert "Permission denied" in r.stderr and str(locked / "m.sock") in r.stderr
    # a client outside the socket's group gets a clear "permission denied"
    d = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        d.wait_ready()
        st = os.stat(d.sock)
        assert st.st_mode & 0o777 == 0o660
        os.chown(d.sock, 65534, 65534)           # owned by nobody:nogroup, mode 0660
        r = subprocess.run(_drop("dac_override", "dac_read_search") + main + [
            "--socket", str(d.sock), "start", "X"], capture_output=True, text=True, timeout=60,
            cwd=str(REPO))
        assert r.returncode == 1 and "permission denied" in r.stderr and r.stderr.count("\n") == 1
        assert status(d.sock)["axes"]["X"]["state"] == "disabled", "nothing moved"
        # a second daemon on the same socket is refused (checked before anything starts)
        os.chown(d.sock, 0, 0)
        r2 = ctl(None, "daemon", cfg, "--socket", d.sock)
        assert r2.returncode == 1 and "already serving" in r2.stderr and r2.stderr.count("\n") == 1
        assert status(d.sock)["loop"]["cycles"] > 0
    finally:
        d.kill()


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed")
def test_the_ethercat_drop_in_grants_raw_frames_and_nothing_else(tmp_path):
    """systemd/ethercat.conf, merged into the unit as systemd merges a drop-in: CAP_NET_RAW,
    CAP_NET_ADMIN (SOEM sets the NIC promiscuous) and AF_PACKET are what SOEM needs
    (tests/test_ethercat.py runs it as nobody with exactly these); the exposure stays at 3.0 or
    lower."""
    drop = (REPO / "systemd" / "ethercat.conf").read_text()
    keys = [ln for ln in drop.splitlines() if ln and not ln.startswith("#")]
    assert keys == ["[Service]", "CapabilityBoundingSet=CAP_NET_RAW CAP_NET_ADMIN",
                    "AmbientCapabilities=CAP_NET_RAW CAP_NET_ADMIN", "RestrictAddressFamilies=AF_PACKET"]
    text = re.sub(r"^(ExecStart(?:Pre)?)=\S+", rf"\1={console_script()}", (REPO / "systemd" / "motorctl.service").read_text(),
                  flags=re.M)
    merged = text.replace("[Install]", "\n".join(keys[1:]) + "\n\n[Install]")
    (tmp_path / "motorctl.service").write_text(merged)
    r = subprocess.run([SYSTEMD_ANALYZE, "security", "--offline=true", str(tmp_path / "motorctl.service")],
                       capture_output=True, text=True, timeout=60)
    out = r.stdout + r.stderr
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", out)
    assert m and float(m.group(1)) <= 3.0, out
    assert "AF_PACKET" in out


def _cpus_allowed(pid: int) -> set[int]:
    """The CPUs ``pid`` may run on (/proc/PID/status Cpus_allowed_list)."""
    text = open(f"/proc/{pid}/status").read()
    spec = re.search(r"^Cpus_allowed_list:\s*(\S+)", text, re.M).group(1)
    out = set()
    for part in spec.split(","):
        lo, _, hi = part.partition("-")
        out |= set(range(int(lo), int(hi or lo) + 1))
    return out


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: nothing to keep off the loop's")
def test_a_pinned_loop_keeps_the_io_process_and_the_planner_off_its_cpu(tmp_path):
    """``loop.realtime.cpu``: the loop process runs there alone; the I/O process, and the planner
    it forks, may run on every other CPU and never on the loop's."""
    import yaml
    cpu = max(os.sched_getaffinity(0))
    cfg = make_config(tmp_path, policy="best_effort")
    d = yaml.safe_load(cfg.read_text())
    d["loop"]["realtime"]["cpu"] = cpu
    cfg.write_text(yaml.safe_dump(d))
    dm = Daemon(cfg, tmp_path / "motorctl.sock")
    try:
        dm.wait_ready()
        st = wait_for(lambda: (s := status(dm.sock))["realtime_summary"] != "pending" and s["process"]["planner_pid"]
                      and s, 30, "the loop's real-time set-up and the planner")
        pr = st["process"]
        assert _cpus_allowed(pr["loop_pid"]) == {cpu}, st["realtime"]
        for who in ("io_pid", "planner_pid"):
            allowed = _cpus_allowed(pr[who])
            assert allowed and cpu not in allowed, (who, allowed)
    finally:
        dm.kill()
