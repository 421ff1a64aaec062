"""No process outlives its run: ``kill -9`` of ``motorctl run`` ends its forked drain (which
keeps every row it took), ``kill -9`` of the daemon's loop process ends the I/O process and
the view and planner processes (each in a session of its own: found as the loop process's
descendants); none is left 2 s later."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

from conftest import MOTORCTL, REPO
from harness import free_port
from test_daemon_helpers import Daemon, make_config, wait_for

from motorctl.recorder.runlog import read_log


def _session(sid: int) -> list[int]:
    """Live (not zombie) processes of session ``sid``."""
    out = []
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            fields = (p / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[3]) == sid:
            out.append(int(p.name))
    return out


def _stat(pid: int) -> tuple[str, int, int] | None:
    """(state, parent pid, start time [clock ticks]) of a process, None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return fields[0], int(fields[1]), int(fields[19])


def _descendants(root: int) -> set[tuple[int, int]]:
    """Live (not zombie) descendants of ``root`` as (pid, start time): the daemon's helpers
    each run in a session of their own, so the session alone no longer finds them."""
    kids: dict[int, list[int]] = {}
    for p in Path("/proc").iterdir():
        if p.name.isdigit() and (st := _stat(int(p.name))) is not None and st[0] != "Z":
            kids.setdefault(st[1], []).append(int(p.name))
    out, todo = set(), [root]
    while todo:
        for c in kids.get(todo.pop(), []):
            if (st := _stat(c)) is not None:
                out.add((c, st[2]))
                todo.append(c)
    return out


def _alive(procs: set[tuple[int, int]]) -> list[int]:
    """The pids of ``procs`` still running (the same start time: not a reused pid; not a zombie)."""
    return [pid for pid, start in procs if (st := _stat(pid)) is not None and st[0] != "Z" and st[2] == start]


def test_kill_9_of_run_leaves_no_drain_and_a_readable_log(tmp_path):
    log = tmp_path / "run.mclog"
    proc = subprocess.Popen([*MOTORCTL, "run", str(REPO / "configs" / "gantry-rigid.yaml"),
                             "--duration", "120", "--realtime", "off", "--log", str(log)],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        wait_for(lambda: log.exists() and log.stat().st_size > 1 << 20, 300,
                 "the run's drain to write 1 MB", interval=0.1)
        assert len(_session(proc.pid)) == 2           # the loop process and its drain
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        wait_for(lambda: not _session(proc.pid), 2.0, "the drain to end")
    finally:
        for pid in _session(proc.pid):
            os.kill(pid, signal.SIGKILL)
        proc.stderr.close()
    rows = read_log(str(log)).data.shape[0]
    assert rows * 8 * 40 > 1 << 20 - 1, rows          # what the drain took stays readable


def test_kill_9_of_the_daemon_ends_its_io_and_view_processes(tmp_path):
    port = free_port()
    cfg = make_config(tmp_path, extra_daemon={"scope": {"listen": f"127.0.0.1:{port}"}})
    d = Daemon(cfg, tmp_path / "motorctl.sock", preexec=os.setsid)
    family: set[tuple[int, int]] = set()
    try:
        d.wait_ready()
        family = wait_for(lambda: len(f := _descendants(d.proc.pid)) == 3 and f, 30,
                          "the I/O, view and planner processes under the loop process",
                          detail=lambda: _descendants(d.proc.pid))
        # none shares the loop's session (the kernel's autogroup: a CPU share of its own each)
        assert all(os.getsid(pid) != os.getsid(d.proc.pid) for pid, _ in family), family
        os.kill(d.proc.pid, signal.SIGKILL)
        d.proc.wait(10)
        wait_for(lambda: not _alive(family), 2.0, "the I/O, view and planner processes to end",
                 detail=lambda: _alive(family))
    finally:
        for pid in _session(d.proc.pid) + _alive(family):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        d.kill()
