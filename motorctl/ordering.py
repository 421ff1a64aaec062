"""Explicit memory ordering for the shared ring: a release store of the heartbeat after the
rows it covers, an acquire load of it before the rows are read.

Two processes share the ring (the loop writes rows, then the heartbeat; the I/O process reads
the heartbeat, then the rows). On x86-64 the hardware keeps stores in order (total store
order), but on weakly ordered CPUs (ARMv8, POWER, RISC-V) a reader could see the new heartbeat
before the rows it covers. :func:`store_release` and :func:`load_acquire` put a full fence
(LLVM ``fence seq_cst``; ``dmb ish`` on ARMv8, ``mfence``-free ``lock``-prefixed ordering on
x86) between the two, compiled by numba (C11 ``atomic_thread_fence`` semantics).

With ``NUMBA_DISABLE_JIT=1`` (plain-Python debugging) the fence cannot be emitted and the
functions are plain stores and loads: correct on x86-64 only.
"""

from __future__ import annotations

import numpy as np
from numba import config as _numba_config
from numba import types
from numba.extending import intrinsic

from motorctl.jit import njit

FENCED = not _numba_config.DISABLE_JIT

if FENCED:
    @intrinsic
    def _fence(typingctx):
        def codegen(context, builder, signature, args):
            builder.fence("seq_cst")
            return context.get_dummy_value()
        return types.void(), codegen

    @njit
    def store_release(arr, idx, value):
        """Fence, then ``arr[idx] = value`` (every earlier store is visible first)."""
        _fence()
        arr[idx] = value

    @njit
    def load_acquire(arr, idx):
        """``arr[idx]``, then a fence (no later load is served before it)."""
        v = arr[idx]
        _fence()
        return v
else:  # pragma: no cover - plain-Python mode
    def store_release(arr, idx, value):
        arr[idx] = value

    def load_acquire(arr, idx):
        return arr[idx]


def warm_up() -> None:
    """Compile (or load the cached code) now, so the first cycle does not pay for it."""
    a = np.zeros(1, dtype=np.int64)
    store_release(a, 0, 1)
    load_acquire(a, 0)
