"""Helper processes of the I/O process: the view, metrics and OPC UA processes.

Each is forked by the I/O process before its threads start (:func:`fork_helper`), joined to it
by an ``AF_UNIX``/``SOCK_SEQPACKET`` socket pair of which the I/O process's end never blocks: a
helper that falls behind loses messages (counted), never delays the drain of the run log. The
child closes every descriptor of the I/O process's but its end of the pair (the control socket,
the loop's pipes and the run log stay the I/O process's), runs its ``main`` and exits with its
code; it ends with the I/O process (EOF on the pair, ``PR_SET_PDEATHSIG``:
:func:`motorctl.app.lifetime.die_with_parent`).

:class:`SnapshotLink` is the I/O process's end for a helper fed a snapshot at a fixed period
(metrics, OPC UA): its reports (one line each on stderr), the snapshot sent when due, and the
helper reaped at the end (:func:`reap`).
"""

from __future__ import annotations

import os
import pickle
import signal
import socket
import sys
import time

from motorctl.app.daemon.journal import plain_stderr
from motorctl.app.lifetime import die_with_parent

#: each helper, and the I/O process itself (:func:`own_session`), in a session of its own
#: (``setsid``). With the kernel's autogroup
#: (``CONFIG_SCHED_AUTOGROUP``, ``/proc/sys/kernel/sched_autogroup_enabled``) the scheduler shares
#: the CPUs between sessions first and between a session's processes second: a helper left in
#: the daemon's session shared one group's time with every CPU-bound process started from that
#: session. Beside 4 such processes on 2 cores (and other sessions' work) the view and OPC UA
#: processes waited for a CPU about 30 times as long as they ran (0.93 and 0.88 s per second
#: against 0.03) and answered in up to 6.6 and 10 s; in sessions of their own every page, read
#: and scrape answered within 0.71 s (benchmarks/bench_factory.py, docs/benchmarks.md
#: 2026-11-28). Without autogroup, or under a systemd unit's cgroup (which the scheduler groups
#: by instead), it changes nothing. A helper still ends with the I/O process (EOF on its link,
#: ``PR_SET_PDEATHSIG``) and ignores the signals a process group would get. The I/O process
#: (nice -10, asleep but for short wakes) in the session of whoever started the daemon shared
#: that session's one share with every CPU-bound process started from it: its niceness counts
#: inside the group only, and a group that is always runnable gets no wake-up preference, so
#: beside 4 such processes on 2 cores its wake counter stood up to 0.95 s (the loop latches
#: "recorder stalled" at 2 s; once in nine runs it did). In its own session it wakes as a
#: group of its own; it still ends with the loop process (EOF on the loop's pipe), its
#: planner process follows it into that session.
OWN_SESSION = True


def own_session() -> None:
    """A session (and with autogroup a scheduling group) of the caller's own, when
    :data:`OWN_SESSION`; a refusal (already a session leader) is ignored."""
    if OWN_SESSION:
        try:
            os.setsid()
        except OSError:
            pass


def fork_helper(what: str, main, buffer_bytes: int | None = None) -> tuple[socket.socket, int] | None:
    """Fork a helper that runs ``main(sock, parent_pid)`` (its end of the pair) and exits with
    the code it returns. Returns (the I/O process's end, non-blocking; the helper's pid), or
    None with one warning line on stderr when the pair or the fork fails. ``buffer_bytes``: the
    pair's send and receive buffers (the kernel's default when None)."""
    try:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        if buffer_bytes:
            for s in (mine, theirs):
                try:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, buffer_bytes)
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, buffer_bytes)
                except OSError:
                    pass
        parent = os.getpid()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
    except OSError as exc:
        sys.stderr.write(f"motorctl: warning: the {what} process not started ({exc})\n")
        return None
    if pid == 0:
        code = 1
        try:
            plain_stderr()                    # (the I/O process's journal thread is not forked)
            mine.close()
            keep = theirs.fileno()            # nothing of the I/O process's: socket, pipes, log
            os.closerange(3, keep)
            os.closerange(keep + 1, os.sysconf("SC_OPEN_MAX"))
            code = main(theirs, parent)
        except BaseException as exc:            # noqa: BLE001 - last resort, one line
            try:
                sys.stderr.write(f"motorctl: warning: the {what} process ended: {type(exc).__name__}: {exc}\n")
            except Exception:                  # noqa: BLE001
                pass
        finally:
            os._exit(code)
    theirs.close()
    mine.setblocking(False)
    return mine, pid


