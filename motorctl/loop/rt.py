"""Real-time set-up of the loop process, verified and reported, never silently skipped.

Steps (each reported as obtained / refused with the reason):
  * SCHED_FIFO at the configured priority (verified with sched_getscheduler afterwards: the
    RT_GROUP_SCHED trap, LinuxCNC#2821, makes the call "succeed" into nothing on some systems);
  * mlockall through libc: with ``lock_pages: touched`` (the default) MCL_CURRENT | MCL_FUTURE |
    MCL_ONFAULT (Linux ≥ 4.4), which locks the pages resident when the loop starts (the
    interpreter, the compiled cycle run once in warm-up, the record buffers written once when
    they are made) and every page touched later, so the locked memory is what the loop uses;
    with ``all`` MCL_CURRENT | MCL_FUTURE, which reads in and locks every mapped page of every
    library loaded (numba's LLVM alone maps 180 MB: about 0.6 GB for the main job). A kernel
    that refuses MCL_ONFAULT gets ``all``, and the report says so;
  * CPU affinity (the configured CPU, else the highest CPU in /sys/devices/system/cpu/isolated);
  * timer slack 1 ns (prctl PR_SET_TIMERSLACK; the kernel ignores slack under SCHED_FIFO);
  * a CPU wake-up latency request to the kernel's PM QoS (``cpu_latency_us``, default 0): the
    value written to /dev/cpu_dma_latency, held open for the run (the kernel's
    Documentation/power/pm_qos_interface.rst; rt-tests' cyclictest does the same). With 0 the
    idle CPUs poll instead of entering a sleep state, so the loop's wake-up does not wait for a
    CPU to leave one (on a virtual machine, for the hypervisor to schedule a halted vCPU back):
    every CPU then runs at full power while the loop runs. The kernel drops the request when
    the file is closed, by :func:`restore` or by the process's end, whatever ends it;
  * gc.collect(); gc.freeze(); gc.disable() so no collection runs inside the loop;
  * with ``lock_pages: touched``, the prefault: every resident page of the process's private
    writable mappings written once (madvise MADV_POPULATE_WRITE, Linux ≥ 5.14), as the RT
    HOWTO prefaults after mlockall. The set-up runs after the loop's helper process (the
    run's drain, the daemon's I/O process) is forked, and after a fork every such page is
    shared copy-on-write with the child: without the prefault the loop's first write to each
    page it shares faults and copies it inside a cycle (about 100 faults in the first cycle,
    100-350 µs, and tens more through the first seconds, on the 2-core VM). With ``all``,
    mlockall's own population writes those pages already.

With ``policy: required`` a refused SCHED_FIFO or mlockall raises :class:`RealtimeError`
before anything starts.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import mmap
import os
import struct
import time
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from motorctl.schema import StrictModel

MCL_CURRENT = 1
MCL_FUTURE = 2
MCL_ONFAULT = 4
PR_SET_TIMERSLACK = 29
#: madvise(2): populate (prefault) page tables writable, breaking copy-on-write (Linux ≥ 5.14)
MADV_POPULATE_WRITE = 23
#: pages per mincore(2) call of the prefault
_MINCORE_CHUNK = 1 << 14
#: the CPUs the process had before setup_realtime pinned it (restore puts them back)
_saved_affinity: list = []
#: the open /dev/cpu_dma_latency holding the PM QoS request (restore closes it)
_latency_fd: list = []
CPU_DMA_LATENCY = "/dev/cpu_dma_latency"


class RealtimeError(RuntimeError):
    """``realtime: required`` and a step was refused."""


@dataclass
class RealtimeReport:
    """What the set-up obtained: step name → (obtained, detail)."""

    steps: dict = field(default_factory=dict)

    def ok(self, name: str) -> bool:
        return self.steps.get(name, (False, ""))[0]

    def summary(self) -> str:
        return "; ".join(f"{k}: {'yes' if ok else 'NO'} ({d})" for k, (ok, d) in self.steps.items())

    def as_dict(self) -> dict:
        return {k: {"obtained": ok, "detail": d} for k, (ok, d) in self.steps.items()}


def _libc():
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def _isolated_cpu() -> int | None:
    try:
        with open("/sys/devices/system/cpu/isolated") as fh:
            text = fh.read().strip()
    except OSError:
        return None
    cpus = []
    for part in filter(None, text.split(",")):
        a, _, b = part.partition("-")
        cpus += list(range(int(a), int(b or a) + 1))
    return max(cpus) if cpus else None


def _lock(lock_pages: str) -> tuple[bool, str]:
    libc = _libc()
    note = ""
    if lock_pages == "touched":
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0:
            return True, "pages in use and every page touched later locked (MCL_ONFAULT)"
        note = f"; MCL_ONFAULT refused ({os.strerror(ctypes.get_errno())}), so every mapped page"
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
        return True, "current and future pages locked" + note
    return False, f"refused: {os.strerror(ctypes.get_errno())}"


def _prefault() -> tuple[bool, str]:
    """Write-fault every resident page of the private writable mappings of /proc/self/maps
    (mincore(2) for the resident ones, madvise(2) MADV_POPULATE_WRITE on each run of them):
    no copy-on-write or first-touch fault is left for the loop on what it has touched (module
    docstring). Mappings that vanish meanwhile are skipped; the kernel's refusal of the advice
    everywhere (before 5.14: EINVAL) is reported."""
    libc = _libc()
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    page = mmap.PAGESIZE
    t0 = time.monotonic()
    try:
        with open("/proc/self/maps") as f:
            spans = [tuple(int(a, 16) for a in fields[0].split("-"))
                     for fields in (line.split() for line in f) if fields[1] == "rw-p"]
    except OSError as exc:
        return False, f"/proc/self/maps: {exc.strerror}"
    vec = np.zeros(_MINCORE_CHUNK + 2, dtype=np.uint8)    # resident flags between two zeros
    pages, refused = 0, 0
    for lo, hi in spans:
        for start in range(lo, hi, _MINCORE_CHUNK * page):
            n = min(_MINCORE_CHUNK, (hi - start) // page)
            if libc.mincore(start, n * page, vec[1:].ctypes.data) != 0:
                break                                      # unmapped since the maps were read
            vec[n + 1] = 0
            edges = np.flatnonzero(np.diff(vec[:n + 2] & 1))
            for a, b in zip(edges[::2], edges[1::2]):
                if libc.madvise(start + int(a) * page, int(b - a) * page, MADV_POPULATE_WRITE) == 0:
                    pages += int(b - a)
                else:
                    refused = ctypes.get_errno()
    if pages == 0 and refused:                             # EINVAL before Linux 5.14
        return False, f"MADV_POPULATE_WRITE refused: {os.strerror(refused)}"
    return True, (f"{pages} pages ({pages * page / 2**20:.1f} MiB) written in {(time.monotonic() - t0) * 1e3:.0f} ms "
                  "before the first cycle")


def _request_cpu_latency(latency_us: int) -> tuple[bool, str]:
    """Hold a PM QoS CPU latency request of ``latency_us`` [µs] (module docstring)."""
    if _latency_fd:
        os.close(_latency_fd.pop())
    try:
        fd = os.open(CPU_DMA_LATENCY, os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        return False, f"{CPU_DMA_LATENCY}: {exc.strerror}"
    try:
        os.write(fd, struct.pack("=i", latency_us))
    except OSError as exc:
        os.close(fd)
        return False, f"{CPU_DMA_LATENCY}: {exc.strerror}"
    _latency_fd.append(fd)
    return True, f"{latency_us} us held through {CPU_DMA_LATENCY}"


def setup_realtime(policy: str = "best_effort", priority: int = 80, cpu: int | None = None,
                   lock_memory: bool = True, lock_pages: str = "touched",
                   cpu_latency_us: int | None = None) -> RealtimeReport:
    """Apply the real-time set-up to the calling process (see module docstring).

    Args:
        policy: 'off' (only gc freeze), 'best_effort' (report refusals), 'required' (raise).
        priority: SCHED_FIFO priority 1..99. cpu: CPU to pin to, or None.
        lock_memory: call mlockall. lock_pages: 'touched' (MCL_ONFAULT) or 'all' (module
            docstring). cpu_latency_us: the PM QoS CPU latency to hold [µs], ≥ 0, or None
            (no request); a refusal is reported, never raised.
    Returns:
        The report. Raises RealtimeError when policy is 'required' and FIFO or mlock is refused.
    """
    rep = RealtimeReport()
    if policy == "off":
        rep.steps["sched_fifo"] = (False, "not requested (policy off)")
    else:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            got = os.sched_getscheduler(0)
            if got == os.SCHED_FIFO:
                rep.steps["sched_fifo"] = (True, f"priority {os.sched_getparam(0).sched_priority}")
            else:
                rep.steps["sched_fifo"] = (False, f"call returned but policy is {got}")
        except OSError as exc:
            rep.steps["sched_fifo"] = (False, f"refused: {exc.strerror}")
        if lock_memory:
            rep.steps["mlockall"] = _lock(lock_pages)
        else:
            rep.steps["mlockall"] = (False, "not requested")
        target = loop_cpu(cpu)
        if target is not None:
            try:
                if not _saved_affinity:
                    _saved_affinity.append(os.sched_getaffinity(0))
                os.sched_setaffinity(0, {target})
                rep.steps["affinity"] = (True, f"cpu {target}")
            except OSError as exc:
                rep.steps["affinity"] = (False, f"cpu {target} refused: {exc.strerror}")
        else:
            rep.steps["affinity"] = (False, "no cpu configured and none isolated")
        try:
            libc = _libc()
            ok = libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(1), 0, 0, 0) == 0
            rep.steps["timer_slack"] = (ok, "1 ns" if ok else os.strerror(ctypes.get_errno()))
        except (OSError, AttributeError) as exc:
            rep.steps["timer_slack"] = (False, str(exc))
        if cpu_latency_us is not None:
            rep.steps["cpu_latency"] = _request_cpu_latency(int(cpu_latency_us))
    gc.collect()
    gc.freeze()
    gc.disable()
    rep.steps["gc"] = (True, "collected, frozen, disabled")
    if lock_pages == "touched" and rep.ok("mlockall"):     # obtained: policy on, memory locked
        rep.steps["prefault"] = _prefault()
    if policy == "required":
        missing = [k for k in ("sched_fifo", "mlockall") if not rep.ok(k) and (k != "mlockall" or lock_memory)]
        if missing:
            restore()
            raise RealtimeError("realtime: required, but refused: "
                                + "; ".join(f"{k} ({rep.steps[k][1]})" for k in missing))
    return rep


def restore() -> None:
    """Undo the set-up (back to SCHED_OTHER on the CPUs the process had before, the CPU
    latency request dropped, gc enabled); used after a run."""
    _sched_other()
    while _latency_fd:
        try:
            os.close(_latency_fd.pop())
        except OSError:
            pass
    if _saved_affinity:
        try:
            os.sched_setaffinity(0, _saved_affinity[0])
        except OSError:
            pass
        _saved_affinity.clear()
    gc.enable()
    gc.unfreeze()


def _sched_other() -> None:
    """Back to SCHED_OTHER (a refusal is ignored)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass


