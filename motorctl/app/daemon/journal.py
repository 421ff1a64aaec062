"""The I/O process's journal: its lines on stderr (under the systemd unit, the journal) written by
a thread of their own, so that the I/O process's main thread, which drains the run log and answers
the control socket, never waits for whoever reads them.

A write to stderr blocks once the reader falls behind by a pipe's buffer (64 KiB on Linux): a
journald that stalls, or a parent that never reads the pipe. The I/O process wrote one line per
fault onset from its main thread; a long run of faults with nobody reading (the state machine's
soak, after 29 minutes) filled the pipe, the next line blocked the main thread for good, the run
log stopped at that fault and the socket went unanswered. Here a write only queues the line
(:meth:`Journal.write`, never blocking); the writer thread passes the lines on, and while it is
held up at most :data:`MAX_LINES` wait: the ones beyond are dropped, counted
(:attr:`Journal.dropped`, ``status`` ``log.journal_dropped``) and said in one line once the reader
takes lines again.
"""

from __future__ import annotations

import collections
import io
import sys
import threading
import time

#: lines that may wait for a held-up reader before further ones are dropped
MAX_LINES = 1000


class Journal(io.TextIOBase):
    """A text stream whose :meth:`write` queues and returns at once; a daemon thread writes the
    queued text to ``real`` (a text stream: the process's stderr) and flushes it.

    Args:
        real: where the lines go.
        max_lines: writes that may wait (:data:`MAX_LINES`); further ones are dropped and counted.

    Attributes:
        dropped: writes dropped since the start because ``max_lines`` were waiting.
    """

    def __init__(self, real, max_lines: int = MAX_LINES):
        super().__init__()
        self.real = real
        self.max_lines = int(max_lines)
        self.dropped = 0
        self._said = 0                       # the dropped writes already said
        self._q: collections.deque = collections.deque()
        self._busy = False                   # the writer holds lines it has not written yet
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="motorctl-journal", daemon=True)
        self._thread.start()

    def writable(self) -> bool:
        return True

    def write(self, s: str) -> int:
        """Queue ``s`` (dropped and counted when ``max_lines`` writes wait). Never blocks on the
        reader; returns len(s)."""
        with self._cv:
            if len(self._q) >= self.max_lines:
                self.dropped += 1
            else:
                self._q.append(s)
                self._cv.notify()
        return len(s)

    def flush(self) -> None:
        """Nothing to do here: the writer thread flushes what it writes."""

    def fileno(self) -> int:
        return self.real.fileno()

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._q:
                    self._busy = False
                    self._cv.notify_all()
                    self._cv.wait()
                text = "".join(self._q)
                self._q.clear()
                self._busy = True
                if self.dropped > self._said:
                    text += (f"motorctl daemon: {self.dropped - self._said} journal lines dropped "
                             f"(the journal's reader fell behind)\n")
                    self._said = self.dropped
            try:
                self.real.write(text)
                self.real.flush()
            except Exception:                 # noqa: BLE001 - a closed or broken stderr: nothing to tell
                pass

    def drain(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` [s] until every queued line is written (before the process
        ends: ``os._exit`` keeps no thread). True when they were."""
        end = time.monotonic() + timeout_s
        with self._cv:
            while self._q or self._busy:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True


def install(max_lines: int = MAX_LINES) -> Journal:
    """``sys.stderr`` replaced by a :class:`Journal` over it (the I/O process, at its start).
    Returns it."""
    journal = Journal(sys.stderr, max_lines)
    sys.stderr = journal
    return journal


def plain_stderr() -> None:
    """In a process forked from one with a :class:`Journal` (a helper: the writer thread is not
    forked with it): ``sys.stderr`` a stream of its own on descriptor 2 again, line-buffered."""
    if isinstance(sys.stderr, Journal):
        sys.stderr = open(2, "w", buffering=1, closefd=False, errors="backslashreplace")


__all__ = ["Journal", "MAX_LINES", "install", "plain_stderr"]
