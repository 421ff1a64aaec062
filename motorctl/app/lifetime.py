"""Child processes that end with their parent: a forked helper (the run's drain, the daemon's
I/O and view processes) asks the kernel for SIGKILL/SIGTERM when its parent dies
(``prctl(PR_SET_PDEATHSIG)``, Linux prctl(2)), so a ``kill -9`` of the parent leaves no orphan
holding the run log open."""

from __future__ import annotations

import ctypes
import os
import signal

PR_SET_PDEATHSIG = 1      #: linux/prctl.h


def die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> bool:
    """Ask for ``sig`` when the parent dies; when it is already gone (it died before the call),
    raise ``sig`` now. Returns False where prctl is unavailable (the caller then relies on its
    own ``os.getppid()`` check)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        ok = libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        ok = False
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), sig)
    return ok


def parent_gone(parent_pid: int) -> bool:
    """True once the process that forked this one has ended (re-parented)."""
    return os.getppid() != parent_pid