def loop_cpu(cpu: int | None) -> int | None:
    """The CPU the loop is pinned to: ``cpu`` when configured, else the highest CPU in
    /sys/devices/system/cpu/isolated, else None (not pinned)."""
    return cpu if cpu is not None else _isolated_cpu()


def keep_off(cpu: int | None) -> None:
    """For a helper process of the loop (a child that drains its records): SCHED_OTHER, and
    every CPU it may use but the loop's ``cpu`` when another remains, so that it neither takes
    the loop's CPU between cycles nor empties its caches. Refusals are ignored (the helper
    then runs where it was)."""
    _sched_other()
    if cpu is None:
        return
    try:
        allowed = (os.sched_getaffinity(0) | set(range(os.cpu_count() or 1))) - {cpu}
        if allowed:
            os.sched_setaffinity(0, allowed)
    except OSError:
        pass


class RealtimeConfig(StrictModel):
    """Real-time set-up of the loop process (reported either way; ``required`` refuses to start)."""

    policy: Literal["off", "best_effort", "required"] = "best_effort"
    priority: Annotated[int, Field(ge=1, le=99)] = 80
    cpu: Annotated[int, Field(ge=0)] | None = None
    lock_memory: bool = True
    lock_pages: Literal["touched", "all"] = "touched"
    spin_us: Annotated[float, Field(ge=0, le=1000)] = 60.0
    #: rehearse the next cycle on copies in the spin tail, so that it finds its code and data
    #: in the CPU's caches (:class:`motorctl.loop.servo.ServoLoop`, ``warm_caches``)
    warm_caches: bool = True
    #: the CPU wake-up latency [µs] requested from the kernel's PM QoS while the loop runs
    #: (/dev/cpu_dma_latency; 0: idle CPUs poll, no sleep state); null: no request
    cpu_latency_us: Annotated[int, Field(ge=0, le=2_000_000_000)] | None = 0