def helper_started(parent_pid: int, nice: int) -> None:
    """First thing in a helper: SIGKILL when the I/O process ``parent_pid`` dies, SIGINT and
    SIGHUP ignored (the daemon's own, sent to the process group), SIGTERM ends it, a session of
    its own (:data:`OWN_SESSION`), niceness ``nice`` (kept where it is not permitted)."""
    die_with_parent(parent_pid, signal.SIGKILL)
    for s in (signal.SIGINT, signal.SIGHUP):
        signal.signal(s, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    own_session()
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError:
        pass


def reap(pid: int, timeout_s: float) -> int | None:
    """Wait for the helper ``pid`` to end, SIGKILL after ``timeout_s`` [s]. Returns its wait
    status (None: it had been reaped already)."""
    end = time.monotonic() + timeout_s
    while True:
        try:
            got, st = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return None
        if got:
            return st
        if time.monotonic() > end:
            try:
                os.kill(pid, signal.SIGKILL)
                return os.waitpid(pid, 0)[1]
            except (ProcessLookupError, ChildProcessError):
                return None
        time.sleep(0.01)


class HelperLink:
    """The I/O process's end of a helper process (:func:`fork_helper`'s pair and pid).

    Attributes:
        pid: the helper. sent, dropped: messages handed over / dropped (the helper was behind).
        alive: False once it has ended (nothing is sent any more).
    """

    def __init__(self, sock: socket.socket, pid: int):
        self.sock, self.pid = sock, pid
        self.sent = self.dropped = 0
        self.alive = True

    def stop(self, timeout_s: float = 2.0) -> int | None:
        """Close the link (the helper ends on EOF) and reap it (SIGKILL after the bound). Returns
        its wait status (None: reaped already)."""
        self.alive = False
        try:
            self.sock.close()
        except OSError:
            pass
        return reap(self.pid, timeout_s)


class SnapshotLink(HelperLink):
    """The I/O process's end of a helper fed a snapshot every ``every_s`` [s].

    A subclass gives :meth:`snapshot` (the picklable message) and :meth:`report_line` (the
    stderr line of a report of the helper's: "ok" once it serves, else why it does not).

    Attributes:
        pid: the helper. sent, dropped: snapshots handed over / dropped (the helper was behind).
        alive: False once it has ended. build_s: the last snapshot's build and send time [s].
    """

    def __init__(self, sock: socket.socket, pid: int, every_s: float):
        super().__init__(sock, pid)
        self.every_s = every_s
        self.last = 0.0
        self.placed = False
        self.build_s = 0.0

    def snapshot(self, io, now: float):
        raise NotImplementedError

    def dropped_one(self) -> None:
        """A snapshot could not be sent (the subclass may carry its content in the next)."""

    def report_line(self, text: str) -> str:
        raise NotImplementedError

    def poll(self, io, now: float) -> None:
        """Each wake of the I/O process: the helper's reports, and a snapshot when due. Never
        blocks, never raises (a failure here ends the link, not the drain)."""
        try:
            self._reports()
            if not self.placed and io.ready is not None:
                # the I/O process has left the loop's CPU by now (IOSide.on_reply): follow it
                self.placed = True
                os.sched_setaffinity(self.pid, os.sched_getaffinity(0))
            if self.alive and now - self.last >= self.every_s:
                t0 = time.perf_counter()
                self.last = now
                data = pickle.dumps(self.snapshot(io, now), protocol=pickle.HIGHEST_PROTOCOL)
                try:
                    self.sock.send(data)
                    self.sent += 1
                except (BlockingIOError, InterruptedError):
                    self.dropped += 1
                    self.dropped_one()
                self.build_s = time.perf_counter() - t0
        except Exception:               # noqa: BLE001 - the drain goes on whatever happens here
            self.alive = False

    def _reports(self) -> None:
        while True:
            try:
                data = self.sock.recv(1 << 12)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b""
            if not data:
                self.alive = False
                return
            sys.stderr.write(self.report_line(data.decode(errors="replace")) + "\n")
