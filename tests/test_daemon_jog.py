"""The operator's recovery path on the real daemon: an axis pushed outside its soft limits is
jogged back inside (``motorctl jog``) without a restart; then ``start`` works again."""

from __future__ import annotations

from test_daemon_helpers import ctl, running_daemon, status, wait_for


def test_jog_recovers_an_axis_outside_its_soft_limits(tmp_path):
    with running_daemon(tmp_path, fault_axis=True) as d:
        sock = d.sock
        x = lambda: status(sock)["axes"]["X"]  # noqa: E731
        assert ctl(sock, "start", "X").returncode == 0
        wait_for(lambda: x()["phase"] == "tracking", 20, "X tracking")
        assert ctl(sock, "inject", "X", "push", "--force-n", "-2000", "--cycles", "30").returncode == 0
        st = wait_for(lambda: (s := x())["state"] == "fault" and s, 20, "the soft-limit fault")
        assert "soft limit" in st["fault"]
        c0 = status(sock)["loop"]["cycles"]
        wait_for(lambda: status(sock)["loop"]["cycles"] > c0 + 5000, 30, "X to coast to rest")
        assert x()["y_m"] < -0.0005
        r = ctl(sock, "fault-reset", "X")
        assert r.returncode == 1 and "outside the soft limits" in r.stderr
        r = ctl(sock, "jog", "X", "-0.01")                  # a target outside: refused
        assert r.returncode == 1 and "outside the soft limits" in r.stderr, r.stderr
        r = ctl(sock, "jog", "X", "0.0", "--speed", "0.2")
        assert r.returncode == 0, r.stderr
        assert "recovering" in r.stdout and "0 V, amplifier off" in r.stdout, r.stdout
        st = x()
        assert st["state"] == "disabled" and st["fault"] == "" and abs(st["y_m"]) < 1e-4, st
        assert ctl(sock, "start", "X").returncode == 0
        wait_for(lambda: x()["phase"] == "tracking", 20, "X tracking again")
        assert x()["state"] == "enabled"
        code, _, _ = d.terminate()
        assert code == 0
